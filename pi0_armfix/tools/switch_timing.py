"""Why a policy's gripper switches miss: timing, direction, or how far ahead in the chunk.

    python -m pi0_armfix.tools.switch_timing --workdir=runs/arm_focused [--step=N] \
        [--tolerances=0,1,2,4,8,16]

`gripper_switch/f1` (docs/evaluation.md) matches a predicted switch to a true one within
`eval.switch_tolerance` steps anywhere in the chunk. A low F1 can mean switches predicted at the
wrong time, switches never predicted, or switches predicted where none happens; and a switch late
in the chunk is one the closed loop never executes (it replans after half the horizon). On the
run's held-out chunks, with the evaluation's own draws, for the single draw (what a robot
executes) and the mean of the `eval.num_draws` draws, this tool reports:

  - precision, recall and F1 against the matching tolerance (0 = the exact step);
  - the recall of the true switches, at `eval.switch_tolerance`, by where they lie in the chunk
    (the executed first half, the rest) and by direction (opens, closes);
  - the predicted switches in chunks with no true switch.

Writes `eval/step_<N>/switch_timing.json` and prints the table.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from absl import app, flags

from pi0_armfix import console
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.evaluation.outputs import strict_json, writable_folder
from pi0_armfix.policies import restore

RESULT_FILE = "switch_timing.json"


def _events(chunk: np.ndarray, valid: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Switch events `[N, 2, D, H]` (opens, closes) of gripper chunks `[N, H, D]`."""
    return np.stack(eval_metrics.switch_events(chunk, valid, threshold), axis=1)


def _matched(predicted: np.ndarray, true: np.ndarray, tolerance: int) -> np.ndarray:
    """The true events `[N, 2, D, H]` matched by a predicted one (`metrics.matched_events`)."""
    horizon = predicted.shape[-1]
    return eval_metrics.matched_events(predicted.reshape(-1, horizon),
                                       true.reshape(-1, horizon), tolerance).reshape(true.shape)


def switch_timing(predicted: np.ndarray, true: np.ndarray, valid: np.ndarray,
                  threshold: np.ndarray, *, tolerances: Sequence[int], tolerance: int,
                  executed: int) -> dict[str, Any]:
    """The timing breakdown of predicted gripper switches against the true ones.

    Args:
      predicted, true: `[N, H, D]` gripper dims of the chunks; valid: `[N, H]` bool;
      threshold: `[D]` the open/close boundary.
      tolerances: the matching tolerances (steps) of the F1 curve.
      tolerance: the tolerance of the recall breakdowns (the evaluation's `switch_tolerance`).
      executed: the steps of a chunk the closed loop executes before replanning.
    Returns:
      `by_tolerance` ({tolerance: {precision, recall, f1}}), `recall` ({part: {true, recall}} for
      `executed` (steps < executed), `ahead` (the rest), `opens`, `closes`), the event counts
      `true` and `predicted`, and `predicted_without_true` (predicted switches in chunks that
      have no true one). A ratio with nothing to count is NaN.
    """
    by_tolerance = {}
    for tol in tolerances:
        sums = eval_metrics.switch_sums(predicted, true, valid, threshold, tol)
        scores = eval_metrics.switch_scores({k: float(v.sum()) for k, v in sums.items()})
        by_tolerance[int(tol)] = {k: scores[f"gripper_switch/{k}"]
                                  for k in ("precision", "recall", "f1")}
    pred_events, true_events = _events(predicted, valid, threshold), _events(true, valid,
                                                                                 threshold)
    steps = np.arange(true_events.shape[-1])  # broadcasts over [N, 2, D, H]'s last axis
    kind = np.arange(2)[:, None, None]  # ... and over its (opens, closes) axis
    parts = {"executed": steps < executed, "ahead": steps >= executed,
             "opens": kind == 0, "closes": kind == 1}
    # One matching over every true switch, then split: matched per part, a predicted switch
    # could match a true one in each part and count twice.
    matched_all = _matched(pred_events, true_events, tolerance)
    recall = {}
    for name, mask in parts.items():
        num_true = int((true_events & mask).sum())
        matched = int((matched_all & mask).sum())
        recall[name] = {"true": num_true,
                        "recall": matched / num_true if num_true else float("nan")}
    no_true = true_events.reshape(len(true_events), -1).sum(axis=1) == 0
    return {"by_tolerance": by_tolerance, "recall": recall, "true": int(true_events.sum()),
            "predicted": int(pred_events.sum()),
            "predicted_without_true": int(pred_events.reshape(len(pred_events), -1)[no_true].sum())}


