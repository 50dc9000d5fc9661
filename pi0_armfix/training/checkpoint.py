"""Orbax checkpoints of a run: train state, data iterator, norm stats and config, per step.

  <workdir>/checkpoints/<step>/state       TrainState (params, optimizer, EMA, loss-balancer state)
                              /data        the data iterator's state (`get_state()`, JSON): the
                                           pipeline's sample order is a pure function of the step
                              /norm_stats  the run's normalization stats (openpi format)
                              /config      the run's config
  <workdir>/checkpoints.<reason>/<step>/   a checkpoint set aside, never deleted: `nonfinite` (the
                                           step after it was NaN/inf), `damaged` (unreadable)

Orbax writes a step into a temporary folder and renames it into place only when every item of every
process is written (its atomic finalize), so a run killed mid-save leaves the previous step as the
latest one; the temporary folder is ignored on restore and removed by the next save.

A checkpoint is *confirmed* once the step computed from it had a finite loss and gradient (its
params can be finite and still overflow the next forward pass). Retention counts only confirmed
checkpoints: the newest `keep` confirmed ones and every newer one stay, so the last checkpoint a
run can go on from is never deleted. An unconfirmed latest checkpoint (a run killed right after
saving it) is confirmed or set aside by the first step of the resumed run.
"""

from __future__ import annotations

import contextlib
import errno
import shutil
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import ml_collections
import orbax.checkpoint as ocp
from etils import epath
from jax.experimental import multihost_utils

from pi0_armfix import sharding as sharding_lib


def has_checkpoints(directory: epath.PathLike) -> bool:
    """Whether `directory` (`<workdir>/checkpoints`) holds a finished checkpoint (a step folder),
    without creating anything."""
    directory = epath.Path(directory)
    return directory.is_dir() and any(p.name.isdigit() for p in directory.iterdir())


def _leaf_shapes(tree: Any) -> dict[str, tuple[int, ...]]:
    """`{"params/a/b": shape}` of the array leaves of a state tree or of its orbax metadata (a
    dataclass's fields and a dict's keys name a level alike)."""
    def name(key) -> str:
        for attr in ("name", "key", "idx"):
            if hasattr(key, attr):
                return str(getattr(key, attr))
        return str(key)

    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {"/".join(name(k) for k in path): tuple(leaf.shape) for path, leaf in leaves
            if hasattr(leaf, "shape")}


def _size(num_bytes: int) -> str:
    if num_bytes < 1024:
        return f"{num_bytes} B"
    size, unit = num_bytes / 1024, "KiB"
    for bigger in ("MiB", "GiB"):
        if size < 1024:
            break
        size, unit = size / 1024, bigger
    return f"{size:.1f} {unit}"


def first_line(error: BaseException) -> str:
    """`Type: the first line of its message` (at most 200 characters): storage errors run to
    kilobytes of spec dumps."""
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0][:200] if text else ''}"


def drop_restore_noise() -> None:
    """Silences the echoes of an orbax restore that failed on a damaged file, which the failure
    itself reports in one line: the "Event loop is closed" that tensorstore's late callbacks raise
    (through sys.excepthook or sys.unraisablehook, from its threads), and the "Exception ignored
    in: <coroutine ...>" of every array read the failed restore left unawaited (thousands of
    lines on exit, one traceback per array)."""
    if getattr(sys.excepthook, "drops_restore_noise", False):
        return

    def is_noise(error: BaseException | None) -> bool:
        text = str(error)
        return ((isinstance(error, RuntimeError) and "Event loop is closed" in text)
                or "Encountered error while reading array index" in text)

    excepthook, unraisablehook = sys.excepthook, sys.unraisablehook

    def quiet_excepthook(kind, error, trace):
        if not is_noise(error):
            excepthook(kind, error, trace)

    def quiet_unraisablehook(unraisable):
        if not is_noise(unraisable.exc_value):
            unraisablehook(unraisable)

    quiet_excepthook.drops_restore_noise = True
    sys.excepthook, sys.unraisablehook = quiet_excepthook, quiet_unraisablehook


EVAL_ITEMS = ("params", "ema_params")  # what an evaluation restores of a train state


