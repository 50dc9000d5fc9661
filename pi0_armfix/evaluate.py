"""`python -m pi0_armfix.evaluate`: a checkpoint's held-out evaluation (`pi0_armfix.evaluation.
evaluator`, docs/evaluation.md) or, with `--closed_loop`, its policy driving the demo world
(`pi0_armfix.evaluation.closed_loop`).

    python -m pi0_armfix.evaluate --workdir=runs/arm_focused [--step=N] [--params=ema|params]
    python -m pi0_armfix.evaluate --workdir=runs/arm_focused --closed_loop [--episodes=50] \
        [--tolerances=1,2,4]
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
from absl import app, flags
from etils import epath

from pi0_armfix import cache, console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.evaluation import closed_loop as closed_loop_lib
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import figures
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.evaluation.evaluator import METRICS_FILE, format_metrics, heldout_paths
from pi0_armfix.evaluation.outputs import strict_json, writable_folder
from pi0_armfix.policies import restore
from pi0_armfix.policies.sampling import SAMPLED_LEVERS
from pi0_armfix.training import metrics_log
from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout as rollout_lib


STAGNATION_FILE = "stagnation.png"  # gain and skill over the offline evaluations, in eval/


def evaluate_checkpoint(workdir: epath.PathLike, step: int | None = None,
                        params_name: str = "ema", levers: Mapping[str, Any] | None = None
                        ) -> tuple[int, dict[str, float], ActionLayout, epath.Path]:
    """Evaluates a run's checkpoint (latest if `step` is None) with its own config and norm stats;
    writes the figures into `<workdir>/eval/step_<N>/`. `params_name`: "ema" (the EMA params when
    the run kept them, else the params) or "params"; `levers`: inference levers in place of the
    run's (`restore.restore_run`). The metrics go to `metrics.json` there (with levers other
    than the plain sampler's, or the raw params of a run with an EMA,
    `metrics<RestoredRun.result_tag>.json`, which the stagnation figure and the study leave out).
    Returns `(step, metrics, layout, metrics path)`."""
    run = restore.restore_run(workdir, step, params_name, levers)
    tag = run.result_tag()
    workdir, step, layout = run.workdir, run.step, run.layout
    out = workdir / "eval" / f"step_{step}"
    writable_folder(out)  # before the sampling, not after
    evaluator, mesh = evaluator_lib.run_evaluator(run)
    with jax.set_mesh(mesh):
        metrics, predicted, true, sums = evaluator(run.params)
    metrics_path, chunk_sums_path = heldout_paths(workdir, step, tag)
    chunk_sums_lib.save_chunk_sums(chunk_sums_path, sums)
    # Strict JSON: a metric with nothing to measure (NaN) is null.
    metrics_path.write_text(json.dumps(
        {"step": step, "params": run.params_name,
         **{key: getattr(run.sampling, key) for key in SAMPLED_LEVERS},
         **strict_json({k: float(v) for k, v in metrics.items()})},
        indent=2, allow_nan=False) + "\n")
    evaluator.plot(predicted, true, out / f"trajectories{tag}.png", f"step {step}: predicted "
                   "(dashed) vs true (solid)")
    figures.plot_group_losses(metrics_log.read_metrics(workdir / metrics_log.METRICS_FILE), layout,
                            out / "group_losses.png")
    figures.plot_stagnation(offline_records(workdir), layout, workdir / "eval" / STAGNATION_FILE)
    return step, metrics, layout, metrics_path


def offline_records(workdir: epath.PathLike) -> list[dict[str, Any]]:
    """Every offline evaluation of a run (`eval/step_<N>/metrics.json`), in step order: a run
    evaluated at several checkpoints draws its stagnation figure from them (`eval/`
    `stagnation.png`), like the one training draws from its in-run evaluations."""
    found = []
    for path in epath.Path(workdir).glob(f"eval/step_*/{METRICS_FILE}"):
        record = json.loads(path.read_text())
        found.append({k: math.nan if v is None else v for k, v in record.items()})
    return sorted(found, key=lambda r: r["step"])


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    cache.use_compilation_cache()
    if FLAGS.closed_loop:
        try:
            try:
                tolerances = [float(f) for f in FLAGS.tolerances]
            except ValueError:
                raise ValueError(f"--tolerances={','.join(FLAGS.tolerances)} must be numbers "
                                 "(tolerance factors, e.g. 1,2,4)") from None
            step, summary = closed_loop_lib.closed_loop(
                FLAGS.workdir, FLAGS.step, FLAGS.params, episodes=FLAGS.episodes,
                sim_seed=FLAGS.sim_seed, tolerances=tolerances, levers=console.lever_flags())
        except ValueError as e:
            raise SystemExit(f"pi0_armfix.evaluate: {e}") from None
        print(f"step {step}, closed loop in the demo world (success rate):")
        print(rollout_lib.format_summary(summary))
        print(f"results in {summary['results']}; rollouts in {summary['figure']}")
        return
    try:
        step, metrics, layout, path = evaluate_checkpoint(FLAGS.workdir, FLAGS.step, FLAGS.params,
                                                          levers=console.lever_flags())
    except ValueError as e:
        raise SystemExit(f"pi0_armfix.evaluate: {e}") from None
    print(f"step {step}, held-out chunks sampled by the policy:")
    print(format_metrics(metrics, layout))
    print(f"metrics in {path}; figures in {path.parent}")


def cli() -> None:
    """The `pi0-armfix-evaluate` console script (also `python -m pi0_armfix.evaluate`)."""
    flags.DEFINE_string("workdir", None, "run folder (holds checkpoints/)", required=True)
    flags.DEFINE_integer("step", None, "checkpoint step (default: the latest)")
    flags.DEFINE_enum("params", "ema", ["ema", "params"],
                      "the EMA params (when the run kept them) or the raw params")
    flags.DEFINE_bool("closed_loop", False, "run the policy in the demo world (pi0_armfix.sim) "
                      "instead of sampling held-out chunks")
    flags.DEFINE_integer("episodes", 50, "closed loop: episodes of the demo world")
    flags.DEFINE_integer("sim_seed", env_lib.EVAL_SEED, "closed loop: world seed of the "
                         "episodes (the demo dataset is seed 0)")
    console.define_lever_flags()
    flags.DEFINE_list("tolerances", [], "closed loop: tolerance factors of a success curve "
                      "(e.g. 1,2,4: the same episodes with the world's tolerances doubled and "
                      "quadrupled; empty: the world as it is only)")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.evaluate"))



if __name__ == "__main__":
    cli()
