"""`python -m pi0_armfix.evaluate`: a checkpoint's held-out evaluation (`pi0_armfix.evaluation.
evaluator`, docs/evaluation.md) or, with `--closed_loop`, its policy driving the demo world
(`pi0_armfix.evaluation.closed_loop`).

    python -m pi0_armfix.evaluate --workdir=runs/arm_focused [--step=N] [--params=ema|params]
    python -m pi0_armfix.evaluate --workdir=runs/arm_focused --closed_loop [--episodes=50] \
        [--tolerances=1,2,4]
"""

from __future__ import annotations

from collections.abc import Sequence

from absl import app, flags

from pi0_armfix import console
from pi0_armfix.evaluation import closed_loop as closed_loop_lib
from pi0_armfix.evaluation.evaluator import evaluate_checkpoint, format_metrics
from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout as rollout_lib


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
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
