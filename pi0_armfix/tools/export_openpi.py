"""A trained run -> a checkpoint folder openpi serves: `params/` and `assets/<id>/norm_stats.json`.

    python -m pi0_armfix.tools.export_openpi --checkpoint=RUN[/checkpoints/STEP] --output=DIR \
        [--asset_id=ID] [--noema] [--dtype=float32|bfloat16] [--force]

What it writes (the layout openpi's `create_trained_policy(train_config, DIR)` reads):
  DIR/params/                       an orbax PyTree checkpoint of `{"params": <params>}`, a pure
                                    nested dict under openpi's names (the run's params already
                                    are: `model/pretrained.py` loads openpi's checkpoints by the
                                    same names), no NNX `value` level, `--dtype` leaves.
  DIR/assets/<ID>/norm_stats.json   `{"norm_stats": {"state": ..., "actions": ...}}`, each with
                                    `mean`, `std`, `q01`, `q99` at the run's real widths (openpi
                                    cuts its statistics to the array it normalizes).
  DIR/pi0_armfix_export.json        the run, step, params, preset, transforms, the openpi
                                    config it pairs with, and any caveat written with `--force`.

openpi applies its own train config's transforms, not the run's, so the tool prints the openpi
config the run needs (model, action horizon and dim, normalization, delta mask, the state the
inputs transform must build, the output slice) and refuses, in one line naming the config key, a
run whose policy needs what openpi cannot do: a model size openpi does not build, per-timestep
normalization, correlated sampling noise, a zeroed state, an offline tokenizer. `--force` writes
the export anyway, its caveats in `pi0_armfix_export.json`. Training-only levers (loss weights,
curriculum, K flow samples, state noise or dropout, augmentation) need nothing at inference.
A LoRA run (`model.lora`) keeps its adapters under openpi's names; the pairing names openpi's
`gemma_2b_lora` / `gemma_300m_lora` variants for the adapted experts.

Constant dims (`NormStats.constant`): the run normalizes them to 0 and returns their mean as the
action, whatever the model samples there; openpi's formula would divide by their tiny spread.
Their statistics are written so that openpi's own formula computes the run's map: a state dim
gets a spread of `CONSTANT_STATE_SPREAD` (it normalizes to within 1e-12 of 0; quantiles centred
on the mean), an action dim a spread of 0 (`std = 0`; `q01 = q99 = mean`), so openpi's
un-normalization `y * (0 + 1e-6) + mean` returns the mean to within 1e-6 of the sample. The
export json lists the dims. pi0.5's state enters only its prompt tokens, which the run
computes with openpi's formula as it is: its state statistics are written unchanged.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import orbax.checkpoint as ocp
from absl import app, flags
from etils import epath

from pi0_armfix import console
from pi0_armfix.data import json_files
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import run_inputs
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.evaluation.outputs import writable_folder
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.policies import restore

EXPORT_FILE = "pi0_armfix_export.json"
OPENPI_PRESETS = {"pi0": "pi0", "pi05": "pi05"}  # our preset -> openpi's model of that size
OPENPI_VARIANTS = {"paligemma": "gemma_2b", "action_expert": "gemma_300m"}  # openpi's expert sizes
DTYPES = ("float32", "bfloat16")
CONSTANT_STATE_SPREAD = 1e12  # a constant state dim's exported spread (normalizes to ~0)


def resolve_checkpoint(path: str | Path) -> tuple[Path, int | None]:
    """`RUN` (its latest step) or `RUN/checkpoints/STEP` -> (run folder, step or None)."""
    path = Path(path).expanduser().absolute()
    if path.name.isdigit() and path.parent.name == "checkpoints":
        return path.parent.parent, int(path.name)
    if not (path / "checkpoints").is_dir():
        raise ValueError(f"--checkpoint={path} is neither a run folder (holding checkpoints/) nor "
                         "a step folder of one (RUN/checkpoints/STEP)")
    return path, None


def openpi_problems(run: restore.RestoredRun) -> list[str]:
    """What openpi's policy cannot reproduce of this run, one line each naming the config key."""
    config, model = run.config, run.model_config
    problems = []
    preset = config.model.preset
    if preset not in OPENPI_PRESETS:
        problems.append(f"model.preset = {preset!r}: openpi builds only its full-size pi0 and "
                        "pi0.5 (presets 'pi0', 'pi05'); this run's parameter tree has other "
                        "sizes, which openpi's Pi0Config cannot load")
    if config.data.get("norm_per_timestep"):
        problems.append("data.norm_per_timestep = True: openpi normalizes every chunk position "
                        "with one statistic per dim; this run's actions need one per position")
    if float(config.loss.get("noise_beta", 1.0)) < 1.0:
        problems.append(f"loss.noise_beta = {config.loss.noise_beta}: this run samples from "
                        "correlated noise; openpi's sampler draws independent N(0, I) noise")
    if config.data.get("delta_action_mask") and config.data.get("delta_reference",
                                                                "state") != "state":
        problems.append(f"data.delta_reference = {config.data.delta_reference!r}: this run's "
                        "actions are relative to the previous commanded action; openpi's "
                        "DeltaActions makes them relative to the state")
    if not model.use_state:
        problems.append("model.use_state = False: this run's model sees a zero state; openpi's "
                        "feeds the normalized state")
    if not config.model.get("tokenizer"):
        problems.append("model.tokenizer is empty: this run tokenized its prompts with an "
                        "offline tokenizer built from the dataset's prompts; openpi tokenizes "
                        "with PaliGemma's")
    return problems


