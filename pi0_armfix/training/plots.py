"""PNG figures of a run: per-group loss curves and predicted vs true action trajectories."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
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
    for g in layout.group_names:
        ax_loss.plot(steps, [r[f"loss/{g}"] for r in rows], label=g)
        ax_weight.plot(steps, [r[f"weight/{g}"] for r in rows], label=g)
    ax_loss.set(xlabel="step", ylabel="unweighted flow-matching MSE", yscale="log",
                title="per-group training loss")
    ax_weight.set(xlabel="step", ylabel="effective weight", title="per-group effective weight")
    for ax in (ax_loss, ax_weight):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(epath.Path(path), dpi=100)
    plt.close(fig)


def plot_trajectories(predicted: np.ndarray, true: np.ndarray, layout: ActionLayout,
                      groups: Sequence[str], path: epath.PathLike, title: str = "") -> None:
    """Predicted (dashed) vs true (solid) action chunks, one row per chunk, one column per group.

    Args:
      predicted, true: `[N, H, D]` normalized action chunks (N rows are plotted).
      groups: the layout groups to show.
    """
    n = len(predicted)
    fig, axes = plt.subplots(n, len(groups), figsize=(3.2 * len(groups), 2.4 * n), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for row in range(n):
        for col, g in enumerate(groups):
            ax = axes[row, col]
            for i, d in enumerate(layout.group_dims(g)):
                color = colors[i % len(colors)]
                ax.plot(true[row, :, d], color=color, lw=1.5)
                ax.plot(predicted[row, :, d], color=color, lw=1.5, ls="--")
            if row == 0:
                ax.set_title(g)
            if row == n - 1:
                ax.set_xlabel("step in chunk")
            ax.grid(alpha=0.3)
    fig.suptitle(title or "predicted (dashed) vs true (solid), normalized units")
    fig.tight_layout()
    fig.savefig(epath.Path(path), dpi=90)
    plt.close(fig)
