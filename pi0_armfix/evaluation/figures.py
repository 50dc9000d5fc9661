"""PNG figures of a run: per-group loss curves, motion gain over training (stagnation) and
predicted vs true action trajectories."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from etils import epath  # noqa: E402

from pi0_armfix.action_space import ActionLayout  # noqa: E402


def plot_group_losses(records: Sequence[Mapping], layout: ActionLayout,
                      path: epath.PathLike) -> None:
    """Unweighted per-group training loss (log scale) and effective group weight over steps.

    Args:
      records: `metrics.jsonl` records; those without `loss/<group>` (evaluation rows) are skipped.
    """
    rows = [r for r in records if f"loss/{layout.group_names[0]}" in r]
    fig, (ax_loss, ax_weight) = plt.subplots(1, 2, figsize=(12, 4.5))
    steps = [r["step"] for r in rows]
    # Groups often share a weight (every arm group at 3x): a marker shape and a staggered
    # `markevery` per group keep each coinciding line visible.
    markers = "osD^vP*X"
    every = max(1, len(steps) // 12)
    for i, g in enumerate(layout.group_names):
        style = dict(label=g, marker=markers[i % len(markers)], markersize=4,
                     markevery=(i * every // max(1, layout.num_groups), every))
        ax_loss.plot(steps, [r[f"loss/{g}"] for r in rows], **style)
        ax_weight.plot(steps, [r[f"weight/{g}"] for r in rows], **style,
                       ls=("-", "--", ":", "-.")[i % 4])
    ax_loss.set(xlabel="step", ylabel="unweighted flow-matching MSE", yscale="log",
                title="per-group training loss")
    ax_weight.set(xlabel="step", ylabel="effective weight", title="per-group effective weight")
    for ax in (ax_loss, ax_weight):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(epath.Path(path), dpi=100)
    plt.close(fig)


def plot_stagnation(records: Sequence[Mapping], layout: ActionLayout,
                    path: epath.PathLike) -> bool:
    """Held-out motion gain and skill of every group over training, beside doing nothing.

    Left: motion gain, the least-squares slope of the policy's sampled displacement on the data's
    (1 = moves as far as the demonstrations, 0 = still or unrelated), with each group's
    persistence gain (hold the previous action) dotted in its colour: a base at ~0.95 there is the
    data's slow command, not learning. Right: skill over persistence, `1 - err / persistence err`
    (> 0: better than doing nothing) of the single draw, and of the mean of the draws (thin,
    x markers) where evaluated. Base-like groups (roles base, torso) are dashed. Returns
    False (and writes nothing) without evaluation records.
    """
    rows = [r for r in records if f"motion_gain/{layout.group_names[0]}" in r]
    if not rows:
        return False
    steps = [r["step"] for r in rows]
    body = set(layout.groups_with_role("base", "torso"))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, (gain_ax, skill_ax) = plt.subplots(1, 2, figsize=(13, 4.5))
    for i, g in enumerate(layout.group_names):
        style = dict(color=colors[i % len(colors)], marker="o", markersize=4,
                     ls="--" if g in body else "-", lw=1.2 if g in body else 2.0)
        gain_ax.plot(steps, [r[f"motion_gain/{g}"] for r in rows], label=g, **style)
        held = rows[-1].get(f"persistence/motion_gain/{g}")
        if held is not None and np.isfinite(held):  # NaN (null in the log): nothing moved
            gain_ax.axhline(held, color=style["color"], ls=":", lw=1.0)
        if f"skill/{g}" in rows[-1]:
            skill_ax.plot(steps, [r.get(f"skill/{g}", np.nan) for r in rows], label=g, **style)
        if f"mean_of_draws/skill/{g}" in rows[-1]:
            skill_ax.plot(steps, [r.get(f"mean_of_draws/skill/{g}", np.nan) for r in rows],
                          color=style["color"], ls=style["ls"], marker="x", lw=0.8, alpha=0.6)
    gain_ax.set_ylim(min(-0.1, gain_ax.get_ylim()[0]), max(1.15, gain_ax.get_ylim()[1]))
    gain_ax.axhline(1.0, color="gray", lw=0.8)
    gain_ax.axhline(0.0, color="black", lw=0.8)
    gain_ax.text(steps[0], 1.02, "moves like the data", color="gray", fontsize=8, va="bottom")
    gain_ax.text(steps[0], 0.02, "still (stagnation)", color="black", fontsize=8, va="bottom")
    gain_ax.set(xlabel="training step", ylabel="motion gain (held-out, sampled actions)",
                title="motion gain (dotted: holding the previous action)")
    skill_ax.axhline(0.0, color="black", lw=0.8)
    skill_ax.text(steps[0], 0.02, "as good as doing nothing", fontsize=8, va="bottom")
    low, high = skill_ax.get_ylim()
    skill_ax.set_ylim(max(low, -3.0), max(high, 0.2))
    skill_ax.set(xlabel="training step", ylabel="skill = 1 - err / persistence err",
                 title="skill over holding the previous action (> 0: better)\n"
                       "o: the single draw (executed), x: the mean of the draws")
    for ax in (gain_ax, skill_ax):
        ax.grid(alpha=0.3)
    styles = [Line2D([], [], color="gray", marker="o", markersize=4, lw=2.0,
                     label="single draw (executed)"),
              Line2D([], [], color="gray", marker="x", lw=0.8, alpha=0.6,
                     label="mean of the draws"),
              Line2D([], [], color="gray", ls=":", lw=1.0,
                     label="holding the previous action (gain; its skill is 0)")]
    handles, _ = skill_ax.get_legend_handles_labels()
    skill_ax.legend(handles=[*handles, *styles], fontsize=8, loc="center left",
                    bbox_to_anchor=(1.0, 0.5))
    fig.suptitle("held-out evaluation per group (dashed: base and torso)")
    fig.tight_layout()
    fig.savefig(epath.Path(path), dpi=100)
    plt.close(fig)
    return True


def plot_trajectories(predicted: np.ndarray, true: np.ndarray, layout: ActionLayout,
                      groups: Sequence[str], path: epath.PathLike, title: str = "") -> None:
    """Predicted (dashed) vs true (solid) action chunks, one row per chunk, one column per group.

    Args:
      predicted, true: `[N, H, D]` absolute action chunks in the data's units (N rows plotted).
      groups: the layout groups to show.
    """
    n = len(predicted)
    fig, axes = plt.subplots(n, len(groups), figsize=(3.2 * len(groups), 2.4 * n + 1.6),
                             squeeze=False, layout="constrained")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for row in range(n):
        for col, g in enumerate(groups):
            ax = axes[row, col]
            for i, d in enumerate(layout.group_dims(g)):
                color = colors[i % len(colors)]
                ax.plot(true[row, :, d], color=color, lw=1.5, label=f"joint {i} (dim {d})")
                ax.plot(predicted[row, :, d], color=color, lw=1.5, ls="--")
            if row == 0:
                ax.set_title(g)
            if row == n - 1:
                ax.set_xlabel("step in chunk")
                # below the last row, where it covers no curve
                ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.3), ncol=2)
            if col == 0:
                ax.set_ylabel(f"chunk {row + 1}\naction (data units)")
            ax.grid(alpha=0.3)
    fig.suptitle((title + "\n" if title else "") + "solid: demonstration, dashed: policy sample; "
                 "absolute actions in the dataset's units")
    fig.savefig(epath.Path(path), dpi=90)
    plt.close(fig)