def openpi_caveats(run: restore.RestoredRun) -> list[str]:
    """What openpi does differently but the user can set on their side (not refused)."""
    sampling = run.sampling
    caveats = []
    if sampling.gripper_hysteresis:
        caveats.append(f"eval.gripper_hysteresis = {sampling.gripper_hysteresis}: "
                       "openpi serves the raw gripper commands; apply the hysteresis in the "
                       "client")
    if sampling.num_steps != 10:
        caveats.append(f"eval.num_steps = {sampling.num_steps}: openpi samples with 10 Euler "
                       "steps unless create_trained_policy gets sample_kwargs={'num_steps': "
                       f"{sampling.num_steps}}}")
    if sampling.average_draws != 1:
        caveats.append(f"eval.average_draws = {sampling.average_draws}: this run executes the "
                       "mean of that many draws per chunk; openpi executes one draw: call "
                       f"infer {sampling.average_draws} times and average the actions in the "
                       "client (before any gripper hysteresis)")
    if sampling.temperature != 1.0:
        caveats.append(f"eval.temperature = {sampling.temperature:g}: this run starts the flow "
                       "from noise scaled by it; openpi starts from N(0, I): pass "
                       "sample_kwargs={'noise': temperature * noise} to its sample_actions")
    if sampling.group_draws:
        caveats.append(f"eval.group_draws = {sampling.group_draws!r}: this run executes those "
                       "groups as the mean of that many draws; openpi executes one draw: call "
                       "infer that many times and average those groups' actions in the client")
    executed = {"n_exec": sampling.n_exec, "rtc": sampling.rtc,
                "temporal_ensemble": sampling.temporal_ensemble, "deadband": sampling.deadband}
    for key, value in executed.items():
        if value:
            caveats.append(f"eval.{key} = {value!r}: how this run's chunks are executed "
                           "(pi0_armfix.policies.execution); openpi returns whole chunks: "
                           "apply it where the client executes them")
    return caveats


def bool_mask_runs(mask: np.ndarray) -> tuple[int, ...]:
    """`[D]` bool -> the arguments of openpi's `make_bool_mask` (n: n True dims, -n: n False)."""
    runs: list[int] = []
    for value in mask:
        sign = 1 if value else -1
        if runs and (runs[-1] > 0) == bool(value):
            runs[-1] += sign
        else:
            runs.append(sign)
    return tuple(runs)


def openpi_norm_stats(norm_stats: Mapping[str, stats_lib.NormStats], mode: str, pi05: bool
                      ) -> tuple[dict[str, Any], dict[str, list[int]]]:
    """A run's statistics (`mode` "zscore" or "quantile") in openpi's `norm_stats.json` form, and
    the constant dims per key whose statistics were rewritten so that openpi's formula computes
    the run's map (`normalize.Normalizer`)."""
    out, adjusted = {}, {}
    for key in ("state", "actions"):
        stats = norm_stats[key]
        fields = {name: np.asarray(getattr(stats, name), np.float64).copy()
                  for name in stats_lib.FIELDS}
        constant = stats.constant(mode)
        if key == "state" and pi05:
            constant[:] = False  # pi0.5 reads its state through openpi's formula as it is
        if constant.any():
            # openpi divides by and multiplies with `spread + 1e-6`: huge for a state that must
            # normalize to 0, ~0 for an action that must un-normalize to its mean.
            spread = CONSTANT_STATE_SPREAD if key == "state" else 0.0
            if mode == "zscore":
                fields["std"][constant] = spread
            else:
                fields["q01"][constant] = fields["mean"][constant] - spread / 2
                fields["q99"][constant] = fields["mean"][constant] + spread / 2
            adjusted[key] = np.flatnonzero(constant).tolist()
        out[key] = {name: value.tolist() for name, value in fields.items()}
    return {"norm_stats": out}, adjusted