class Checkpoints:
    """The checkpoints of one run folder.

    Args:
      directory: `<workdir>/checkpoints`.
      every: a save is kept every `every` steps (the final step is always saved with force=True).
      keep: how many confirmed checkpoints are kept (older ones are deleted); None keeps all.
    """

    def __init__(self, directory: epath.PathLike, *, every: int = 1, keep: int | None = None,
                 read_only: bool = False):
        if every <= 0:
            raise ValueError(f"train.checkpoint_every = {every} must be positive")
        if keep is not None and keep <= 0:
            raise ValueError(f"train.keep_checkpoints = {keep} must be positive")
        self.directory = epath.Path(directory).absolute()  # orbax wants absolute paths
        drop_restore_noise()  # before any read: a damaged file echoes from the first one
        self._keep = None if read_only else keep
        self._confirmed: int | None = None  # the newest step known to be good
        self._saving: int | None = None  # the step of the save in flight
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                save_interval_steps=every, max_to_keep=None, create=not read_only,
                read_only=read_only, cleanup_tmp_directories=not read_only),
            item_handlers={
                "state": ocp.StandardCheckpointHandler(),
                "data": ocp.JsonCheckpointHandler(),
                "norm_stats": ocp.JsonCheckpointHandler(),
                "config": ocp.JsonCheckpointHandler(),
            })

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def save(self, step: int, state: Any, data_state: Mapping[str, Any],
             norm_stats: Mapping[str, Any], config_json: Mapping[str, Any], *,
             force: bool = False) -> bool:
        """Starts an asynchronous save of `step` (after the previous save is finished and the
        checkpoints retention drops are deleted); True if one was started (see `every`).
        `config_json`: the run's config as JSON values (`ConfigDict.to_json_best_effort`).

        Raises:
          SaveError: the previous save failed, or the disk has less room than `state` needs.
        """
        if not (force or self._manager.should_save(step)):
            return False
        self.wait()
        self._prune()
        needed = sum(x.nbytes for x in jax.tree.leaves(state) if hasattr(x, "nbytes"))
        free = shutil.disk_usage(self.directory).free
        if free < needed:
            raise SaveError(f"checkpoint {step} needs about {_size(needed)} but "
                            f"{self.directory} has {_size(free)} free: free space on "
                            f"that disk, then rerun to resume from checkpoint "
                            f"{self.latest_step() or '(none: step 0)'}")
        self._saving = step
        with self._errors_as_save_errors():
            return self._manager.save(step, args=ocp.args.Composite(
                state=ocp.args.StandardSave(state),
                data=ocp.args.JsonSave(dict(data_state)),
                norm_stats=ocp.args.JsonSave(dict(norm_stats)),
                config=ocp.args.JsonSave(dict(config_json)),
            ), force=force)

    def check_for_errors(self) -> None:
        """Raises SaveError if the asynchronous save in flight has failed (a full disk shows at
        the step it happens, not one save later)."""
        with self._errors_as_save_errors():
            self._manager.check_for_errors()

    @contextlib.contextmanager
    def _errors_as_save_errors(self):
        try:
            yield
        except Exception as e:  # noqa: BLE001 - tensorstore, os and orbax errors alike
            step, self._saving = self._saving, None
            full = "No space left" in str(e) or getattr(e, "errno", None) == errno.ENOSPC
            fix = ("the disk is full: free space on it" if full
                   else "fix the file system")
            raise SaveError(
                f"checkpoint {step} could not be written in {self.directory} ({first_line(e)}): "
                f"{fix}, then rerun to resume from the last complete checkpoint "
                f"({self.latest_step() or 'none: step 0'})") from e

    def confirm(self, step: int) -> None:
        """Marks `step` good: the step computed from it was finite. Older checkpoints beyond
        `keep` are deleted at the next save or close."""
        self._confirmed = max(step, self._confirmed or 0)

    def set_aside(self, step: int, reason: str) -> epath.Path:
        """Moves checkpoint `step` (after its save is finished) to `checkpoints.<reason>/<step>`,
        where neither a restore nor retention sees it; returns the new path."""
        self.wait()
        destination = self.directory.parent / f"{self.directory.name}.{reason}" / str(step)
        if jax.process_index() == 0:
            destination.parent.mkdir(parents=True, exist_ok=True)
            if destination.exists():  # set aside before, by an earlier attempt of the same run
                destination = destination.parent / f"{step}.{len(list(destination.parent.iterdir()))}"
            (self.directory / str(step)).rename(destination)
        if jax.process_count() > 1:
            multihost_utils.sync_global_devices(f"checkpoint set aside {step}")
        self._manager.reload()
        return destination

    def _prune(self) -> None:
        if self._keep is None or self._confirmed is None:
            return
        confirmed = [s for s in self.all_steps() if s <= self._confirmed]
        for step in confirmed[:-self._keep]:
            self._manager.delete(step)

    def check_matches(self, step: int, abstract_state: Any) -> None:
        """Raises ValueError naming the differing arrays when checkpoint `step` holds another
        state tree than `abstract_state` (another model, loss strategy, EMA setting); an
        unreadable description is left for the restore to report as damage."""
        try:
            metadata = self._manager.item_metadata(step)["state"]
        except Exception:  # noqa: BLE001 - damaged: the restore says so
            return
        if metadata is None:
            return
        saved, expected = _leaf_shapes(metadata), _leaf_shapes(abstract_state)
        if saved == expected:
            return
        differing = [f"{k}: saved {saved.get(k, 'absent')}, this run {expected.get(k, 'absent')}"
                     for k in sorted(set(saved) | set(expected)) if saved.get(k) != expected.get(k)]
        raise ValueError(
            f"checkpoint {self.directory / str(step)} holds another train state than this run "
            f"builds ({len(differing)} arrays differ: {'; '.join(differing[:4])}"
            f"{'; ...' if len(differing) > 4 else ''}): the model, loss strategy or optim."
            "ema_decay differs from the run's; resume with its config or use another --workdir")

    def restore(self, step: int, abstract_state: Any) -> tuple[Any, dict[str, Any]]:
        """The state of `step`, in the shardings of `abstract_state` (a tree of
        ShapeDtypeStructs), and the data iterator's state. Returns `(state, data_state)`.

        Raises:
          ValueError: the checkpoint holds another state tree (`check_matches`).
          DamagedCheckpointError: a file of the checkpoint is missing or unreadable.
        """
        self.check_matches(step, abstract_state)
        try:
            restored = self._manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract_state),
                data=ocp.args.JsonRestore(),
            ))
        except Exception as e:  # noqa: BLE001 - tensorstore, json and os errors alike
            raise DamagedCheckpointError(self.directory / str(step), e) from e
        return restored["state"], restored["data"]

    def restore_latest(self, abstract_state: Any, say=print
                       ) -> tuple[int, Any, dict[str, Any]] | None:
        """The newest checkpoint that restores: `(step, state, data_state)`, or None when there
        is none. Damaged newer checkpoints are reported with `say` and set aside to
        `checkpoints.damaged/` once an older one has restored.

        Raises:
          ValueError: every checkpoint is damaged (nothing is moved), or holds another state.
        """
        damaged: list[DamagedCheckpointError] = []
        for step in reversed(self.all_steps()):
            try:
                state, data_state = self.restore(step, abstract_state)
            except DamagedCheckpointError as e:
                damaged.append(e)
                continue
            for error in damaged:
                moved = self.set_aside(int(error.path.name), "damaged")
                say(f"warning: {error}: moved it to {moved}; resuming from step {step} instead")
            return step, state, data_state
        if damaged:
            raise ValueError(f"no checkpoint in {self.directory} can be read: "
                             + "; ".join(str(e) for e in damaged)
                             + ". Restore the files, or start over with --config.train.resume=new")
        return None

    def restore_for_eval(self, step: int, mesh: jax.sharding.Mesh,
                         items: Sequence[str] | None = EVAL_ITEMS
                         ) -> tuple[dict[str, Any], dict[str, Any], ml_collections.ConfigDict]:
        """The `items` of the train state of `step` (default: the params, and the EMA params when
        kept; None: all of it) as nested dicts sharded by the rule table on `mesh`, its norm stats and config,
        without a run's model or data to build a target from, and without the optimizer state
        an evaluation never uses.

        Raises:
          DamagedCheckpointError: a file of the checkpoint is missing or unreadable.
        """
        try:
            # The state item read as a plain PyTree (the format the train state is saved in),
            # so that only the params are restored.
            reader = ocp.CheckpointManager(
                self.directory, options=ocp.CheckpointManagerOptions(read_only=True,
                                                                     create=False),
                item_handlers={"state": ocp.PyTreeCheckpointHandler(),
                               "norm_stats": ocp.JsonCheckpointHandler(),
                               "config": ocp.JsonCheckpointHandler()})
            metadata = reader.item_metadata(step)["state"]
            wanted = {k: metadata[k] for k in (metadata if items is None else items)
                      if k in metadata and metadata[k]}
            abstract = jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype), wanted)
            abstract = jax.tree.map(
                lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
                abstract, sharding_lib.tree_shardings(abstract, mesh))
            restored = reader.restore(step, args=ocp.args.Composite(
                state=ocp.args.PyTreeRestore(
                    abstract, restore_args=ocp.checkpoint_utils.construct_restore_args(abstract),
                    partial_restore=True),
                norm_stats=ocp.args.JsonRestore(),
                config=ocp.args.JsonRestore(),
            ))
        except Exception as e:  # noqa: BLE001 - tensorstore, json and os errors alike
            raise DamagedCheckpointError(self.directory / str(step), e) from e
        return (restored["state"], restored["norm_stats"],
                ml_collections.ConfigDict(restored["config"]))

    def wait(self) -> None:
        """Blocks until the pending asynchronous save is finalized.

        Raises:
          SaveError: it failed.
        """
        with self._errors_as_save_errors():
            self._manager.wait_until_finished()
        self._saving = None

    def close(self) -> None:
        """Waits for the pending save, deletes what retention drops, closes the manager (also
        when the save failed: the error is raised after)."""
        try:
            self.wait()
            self._prune()
        finally:
            with contextlib.suppress(Exception):  # its failed save was reported by wait()
                self._manager.close()


class SaveError(RuntimeError):
    """A checkpoint could not be written (disk full, file system error); the last complete one is
    intact."""


class DamagedCheckpointError(ValueError):
    """A checkpoint whose files are missing or unreadable (a disk error, a deleted file)."""

    def __init__(self, path: epath.Path, error: BaseException):
        super().__init__(f"checkpoint {path} is damaged ({first_line(error)})")
        self.path = path
