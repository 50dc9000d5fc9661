"""Reading orbax checkpoints and writing/loading the PyTorch mirror's files.

The CLI is `python -m pi0_armfix.torch_mirror.convert --checkpoint=DIR --output=DIR [--step=N] [--ema]`.

`--checkpoint` may be
  * a run of this project (`pi0_armfix/training/checkpoint.py`): the workdir, its `checkpoints/`
    folder (the latest step, or `--step`) or one step folder `<step>/` holding the orbax items
    `state` (a TrainState: only `params`, or `ema_params` with `--ema`, is read), `config` (the
    run's config; its `model` section gives the model config) and `norm_stats`;
  * an openpi checkpoint (a released one such as pi0_base, or a step of an openpi run): a folder
    holding `params/` (an orbax PyTree `{"params": ...}`; NNX's trailing "value" keys are dropped)
    and `assets/<asset_id>/norm_stats.json`, or that `params/` folder itself. It carries no model config: `--preset` (default pi0)
    and `--action_horizon` say which one.

The output folder gets
  model.safetensors  float32 tensors under the mirror's names (`params.py`: openpi name with
                     "/" -> ".", depth axes stacked, flax layouts), exactly `Pi0(config).state_dict()`;
  config.json        `Pi0Config.to_dict()`;
  norm_stats.json    the checkpoint's normalization stats in openpi's format, when it has any.
LoRA adapters (a run with `model.lora`, or its openpi export) are folded into their weights
(`gemma.merge_lora`): the mirror holds the plain tree, and its config no adapters.
Parameters are checked strictly against the config before anything is written: a missing,
unexpected or mis-shaped name is a ValueError listing all of them. Only safetensors and JSON are
read and written (no pickle). `load_converted(dir)` loads the result back.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
import tqdm
from etils import epath
from safetensors.torch import load_file, save_file

from pi0_armfix.model import gemma
from pi0_armfix.model.config import Pi0Config, from_model_config, get_preset
from pi0_armfix.torch_mirror.model import Pi0
from pi0_armfix.model.tree import flatten_tree
from pi0_armfix.torch_mirror.params import check_state_dict, param_shapes, torch_name

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
NORM_STATS_FILE = "norm_stats.json"


class CheckpointError(ValueError):
    """A checkpoint folder that cannot be converted (not found, not a checkpoint, incomplete)."""


# ----------------------------------------------------------------------------------- reading


def _step_dirs(directory: epath.Path) -> dict[int, epath.Path]:
    """Finalized step folders of a CheckpointManager directory (`<step>/state`)."""
    return {int(p.name): p for p in directory.iterdir()
            if p.is_dir() and p.name.isdigit() and (p / "state").exists()}


def locate(checkpoint: str, step: int | None = None, say=lambda message: None
           ) -> tuple[str, epath.Path]:
    """Resolves `checkpoint` to ("run", step folder) or ("openpi", folder holding `params/`).
    `say` is told when newer step folders than the latest complete one were passed over."""
    path = epath.Path(checkpoint)
    if not path.is_dir():
        raise CheckpointError(f"checkpoint folder {path} does not exist")
    if (path / "params").is_dir():
        return "openpi", path
    if path.name == "params" and (path / "_METADATA").exists():  # openpi's own restore_params path
        return "openpi", path.parent
    if (path / "state").is_dir():
        return "run", path
    manager_dir = path / "checkpoints" if (path / "checkpoints").is_dir() else path
    steps = _step_dirs(manager_dir)
    if not steps:
        raise CheckpointError(
            f"{path} is not a checkpoint: expected a run step folder (with state/), a run's "
            f"checkpoints/ folder, a run workdir, or an openpi checkpoint (with params/)")
    if step is None:
        latest = max(steps)
        passed_over = sorted(p.name for p in manager_dir.iterdir() if p.is_dir()
                             and p.name.split(".")[0].isdigit()
                             and int(p.name.split(".")[0]) > latest)
        if passed_over:
            say(f"note: {manager_dir} holds incomplete newer step folder(s) {passed_over} (a "
                f"save cut short, or a deleted state/): converting step {latest}, the latest "
                "complete one")
        return "run", steps[latest]
    if step not in steps:
        raise CheckpointError(f"step {step} not in {manager_dir}; saved steps: {sorted(steps)}")
    return "run", steps[step]


def _restore_arrays(item_dir: epath.Path, subtree: Sequence[str]) -> dict[str, np.ndarray]:
    """The leaves under key path `subtree` of an orbax PyTree item, as {"a/b/c": float32 array}.

    Leaves are read one at a time (partial restore) so that nothing else in the item (optimizer
    state) is loaded, with a progress bar.
    """
    # Imported here so that `load_converted` (deployment) needs neither JAX nor orbax.
    import jax
    import orbax.checkpoint as ocp

    from pi0_armfix.training.checkpoint import drop_restore_noise

    drop_restore_noise()  # a damaged file echoes from tensorstore's threads
    handler = ocp.PyTreeCheckpointHandler()
    try:
        tree = handler.metadata(item_dir).tree
    except Exception as e:  # noqa: BLE001 - orbax raises many kinds for damaged files
        raise _damaged(item_dir, e) from e
    for key in subtree:
        if not isinstance(tree, Mapping) or tree.get(key) is None:
            raise CheckpointError(f"{item_dir} holds no '{'/'.join(subtree)}' tree")
        tree = tree[key]
    leaves = flatten_tree(tree)
    arrays = {}
    for name, meta in tqdm.tqdm(leaves.items(), desc=f"reading {item_dir.name}", unit="array"):
        item: dict[str, Any] = {}
        node = item
        for key in (*subtree, *name.split("/")[:-1]):
            node = node.setdefault(key, {})
        node[name.split("/")[-1]] = meta
        restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), item)
        try:
            restored = handler.restore(item_dir, args=ocp.args.PyTreeRestore(
                item=item, restore_args=restore_args, partial_restore=True))
        except Exception as e:  # noqa: BLE001 - tensorstore reports a damaged file many ways
            raise _damaged(item_dir, e) from e
        for key in (*subtree, *name.split("/")):
            restored = restored[key]
        arrays[name] = np.asarray(restored, dtype=np.float32)
    return arrays


class DamagedCheckpointError(CheckpointError):
    """A step whose files are missing or unreadable."""


def _damaged(item_dir: epath.Path, error: BaseException) -> CheckpointError:
    from pi0_armfix.training.checkpoint import first_line  # see _restore_arrays

    return DamagedCheckpointError(f"{item_dir} cannot be read ({first_line(error)}): the "
                                  "checkpoint is damaged; convert an earlier step with --step")


def _read_json_item(item_dir: epath.Path) -> Any:
    import orbax.checkpoint as ocp  # see _restore_arrays

    return ocp.JsonCheckpointHandler().restore(item_dir)


def _openpi_norm_stats(folder: epath.Path) -> dict[str, Any] | None:
    found = sorted(folder.glob("assets/*/norm_stats.json"))
    if len(found) > 1:
        raise CheckpointError(f"{folder} holds several norm stats {[str(p) for p in found]}; "
                              "pass --norm_stats=FILE to choose one")
    return json.loads(found[0].read_text()) if found else None


def _as_openpi_norm_stats(stats: Mapping[str, Any], source: str) -> dict[str, Any]:
    """`{"norm_stats": {...}}` (openpi's file format) from either that or its inner dict."""
    stats = dict(stats)
    if "norm_stats" not in stats:
        stats = {"norm_stats": stats}
    if not isinstance(stats["norm_stats"], Mapping):
        raise CheckpointError(f"norm stats in {source} are not an openpi norm_stats dict")
    return stats


def _read_run_step(folder: epath.Path, ema: bool, preset: str, action_horizon: int
                   ) -> tuple[dict[str, np.ndarray], Pi0Config, Any]:
    """The params, model config and norm stats of a run's step folder."""
    run_config = _read_json_item(folder / "config") if (folder / "config").exists() else None
    if not run_config or "model" not in run_config:
        raise CheckpointError(f"{folder / 'config'} is missing or has no 'model' section")
    config = from_model_config(run_config["model"])
    for flag, value, expected in (("preset", preset, run_config["model"].get("preset")),
                                  ("action_horizon", action_horizon, config.action_horizon)):
        if value and value != expected:
            raise CheckpointError(f"--{flag}={value} contradicts the run's config "
                                  f"({flag}={expected}) in {folder / 'config'}")
    arrays = _restore_arrays(folder / "state", ["ema_params" if ema else "params"])
    stats = _read_json_item(folder / "norm_stats") if (folder / "norm_stats").exists() else None
    return arrays, config, stats


def read_checkpoint(checkpoint: str, *, step: int | None = None, ema: bool = False,
                    preset: str = "", action_horizon: int = 0, norm_stats: str = "",
                    say=lambda message: None
                    ) -> tuple[dict[str, np.ndarray], Pi0Config, dict[str, Any] | None]:
    """Reads a run or openpi checkpoint (see the module docstring).

    Args:
      step: the step of a run's checkpoints folder (None = latest).
      ema: read a run's EMA parameters instead of the trained ones.
      preset, action_horizon: the model config of an openpi checkpoint ("" / 0: pi0 and its
        horizon); for a run they must agree with its config when given.
      norm_stats: a norm_stats.json to use instead of the checkpoint's.
      say: gets a line naming the folder read, and what was passed over to get to it.
    Returns:
      ({openpi name: float32 array}, model config, norm stats in openpi format or None).
    """
    kind, folder = locate(checkpoint, step, say)
    if kind == "run":
        # The latest step of a run that reads, as evaluate, serve and export take it; a step
        # asked for (--step, or its own folder) is read or refused.
        asked = step is not None or (epath.Path(checkpoint) / "state").is_dir()
        older = [] if asked else [f for s, f in sorted(_step_dirs(folder.parent).items(),
                                                        reverse=True) if f != folder]
        candidates = [folder, *older]
        for i, candidate in enumerate(candidates):
            say(f"converting {candidate} (a run step)")
            try:
                arrays, config, stats = _read_run_step(candidate, ema, preset, action_horizon)
                break
            except DamagedCheckpointError as e:
                if i == len(candidates) - 1:
                    raise
                say(f"warning: {e}; trying the step before it")
    else:
        say(f"converting {folder} (openpi params)")
        if ema:
            raise CheckpointError(f"--ema: the openpi checkpoint {folder} has no EMA parameters")
        config = get_preset(preset or "pi0")
        if action_horizon:
            config = config.replace(action_horizon=action_horizon)
        arrays = _restore_arrays(folder / "params", ["params"])
        # NNX states saved by openpi's trainer end every path in "value".
        if all(name.endswith("/value") for name in arrays):
            arrays = {name.removesuffix("/value"): value for name, value in arrays.items()}
        stats = _openpi_norm_stats(folder)
    if any(gemma.is_adapter(name.rpartition("/")[2]) for name in arrays):
        arrays = {name: np.asarray(value) for name, value in gemma.merge_lora(arrays).items()}
        config = config.without_lora()
        say("folded the LoRA adapters into their weights")
    if norm_stats:
        stats = json.loads(epath.Path(norm_stats).read_text())
    source = norm_stats or str(folder)
    return arrays, config, None if stats is None else _as_openpi_norm_stats(stats, source)


# ---------------------------------------------------------------------------- writing, loading


def expected_shapes(config: Pi0Config) -> dict[str, tuple[int, ...]]:
    """{torch name: shape} of `Pi0(config).state_dict()`."""
    return {torch_name(name): shape for name, shape in param_shapes(config).items()}


def write_converted(output: str, arrays: Mapping[str, np.ndarray], config: Pi0Config,
                    norm_stats: Mapping[str, Any] | None, *, source: str) -> epath.Path:
    """Checks `arrays` ({openpi name: array}) against `config` strictly, then writes the folder."""
    tensors = {torch_name(name): torch.from_numpy(np.require(value, np.float32, ['C', 'W']))
               for name, value in arrays.items()}
    check_state_dict({k: tuple(v.shape) for k, v in tensors.items()}, expected_shapes(config),
                     source=source)
    out = epath.Path(output)
    out.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(out / MODEL_FILE), metadata={"format": "pt"})
    (out / CONFIG_FILE).write_text(json.dumps(config.to_dict(), indent=2) + "\n")
    if norm_stats is not None:
        (out / NORM_STATS_FILE).write_text(json.dumps(norm_stats, indent=2) + "\n")
    return out


def load_converted(directory: str) -> tuple[Pi0, dict[str, Any] | None]:
    """(the torch model in eval mode, norm stats in openpi format or None) of a converted folder."""
    folder = epath.Path(directory)
    for name in (MODEL_FILE, CONFIG_FILE):
        if not (folder / name).exists():
            raise CheckpointError(f"{folder / name} does not exist (write it with "
                                  "`python -m pi0_armfix.torch_mirror.convert`)")
    config = Pi0Config.from_dict(json.loads((folder / CONFIG_FILE).read_text()))
    state_dict = load_file(str(folder / MODEL_FILE))
    check_state_dict({k: tuple(v.shape) for k, v in state_dict.items()}, expected_shapes(config),
                     source=str(folder / MODEL_FILE))
    model = Pi0(config)
    model.load_state_dict(state_dict, strict=True)
    stats_file = folder / NORM_STATS_FILE
    norm_stats = json.loads(stats_file.read_text()) if stats_file.exists() else None
    return model.eval(), norm_stats