def run_switch_timing(workdir: str, step: int | None, tolerances: Sequence[int]
                      ) -> tuple[int, dict[str, Any]]:
    """`switch_timing` of a run's checkpoint on its held-out chunks: `{"single_draw": ...,
    "mean_of_draws": ...}` with the settings used; written to `eval/step_<N>/` (`RESULT_FILE`).
    Returns `(step, result)`."""
    run = restore.restore_run(workdir, step)
    groups = evaluator_lib.eval_groups(run.config.eval, run.layout)["gripper_groups"]
    if not groups:
        raise ValueError(f"{workdir}: the layout has no gripper group (eval.gripper_groups or a "
                         "group of role gripper): there are no switches to time")
    out = run.workdir / "eval" / f"step_{run.step}"
    writable_folder(out)
    evaluator, mesh = evaluator_lib.run_evaluator(run)
    with jax.set_mesh(mesh):
        draws = evaluator.absolute_draws(run.params)
    chunks = evaluator.chunks
    dims = np.concatenate([run.layout.group_dims(g) for g in groups])
    settings = {"tolerance": int(run.config.eval.switch_tolerance),
                "executed": run.sampling.executed(run.model_config.action_horizon),
                "tolerances": [int(t) for t in tolerances]}
    result = {"step": run.step, "draws": len(draws), "gripper_groups": list(groups), **settings}
    for name, predicted in (("single_draw", draws[0]), ("mean_of_draws", draws.mean(axis=0))):
        result[name] = switch_timing(predicted[..., dims], chunks.true[..., dims], chunks.valid,
                                     chunks.gripper_threshold[dims], **settings)
    (out / RESULT_FILE).write_text(json.dumps(strict_json(result), indent=2, allow_nan=False)
                                   + "\n")
    return run.step, result


def format_timing(result: dict[str, Any]) -> str:
    """A console table of `run_switch_timing`'s result."""
    horizon_note = (f"executed: the first {result['executed']} steps of a chunk (the closed loop "
                    "replans after them); ahead: the rest")
    lines = [f"gripper switches of the held-out chunks ({result['gripper_groups']}), step "
             f"{result['step']}; recall by part at tolerance {result['tolerance']}; {horizon_note}"]
    for name, label in (("single_draw", "single draw"),
                        ("mean_of_draws", f"mean of {result['draws']} draws")):
        timing = result[name]
        lines.append(f"{label}: {timing['predicted']} predicted, {timing['true']} true, "
                     f"{timing['predicted_without_true']} predicted in chunks without a true one")
        lines.append("  tolerance  precision  recall     F1")
        for tol, scores in timing["by_tolerance"].items():
            lines.append(f"  {tol:>9}  {scores['precision']:9.2f}  {scores['recall']:6.2f}  "
                         f"{scores['f1']:5.2f}")
        lines.append("  recall: " + ", ".join(
            f"{part} {r['recall']:.2f} ({r['true']} true)" for part, r in timing["recall"].items()))
    return "\n".join(lines)


def main(argv: Sequence[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    FLAGS = flags.FLAGS
    console.quiet_library_logging()
    try:
        tolerances = [int(t) for t in FLAGS.tolerances]
    except ValueError:
        raise SystemExit(f"pi0_armfix.tools.switch_timing: --tolerances="
                         f"{','.join(FLAGS.tolerances)} must be whole numbers of steps "
                         "(e.g. 0,1,2,4,8)") from None
    if any(t < 0 for t in tolerances):
        raise SystemExit(f"pi0_armfix.tools.switch_timing: --tolerances={tolerances} must be "
                         ">= 0 (steps by which a predicted switch may miss the true one)")
    try:
        step, result = run_switch_timing(FLAGS.workdir, FLAGS.step, tolerances)
    except ValueError as e:
        raise SystemExit(f"pi0_armfix.tools.switch_timing: {e}") from None
    print(format_timing(result))
    print(f"in {FLAGS.workdir}/eval/step_{step}/{RESULT_FILE}")


def cli() -> None:
    """The `pi0-armfix-switch-timing` console script."""
    flags.DEFINE_string("workdir", None, "run folder (holds checkpoints/)", required=True)
    flags.DEFINE_integer("step", None, "checkpoint step (default: the latest)")
    flags.DEFINE_list("tolerances", ["0", "1", "2", "4", "8", "16"],
                      "matching tolerances (steps) of the F1 curve")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.switch_timing"))


if __name__ == "__main__":
    cli()