def openpi_config(run: restore.RestoredRun, asset_id: str) -> dict[str, Any]:
    """The openpi train config this run pairs with, as the fields to set."""
    config, layout, model = run.config, run.layout, run.model_config
    mask = transforms.delta_action_mask(config.data.delta_action_mask, layout)
    # What the run folder keeps of its dataset; a run trained before it kept them opens its data.
    inputs = run_inputs.load(run.workdir) or sources.open_source(config.data, layout)
    selection = getattr(inputs, "state_selection", None)
    state = None
    if selection is not None:
        state = {"field": selection.field, "stored_width": selection.stored_width,
                 "preset": selection.preset.name if selection.preset else "",
                 "dims": [list(selection.stored_dims(d)) for d in range(selection.width)]}
    return {
        "style": "pi05_b1k" if model.pi05 else "pi0_b1k",
        "model": {"pi05": model.pi05, "action_horizon": model.action_horizon,
                  "action_dim": model.action_dim, "max_token_len": model.max_token_len,
                  # openpi's names of the experts' sizes; "_lora" where the params hold adapters
                  **{f"{name}_variant": variant + ("_lora" if name in model.lora_experts else "")
                     for name, variant in OPENPI_VARIANTS.items()}},
        "use_quantile_norm": model_config_lib.norm_mode(config) == "quantile",
        "delta_action_mask": None if mask is None else list(bool_mask_runs(mask)),
        "state": state,
        "action_groups": {g: list(map(int, v)) for g, v in layout.groups.items()},
        "actions_out": layout.real_dim,
        "cameras": dict(getattr(inputs, "cameras", {}) or {}),
        "asset_id": asset_id,
        "num_steps": run.sampling.num_steps,
    }


def describe(pairing: Mapping[str, Any]) -> str:
    """The openpi config in words, for the console."""
    model = pairing["model"]
    lines = [f"openpi config to serve it with ({pairing['style']} style):",
             f"  model: pi0_config.Pi0Config(pi05={model['pi05']}, action_horizon="
             f"{model['action_horizon']}, action_dim={model['action_dim']}, max_token_len="
             f"{model['max_token_len']}, paligemma_variant={model['paligemma_variant']!r}, "
             f"action_expert_variant={model['action_expert_variant']!r})",
             f"  normalization: {'quantile' if pairing['use_quantile_norm'] else 'z-score'} "
             f"(use_quantile_norm={pairing['use_quantile_norm']}), stats of asset_id "
             f"{pairing['asset_id']!r}"]
    mask = pairing["delta_action_mask"]
    lines.append("  actions: absolute (no DeltaActions)" if mask is None else
                 f"  actions: DeltaActions / AbsoluteActions(make_bool_mask{tuple(mask)}) "
                 "(relative to the state's same dims)")
    state = pairing["state"]
    if state is not None:
        lines.append(f"  state: the inputs transform builds {len(state['dims'])} dims from the "
                     f"stored {state['stored_width']}-D {state['field']!r}"
                     + (f" (preset {state['preset']!r})" if state["preset"] else "")
                     + ": " + ", ".join("+".join(map(str, d)) for d in state["dims"]))
    lines.append(f"  outputs: the first {pairing['actions_out']} action dims ("
                 + ", ".join(f"{g} {a}:{b}" for g, (a, b) in pairing["action_groups"].items())
                 + ")")
    if pairing["cameras"]:
        lines.append("  cameras: " + ", ".join(f"{key} -> {slot}"
                                           for slot, key in pairing["cameras"].items()))
    return "\n".join(lines)


