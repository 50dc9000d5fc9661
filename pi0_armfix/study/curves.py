"""A study's learning curves: `study_curves.png` and study.md's last table (held-out skill at
every evaluated step, with the training minutes to it), from the runs' metrics logs."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pi0_armfix.evaluation.chunk_sums import MEAN_OF_DRAWS  # noqa: E402
from pi0_armfix.study.aggregate import as_number, nanmean, nanstd  # noqa: E402
from pi0_armfix.study.report import fit_skill_axis  # noqa: E402

CURVES_HEADING = "## Learning curves"  # study.md's last section


def plot_curves(curves: Mapping[str, Sequence[Sequence[Mapping[str, Any]]]],
                groups: Sequence[str], path: Path) -> None:
    """`study_curves.png`: per config, the training loss and each group's held-out skill over
    persistence against the training minutes (the single draw solid, the mean of the draws
    dashed, where logged), the mean over seeds as a line and the seeds' range shaded; doing
    nothing (persistence) is the line at 0. Minutes (`training_seconds`, mean over the seeds)
    compare recipes whose steps cost differently; where a run logged no timings the axis is the
    step. Draws nothing when no run has a metrics log (a study gathered from kept `result.json`
    files only).

    Args:
      curves: {config: one `metrics.jsonl` record list per seed}.
      groups: the action groups, in the study's order.
    """
    if not any(records for runs in curves.values() for records in runs):
        return
    panels = [("loss", "training loss (weighted, normalized units)")] + [
        (f"skill/{g}", f"held-out skill: {g}") for g in groups]
    columns = min(4, len(panels))
    rows = math.ceil(len(panels) / columns)
    fig, axes = plt.subplots(rows, columns, squeeze=False, figsize=(4.2 * columns, 3.4 * rows))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    timings = {name: [training_seconds(records) for records in runs if records]
               for name, runs in curves.items()}
    timed = all(seconds for runs in timings.values() for seconds in runs)

    def x_of(name: str, steps: Sequence[int]) -> np.ndarray:
        if not timed:
            return np.asarray(steps, float)
        return np.asarray([np.mean([minutes_at(seconds, s) for seconds in timings[name]])
                           for s in steps])

    for (key, title), ax in zip(panels, axes.flat):
        for i, (name, runs) in enumerate(curves.items()):
            steps, values = _curve_values(runs, key)
            if not steps:
                continue
            color = colors[i % len(colors)]
            ax.plot(x_of(name, steps), np.nanmean(values, axis=0), color=color, marker="." if
                    key != "loss" else None, label=f"{name} ({len(values)} seeds)")
            if len(values) > 1:
                ax.fill_between(x_of(name, steps), np.nanmin(values, axis=0),
                                np.nanmax(values, axis=0), color=color, alpha=0.2, lw=0)
            if key != "loss":
                steps, values = _curve_values(runs, f"{MEAN_OF_DRAWS}/{key}")
                if steps:
                    ax.plot(x_of(name, steps), np.nanmean(values, axis=0), color=color, ls="--",
                            label=f"{name}: mean of the draws")
        if key != "loss":
            ax.axhline(0.0, color="black", lw=0.8, ls="--", label="persistence (do nothing)")
            fit_skill_axis(ax, top=1.05)
        ax.set(title=title, xlabel="training minutes" if timed else "step")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"training and held-out evaluation over {'training time' if timed else 'steps'}"
                 ": mean over seeds, seeds' range shaded")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def curve_table(curves: Mapping[str, Sequence[Sequence[Mapping[str, Any]]]],
                study: Mapping[str, Any]) -> list[str]:
    """study.md's learning-curve table: per config and evaluated step, the training minutes it
    took (`training_seconds`, mean over the seeds), each group's held-out skill over persistence
    (single draw; the arms also as the mean of the draws) and switch F1, mean ± sample std over the
    seeds that logged that step (how many, per row), as every study table: skill against wall
    time, so that recipes of different step costs compare. Nothing when no run logged more than its
    final evaluation."""
    groups, arms = study["groups"], study["arm_groups"]
    keys = ([(f"skill/{g}", g) for g in groups]
            + [(f"{MEAN_OF_DRAWS}/skill/{g}", f"{g} (mean of draws)") for g in arms]
            + [("gripper_switch/f1", "switch F1")])
    rows = []
    for name, runs in curves.items():
        steps = sorted({int(r["step"]) for records in runs for r in records
                        if f"skill/{groups[0]}" in r})
        timings = [training_seconds(records) for records in runs]
        for step in steps:
            at = [next((r for r in records if int(r["step"]) == step
                        and f"skill/{groups[0]}" in r), None) for records in runs]
            at = [r for r in at if r is not None]
            minutes = [minutes_at(seconds, step) for seconds in timings]
            minutes = [m for m in minutes if math.isfinite(m)]
            cells = [f"{np.mean(minutes):.1f}" if minutes else "n/a"]
            for key, _ in keys:
                values = np.asarray([as_number(r.get(key)) for r in at], np.float64)
                mean, std = nanmean(values), nanstd(values)
                cells.append("n/a" if mean is None else f"{mean:+.2f}" + (
                    f" ± {std:.2f}" if np.isfinite(values).sum() > 1 else ""))
            rows.append(f"| {name} | {step} | {len(at)} | " + " | ".join(cells) + " |")
    if len({row.split(" | ")[1] for row in rows}) < 2:
        return []
    return ["", f"{CURVES_HEADING} (held-out skill over persistence at every evaluated step)",
            "", "Single draw unless said; mean ± std over the seeds that reached the step. "
            "Persistence (doing nothing) is 0 everywhere.", "",
            "| config | step | seeds | training min | "
            + " | ".join(label for _, label in keys) + " |",
            "|---" * (len(keys) + 4) + "|", *rows]


def training_seconds(records: Sequence[Mapping[str, Any]]) -> dict[int, float]:
    """Wall seconds of training up to each logged step: the sum of the logged windows (`steps /
    steps_per_sec`; a window holds the steps, the compilation and checkpoint saves, never an
    evaluation). A run logged without timings has none."""
    seconds, total, last = {}, 0.0, 0
    for record in sorted((r for r in records if r.get("steps_per_sec")), key=lambda r: r["step"]):
        total += (int(record["step"]) - last) / float(record["steps_per_sec"])
        last = int(record["step"])
        seconds[last] = total
    return seconds


def minutes_at(seconds: Mapping[int, float], step: int) -> float:
    """Training minutes to `step`, interpolated between the logged steps of `training_seconds`
    (an evaluation between two log records); NaN for a run without timings."""
    if not seconds:
        return math.nan
    steps = sorted(seconds)
    return float(np.interp(step, steps, [seconds[s] for s in steps])) / 60


def _curve_values(runs: Sequence[Sequence[Mapping[str, Any]]], key: str
                  ) -> tuple[list[int], np.ndarray]:
    """The steps at which every seed logged `key`, and the seeds' values there `[seeds, steps]`
    (seeds without `key` left out)."""
    logged = [{int(r["step"]): as_number(r[key]) for r in records if key in r} for records in runs]
    logged = [by_step for by_step in logged if by_step]
    if not logged:
        return [], np.zeros((0, 0))
    steps = sorted(set.intersection(*(set(by_step) for by_step in logged)))
    return steps, np.array([[by_step[s] for s in steps] for by_step in logged], dtype=float)
