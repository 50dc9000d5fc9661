"""What the demo world's closed-loop success means: the calibration rows and the success curve.

    python -m pi0_armfix.tools.closed_loop_calibration [--episodes=50] [--tolerances=1,2,4] \
        [--noise_run=runs/uniform] [--hold=16] [--output=results/closed_loop_calibration]

Runs, on the closed-loop evaluation's episodes (world seed 1000, never trained on), at the world's
tolerances and at each factor of `--tolerances` (`sim.world.tolerances`):

  expert                 the scripted teleoperator (the upper bound).
  expert + policy error  the expert with an error the size of a trained run's held-out error
                         added to every action (`--noise_run`: its last evaluation's `err/<g>` in
                         data units), drawn afresh every `--hold` steps (a chunk's error is much
                         the same over the steps executed from it): how far a policy that is as
                         wrong as that run, but otherwise perfect, gets.
  hold last action       persistence: the starting command held (base still, arms in posture).
  zero                   every action 0.
  recorded chunks        random recorded chunks of `--hold` * 2 steps, `--hold` executed: motion of
                         the right kind at the wrong time and place.

Writes `calibration.json` (every row's summary per factor, with failure reasons), `calibration.md`
(the table) and `success_curve.png` into `--output`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from absl import app, flags

from pi0_armfix import console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import json_files
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout as rollout_lib
from pi0_armfix.sim.outcomes import FAILURE_REASONS
from pi0_armfix.sim.world import DemoSpec
from pi0_armfix.training import metrics_log

NOISY_EXPERT = "expert + policy error"


def policy_error_std(run: Path) -> np.ndarray:
    """`[23]` a run's held-out error per action dim in data units: its last evaluation's
    `err/<g>` (mean squared error in evaluation units) times each dim's evaluation scale (the
    training split's std of the absolute actions, `norm_stats.json`'s `actions_absolute`)."""
    run = Path(run)
    config = json.loads((run / "config.json").read_text()) if (run / "config.json").exists() \
        else None
    records = [r for r in metrics_log.read_metrics(run / metrics_log.METRICS_FILE)
               if any(k.startswith("err/") for k in r)] if (run / metrics_log.METRICS_FILE
                                                             ).exists() else []
    if config is None or not records:
        raise ValueError(f"--noise_run={run} is not a run folder with a held-out evaluation "
                         f"(config.json and evaluation records in {metrics_log.METRICS_FILE}); "
                         "train one (python -m pi0_armfix.train) or leave --noise_run empty")
    layout = ActionLayout.from_config(config["layout"])
    stats = stats_lib.load_norm_stats(run / "norm_stats.json")
    if "actions_absolute" not in stats:
        raise ValueError(f"{run / 'norm_stats.json'} has no 'actions_absolute' statistics (the "
                         "evaluation's units); retrain or evaluate the run with this version")
    scale, _ = eval_metrics.evaluation_units(stats["actions_absolute"].std,
                                             stats["actions_absolute"].q01,
                                             stats["actions_absolute"].q99)
    std = np.zeros(layout.real_dim)
    for g in layout.group_names:
        dims = layout.group_dims(g)
        std[dims] = np.sqrt(records[-1][f"err/{g}"]) * scale[dims]
    return std


def calibration_rows(noise_std: np.ndarray | None, hold: int
                     ) -> dict[str, tuple[rollout_lib.Driver, int]]:
    """`{name: (policy, actions executed per chunk)}` of the calibration rows."""
    rows = {"expert": (rollout_lib.ExpertDriver(), 1)}
    if noise_std is not None:
        rows[NOISY_EXPERT] = (rollout_lib.NoisyExpertDriver(noise_std, hold), 1)
    rows |= {"hold last action": (rollout_lib.HoldDriver(), 1),
             "zero": (rollout_lib.ZeroDriver(), 1),
             "recorded chunks": (rollout_lib.RecordedChunkDriver(horizon=2 * hold), hold)}
    return rows


def calibrate(rows: Mapping[str, tuple[rollout_lib.Driver, int]], episodes: Sequence[int],
              factors: Sequence[float], progress: bool = True,
              spec: DemoSpec = DemoSpec(seed=env_lib.EVAL_SEED)) -> dict[str, Any]:
    """`{name: {factor: summary}}` of every row on `episodes` of `spec` (the closed-loop
    evaluation's world)."""
    return {name: rollout_lib.success_curve(policy, episodes, spec=spec, factors=factors,
                                            n_exec=n_exec, progress=progress)
            for name, (policy, n_exec) in rows.items()}


def markdown(curves: Mapping[str, Any], episodes: int) -> str:
    """The calibration table: phase success per row and factor, and why phases failed."""
    factors = list(next(iter(curves.values())))
    lines = [f"# Closed-loop calibration: {episodes} episodes of world seed "
             f"{env_lib.EVAL_SEED}", "",
             "Phase success (fraction of phases) at the world's tolerances (1x) and looser; "
             "then, at 1x, the fraction of phases that failed for each reason.", "",
             "| row | " + " | ".join(f"navigation {f}x | manipulation {f}x" for f in factors)
             + " |", "|---" * (1 + 2 * len(factors)) + "|"]
    for name, curve in curves.items():
        lines.append(f"| {name} | " + " | ".join(
            f"{curve[f]['phase_success/navigation']:.2f} | "
            f"{curve[f]['phase_success/manipulation']:.2f}" for f in factors) + " |")
    reasons = [(k, r) for k in ("navigation", "manipulation") for r in FAILURE_REASONS[k]]
    lines += ["", "| row (1x) | " + " | ".join(f"{k[:3]}: {r}" for k, r in reasons) + " |",
              "|---" * (1 + len(reasons)) + "|"]
    for name, curve in curves.items():
        first = curve[factors[0]]
        lines.append(f"| {name} | " + " | ".join(
            f"{first[f'failure/{k}/{r}']:.2f}" for k, r in reasons) + " |")
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    try:
        factors = [float(f) for f in FLAGS.tolerances]
        if not factors or min(factors) <= 0:
            raise ValueError(f"--tolerances={','.join(FLAGS.tolerances)} must be factors > 0")
        if FLAGS.episodes < 1 or FLAGS.hold < 1:
            raise ValueError("--episodes and --hold must be >= 1")
        noise_std = policy_error_std(Path(FLAGS.noise_run)) if FLAGS.noise_run else None
    except ValueError as e:
        raise SystemExit(f"pi0_armfix.tools.closed_loop_calibration: {e}") from None
    curves = calibrate(calibration_rows(noise_std, FLAGS.hold), range(FLAGS.episodes),
                       factors)
    out = Path(FLAGS.output)
    out.mkdir(parents=True, exist_ok=True)
    json_files.write_json_atomic(out / "calibration.json", {
        "episodes": FLAGS.episodes, "tolerances": factors, "hold": FLAGS.hold,
        "noise_run": FLAGS.noise_run or None,
        "noise_std": None if noise_std is None else noise_std.tolist(), "rows": curves})
    text = markdown(curves, FLAGS.episodes)
    (out / "calibration.md").write_text(text)
    rollout_lib.plot_success_curves(curves, out / "success_curve.png",
                                    f"calibration rows, {FLAGS.episodes} episodes")
    print(text)
    print(f"calibration.json, calibration.md and success_curve.png in {out}")


def cli() -> None:
    """The `pi0-armfix-closed-loop-calibration` console script (also `python -m
    pi0_armfix.tools.closed_loop_calibration`)."""
    flags.DEFINE_integer("episodes", 50, "episodes of the closed-loop evaluation's world")
    flags.DEFINE_list("tolerances", ["1", "2", "4"], "tolerance factors of the success curve")
    flags.DEFINE_string("noise_run", "", "a trained run whose held-out error the noisy expert "
                        "carries ('' = no such row)")
    flags.DEFINE_integer("hold", 16, "steps a noise draw is held (and recorded chunks executed)")
    flags.DEFINE_string("output", "results/closed_loop_calibration", "output folder")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.closed_loop_calibration"))


if __name__ == "__main__":
    cli()