def code_version() -> str:
    """The git commit of this checkout ('' outside one)."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def write_params(params: Any, directory: Path, dtype: str) -> int:
    """Writes `{"params": params}` (leaves cast to `dtype`) as openpi's params checkpoint; returns
    the leaf count."""
    import jax
    import jax.numpy as jnp

    cast = jax.tree.map(lambda x: np.asarray(jnp.asarray(x, dtype)), params)
    with ocp.PyTreeCheckpointer() as checkpointer:
        checkpointer.save(directory.absolute(), {"params": cast})
    return len(jax.tree.leaves(cast))


def export(checkpoint: str | Path, output: str | Path, *, asset_id: str = "",
           ema: bool = True, dtype: str = "float32", force: bool = False) -> dict[str, Any]:
    """Exports a run's checkpoint for openpi (module docstring); returns what
    `pi0_armfix_export.json` says. Raises ValueError for a run openpi cannot reproduce (unless
    `force`), a bad dtype, or an output folder that is not empty."""
    if dtype not in DTYPES:
        raise ValueError(f"--dtype={dtype} must be one of {DTYPES}")
    workdir, step = resolve_checkpoint(checkpoint)
    output = Path(output).expanduser().absolute()
    if output.exists() and not output.is_dir():
        raise ValueError(f"--output={output} is a file; name a new folder (an export writes "
                         "params/ and assets/ into one)")
    if output.exists() and any(output.iterdir()):
        raise ValueError(f"--output={output} is not empty; name a new folder (an export never "
                         "overwrites one)")
    writable_folder(output, "pass an --output on a writable file system", create=False)
    run = restore.restore_run(epath.Path(workdir), step, "ema" if ema else "params")
    problems = openpi_problems(run)
    if problems and not force:
        raise ValueError(f"openpi cannot reproduce {workdir} step {run.step}: {problems[0]}"
                         + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")
                         + "; --force writes the export anyway with the caveats in "
                         f"{EXPORT_FILE}")
    asset_id = asset_id or default_asset_id(run)
    norm_stats, adjusted = openpi_norm_stats(
        run.norm_stats, model_config_lib.norm_mode(run.config), run.model_config.pi05)
    pairing = openpi_config(run, asset_id)
    output.mkdir(parents=True, exist_ok=True)
    try:
        leaves = write_params(run.params, output / "params", dtype)
        json_files.write_json_atomic(output / "assets" / asset_id / "norm_stats.json", norm_stats)
        summary = {"run": str(workdir), "step": run.step, "params": run.params_name,
                   "preset": run.config.model.preset, "dtype": dtype, "leaves": leaves,
                   "code_version": code_version(), "openpi_config": pairing,
                   "constant_dims_rewritten": adjusted, "refused_without_force": problems,
                   "caveats": openpi_caveats(run)}
        json_files.write_json_atomic(output / EXPORT_FILE, summary)
    except BaseException:
        shutil.rmtree(output, ignore_errors=True)  # never leave a half export that looks whole
        raise
    return summary


def default_asset_id(run: restore.RestoredRun) -> str:
    """openpi names a dataset's statistics by its repo id: the run's data folder name (the demo's
    'pi0_armfix_demo')."""
    root = run.config.data.get("root") or ""
    return Path(root).name if root else "pi0_armfix_demo"


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    with console.user_errors("pi0_armfix.tools.export_openpi"):
        if not FLAGS.checkpoint or not FLAGS.output:
            raise ValueError("--checkpoint (a run folder or RUN/checkpoints/STEP) and --output "
                             "(a new folder) are required")
        summary = export(FLAGS.checkpoint, FLAGS.output, asset_id=FLAGS.asset_id, ema=FLAGS.ema,
                         dtype=FLAGS.dtype, force=FLAGS.force)
    output = Path(FLAGS.output).expanduser().absolute()
    print(f"exported {summary['run']} step {summary['step']} ({summary['params']}, "
          f"{summary['preset']}, {summary['leaves']} arrays, {summary['dtype']}) to {output}")
    print(describe(summary["openpi_config"]))
    for key, dims in summary["constant_dims_rewritten"].items():
        print(f"  constant {key} dims {dims}: statistics written so openpi's formula passes "
              "them centred, as the run does")
    for line in summary["refused_without_force"] + summary["caveats"]:
        print(f"caveat: {line}")
    print(f"load it in openpi: create_trained_policy(<that train config>, {str(output)!r})")


def cli() -> None:
    """The `pi0-armfix-export-openpi` console script."""
    flags.DEFINE_string("checkpoint", "", "a run folder (its latest step) or RUN/checkpoints/STEP")
    flags.DEFINE_string("output", "", "the new folder to write (params/, assets/, the summary)")
    flags.DEFINE_string("asset_id", "", "openpi's asset id of the statistics (default: the run's "
                        "data folder name)")
    flags.DEFINE_bool("ema", True, "export the EMA params where the run kept them (what "
                      "evaluate and serve use); --noema: the raw params")
    flags.DEFINE_enum("dtype", "float32", DTYPES, "the params' dtype on disk (bfloat16 halves "
                      "it; float32 gives the run's actions exactly)")
    flags.DEFINE_bool("force", False, "export a run openpi cannot reproduce, its caveats written "
                      f"into {EXPORT_FILE}")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.export_openpi"))


if __name__ == "__main__":
    cli()
