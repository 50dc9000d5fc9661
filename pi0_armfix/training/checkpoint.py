"""Orbax checkpoints of a run: train state, data iterator, norm stats and config, per step.

  <workdir>/checkpoints/<step>/state       TrainState (params, optimizer, EMA, loss-balancer state)
                              /data        the data iterator's state (`get_state()`, JSON): the
                                           pipeline's sample order is a pure function of the step
                              /norm_stats  the run's normalization stats (openpi format)
                              /config      the run's config

Orbax writes a step into a temporary folder and renames it into place only when every item of every
process is written (its atomic finalize), so a run killed mid-save leaves the previous step as the
latest one; the temporary folder is ignored on restore and removed by the next save.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import jax
import ml_collections
import orbax.checkpoint as ocp
from etils import epath

from pi0_armfix.training import sharding as sharding_lib


def has_checkpoints(directory: epath.PathLike) -> bool:
    """Whether `directory` (`<workdir>/checkpoints`) holds a finished checkpoint (a step folder),
    without creating anything."""
    directory = epath.Path(directory)
    return directory.is_dir() and any(p.name.isdigit() for p in directory.iterdir())


class Checkpoints:
    """The checkpoints of one run folder.

    Args:
      directory: `<workdir>/checkpoints`.
      every: a save is kept every `every` steps (the final step is always saved with force=True).
      keep: how many of the latest checkpoints are kept (older ones are deleted).
    """

    def __init__(self, directory: epath.PathLike, *, every: int = 1, keep: int | None = None,
                 read_only: bool = False):
        if every <= 0:
            raise ValueError(f"train.checkpoint_every = {every} must be positive")
        if keep is not None and keep <= 0:
            raise ValueError(f"train.keep_checkpoints = {keep} must be positive")
        self.directory = epath.Path(directory).absolute()  # orbax wants absolute paths
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=ocp.CheckpointManagerOptions(
                save_interval_steps=every, max_to_keep=keep, create=not read_only,
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
        return list(self._manager.all_steps())

    def save(self, step: int, state: Any, data_state: Mapping[str, Any],
             norm_stats: Mapping[str, Any], config: ml_collections.ConfigDict, *,
             force: bool = False) -> bool:
        """Starts an asynchronous save of `step`; True if one was started (see `every`)."""
        return self._manager.save(step, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state),
            data=ocp.args.JsonSave(dict(data_state)),
            norm_stats=ocp.args.JsonSave(dict(norm_stats)),
            config=ocp.args.JsonSave(json.loads(config.to_json_best_effort())),
        ), force=force)

    def restore(self, step: int, abstract_state: Any) -> tuple[Any, dict[str, Any]]:
        """The state of `step`, in the shardings of `abstract_state` (a tree of
        ShapeDtypeStructs), and the data iterator's state. Returns `(state, data_state)`."""
        try:
            restored = self._manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract_state),
                data=ocp.args.JsonRestore(),
            ))
        except (ValueError, KeyError, TypeError) as e:
            raise ValueError(f"checkpoint {self.directory / str(step)} does not match this run "
                             f"(different model, loss strategy or process count?): {e}") from e
        return restored["state"], restored["data"]

    def restore_for_eval(self, step: int, mesh: jax.sharding.Mesh
                         ) -> tuple[dict[str, Any], dict[str, Any], ml_collections.ConfigDict]:
        """The saved state tree (as nested dicts, sharded by the rule table on `mesh`), norm stats
        and config of `step`, without a run's model or data to build a target from."""
        metadata = self._manager.item_metadata(step)["state"]
        abstract = jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype), metadata)
        abstract = jax.tree.map(
            lambda x, s: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s),
            abstract, sharding_lib.tree_shardings(abstract, mesh))
        restored = self._manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract),
            norm_stats=ocp.args.JsonRestore(),
            config=ocp.args.JsonRestore(),
        ))
        return (restored["state"], restored["norm_stats"],
                ml_collections.ConfigDict(restored["config"]))

    def wait(self) -> None:
        """Blocks until the pending asynchronous save is finalized."""
        self._manager.wait_until_finished()

    def close(self) -> None:
        self._manager.close()
