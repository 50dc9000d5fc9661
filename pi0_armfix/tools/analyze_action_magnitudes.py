"""Per-group action magnitudes and motion, loss shares, suggested weights and layout checks.

    python -m pi0_armfix.tools.analyze_action_magnitudes --config=configs/uniform.py \
        [--config.data.root=DIR] --output=magnitudes.json

Over the training episodes (two streaming passes, plus one for the norm stats when the config
does not name a file), per layout group:

- magnitude: per frame, the RMS over the group's dims of the raw action (mean, median, p95);
- motion: per frame pair within an episode, the RMS over the group's non-constant dims of the
  frame-to-frame change in the run's normalized units (`data.norm`, the run's norm stats) (mean,
  median, p95, RMS); medians and p95 from 1%-resolution log histograms;
- motion_share: the group's share of the summed per-dim mean squared frame-to-frame motion in
  normalized units (late in training a uniform loss's per-dim error tracks how much a dim moves,
  so this says where that loss will sit); compare it with `dim_share` (its share of the dims);
- suggested_weight: the inverse of the group's motion RMS, normalized to 1 for the base (or, with
  no moving base group, the median group): the static weights that even out the groups' motion,
  capped at 10 with a warning (a group that barely moves would get a weight of tens).

The stagnation mechanism (`pi0_armfix.tools.mechanism`, docs/mechanisms.md), per group: its share
of the uniform loss (the magnitude mechanism), the part of its targets the current state
explains and its share of what is left (the state-copy mechanism), the change within a chunk;
then a verdict naming the mechanism(s) found and the lever to try first. One more streaming pass
over actions and state.

Layout warnings: a group that mixes gripper-like dims (>= 80% of the frames within 10% of the
[q01, q99] range from either end, each end holding >= 2%) with joint-like dims — e.g. the widely
copied wrong B1K layout `left_arm (7,14), right_arm (14,21), grippers (21,23)`, which is the state
order, not the action order — and constant dims (std < 1e-6).

Writes the JSON report to --output and per-group motion histograms to the same path with a .png
suffix.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import ml_collections
import numpy as np
from absl import app, flags
from matplotlib.figure import Figure  # pyplot-free: renders with Agg, no display needed
from ml_collections import config_flags

from pi0_armfix import console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.data.statistics.bimodal import gripper_like_dims
from pi0_armfix.evaluation import baselines
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.tools import mechanism as mechanism_lib


def layout_warnings(layout: ActionLayout, gripper_like: np.ndarray,
                    constant: np.ndarray) -> list[str]:
    """Groups mixing gripper-like and joint-like dims; constant dims."""
    warnings = []
    for name, (start, stop) in layout.groups.items():
        dims = np.arange(start, stop)
        grippers = dims[gripper_like[dims]]
        joints = dims[~gripper_like[dims] & ~constant[dims]]
        if grippers.size and joints.size:
            warnings.append(
                f"group {name!r} ({start}, {stop}) mixes gripper-like dims {grippers.tolist()} "
                f"(mass at two ends) with joint-like dims {joints.tolist()}: check the layout "
                "(B1K actions: dim 14 is the left gripper and 15:22 the right arm; the baseline's "
                "state order, which puts the grippers last, is wrong for actions)")
    for d in np.flatnonzero(constant):
        group = layout.group_of_dim(int(d))
        warnings.append(f"dim {d} (group {group!r}) is constant (std < "
                        f"{stats_lib.CONSTANT_SPREAD}): it is pinned to its mean and carries no "
                        "loss")
    return warnings


# A group that barely moves gets a huge inverse-motion weight that mostly amplifies its noise.
MAX_SUGGESTED_WEIGHT = 10.0


def suggested_weights(layout: ActionLayout, motion_rms: np.ndarray) -> dict[str, float]:
    """Inverse motion RMS, normalized to the base group (else the median moving group), capped at
    `MAX_SUGGESTED_WEIGHT` (`capped_weight_warnings` names the groups it cut)."""
    moving = motion_rms > 0
    if not moving.any():
        return {name: 1.0 for name in layout.group_names}
    names = layout.group_names
    bases = [names.index(g) for g in layout.groups_with_role("base") if moving[names.index(g)]]
    reference = motion_rms[bases].mean() if bases else np.median(motion_rms[moving])
    return {name: float(min(reference / motion_rms[g], MAX_SUGGESTED_WEIGHT)) if moving[g]
            else 1.0 for g, name in enumerate(layout.group_names)}


def capped_weight_warnings(groups: dict[str, dict[str, Any]]) -> list[str]:
    """A caveat per group whose suggested weight hit the cap."""
    return [f"{name} barely moves (motion RMS {g['motion_normalized']['rms']:.3g} normalized "
            f"units): its inverse-motion weight is capped at {MAX_SUGGESTED_WEIGHT:g}; a group "
            "with little motion has little to learn, so weight it by judgment, not by this ratio"
            for name, g in groups.items() if g["suggested_weight"] >= MAX_SUGGESTED_WEIGHT]


def _quantiles(histograms: motion_lib.LogHistograms) -> dict[str, np.ndarray]:
    return {"mean": histograms.mean(), "median": histograms.quantile(0.5),
            "p95": histograms.quantile(0.95)}


def group_report(layout: ActionLayout, summary: motion_lib.MotionSummary, unit: np.ndarray,
                 active: np.ndarray) -> dict[str, dict[str, Any]]:
    """Per group: dims, magnitude, motion, motion_share, dim_share, suggested_weight."""
    motion_rms = summary.group_motion_rms(layout, unit, active)
    per_dim_energy = np.where(active, summary.dim_sq_sum * unit**2, 0.0)
    total_energy = per_dim_energy.sum()
    weights = suggested_weights(layout, motion_rms)
    magnitude, motion = _quantiles(summary.magnitude), _quantiles(summary.motion)
    report = {}
    for g, (name, (start, stop)) in enumerate(layout.groups.items()):
        report[name] = {
            "dims": [start, stop],
            "magnitude_raw": {k: float(v[g]) for k, v in magnitude.items()},
            "motion_normalized": {**{k: float(v[g]) for k, v in motion.items()},
                                  "rms": float(motion_rms[g])},
            "motion_share": float(per_dim_energy[start:stop].sum() / total_energy)
                          if total_energy > 0 else 0.0,
            "dim_share": (stop - start) / layout.real_dim,
            "suggested_weight": weights[name],
        }
    return report


def plot_motion(layout: ActionLayout, summary: motion_lib.MotionSummary, path: Path,
                bins_per_decade: int = 10) -> None:
    """One log-x histogram of per-pair motion (normalized units) per group."""
    merge = (len(motion_lib.LogHistograms.EDGES) - 1) // (12 * bins_per_decade)
    edges = motion_lib.LogHistograms.EDGES[::merge]
    counts = summary.motion.counts[:, 1:-1].reshape(layout.num_groups, -1, merge).sum(-1)
    share = counts / max(summary.motion.count, 1)
    occupied = np.flatnonzero(counts.sum(0))
    fig = Figure(figsize=(7, 1.6 * layout.num_groups + 0.6))
    axes = np.atleast_1d(fig.subplots(layout.num_groups, 1, sharex=True))
    for g, (ax, name) in enumerate(zip(axes, layout.group_names)):
        ax.stairs(share[g], edges, fill=True, alpha=0.7)
        ax.set_xscale("log")
        # The name inside the panel: as a y-label it collided with the tick labels.
        ax.text(0.01, 0.8, name, transform=ax.transAxes, ha="left", fontweight="bold")
        ax.set_ylabel("share")
        still = summary.motion.counts[g, 0] / max(summary.motion.count, 1)
        ax.text(0.99, 0.8, f"still: {still:.0%}", transform=ax.transAxes, ha="right")
    if occupied.size:
        axes[-1].set_xlim(edges[max(occupied[0] - 1, 0)],
                          edges[min(occupied[-1] + 2, len(edges) - 1)])
    axes[-1].set_xlabel("frame-to-frame motion per pair (normalized units, RMS over the group)")
    fig.suptitle("per-group motion histograms (share of frame pairs)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def run(config: ml_collections.ConfigDict, output: str | Path) -> dict[str, Any]:
    layout = ActionLayout.from_config(config.layout)
    norm_mode = model_config_lib.norm_mode(config)
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    spec = DataSpec.from_config(config, layout)
    source = sources.open_source(spec.options, layout)
    dataset_lib.check_data(spec, source, images=False)
    episodes = dataset_lib.training_episodes(spec, source)
    print(dataset_lib.describe_episodes(spec, source, episodes))
    norm_stats = dataset_lib.load_or_compute_norm_stats(spec, action_horizon=horizon,
                                                        source=source)
    blocks, total = dataset_lib.training_blocks(spec, ("actions",), source=source)
    actions = stats_lib.compute_stats(blocks, ("actions",), total_frames=total)["actions"]
    layout.check_real_dim(actions.width, source="the dataset's actions")
    constant = actions.std < stats_lib.CONSTANT_SPREAD
    summary = dataset_lib.dataset_motion(spec, norm_stats["actions"], norm_mode,
                                         source=source)
    unit, active = motion_lib.normalized_units(norm_stats["actions"], norm_mode)
    blocks, _ = dataset_lib.training_blocks(spec, ("actions", "state"), source=source)
    copy_dims = baselines.state_copy_dims(layout, spec.state_groups)
    sums = mechanism_lib.accumulate(stats_lib.whole_episode_blocks(blocks), actions.result(),
                                    norm_stats["state"], horizon, copy_dims)
    mechanism = mechanism_lib.group_mechanisms(sums, layout)
    report = {
        "normalization": norm_mode,
        "num_frames": int(summary.episode_frames.sum()),
        "num_episodes": len(summary.episode_index),
        "num_frame_pairs": summary.num_pairs,
        "groups": group_report(layout, summary, unit, active),
        "warnings": layout_warnings(layout, gripper_like_dims(actions), constant),
        "mechanism": {"horizon": horizon, "groups": mechanism,
                      **mechanism_lib.verdict(mechanism, layout)},
    }
    report["warnings"] += capped_weight_warnings(report["groups"])
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(report, indent=2))
    plot_motion(layout, summary, output.with_suffix(".png"))
    return report


def format_report(report: dict[str, Any]) -> str:
    lines = [f"{'group':<16}{'|a| mean':>10}{'motion rms':>12}{'median':>10}{'p95':>10}"
             f"{'motion %':>10}{'dims %':>8}{'weight':>8}"]
    for name, g in report["groups"].items():
        m = g["motion_normalized"]
        lines.append(f"{name:<16}{g['magnitude_raw']['mean']:>10.3g}{m['rms']:>12.3g}"
                     f"{m['median']:>10.3g}{m['p95']:>10.3g}{100 * g['motion_share']:>10.1f}"
                     f"{100 * g['dim_share']:>8.1f}{g['suggested_weight']:>8.2f}")
    mechanism = report["mechanism"]
    lines += ["", f"stagnation mechanism (z-scored absolute actions, chunks of "
              f"H = {mechanism['horizon']}):",
              f"{'group':<16}{'loss %':>8}{'dims %':>8}{'state R2':>10}{'after state %':>15}"
              f"{'chunk change':>14}{'hold err':>10}{'copy err':>10}{'offset':>8}"
              f"{'lag':>5}{'at lag':>8}"]
    for name, g in mechanism["groups"].items():
        explained = "constant" if g["constant"] else f"{g['state_explained']:.3f}"
        copied = ("" if g["copy_error"] is None
                  else f"{g['copy_error']:>10.3f}{g['steady_offset']:>8.3f}"
                       f"{g['state_lag']:>5d}{g['lagged_copy_error']:>8.3f}")
        lines.append(f"{name:<16}{100 * g['loss_share']:>8.1f}{100 * g['dim_share']:>8.1f}"
                     f"{explained:>10}{100 * g['share_after_state']:>15.1f}"
                     f"{g['within_chunk_change']:>14.4f}{g['hold_error']:>10.3f}{copied}")
    lines += [f"VERDICT: {v}" for v in mechanism["verdict"]]
    lines += [f"WARNING: {w}" for w in report["warnings"]]
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    with console.user_errors("pi0_armfix.tools.analyze_action_magnitudes"):
        report = run(flags.FLAGS.config, flags.FLAGS.output)
    print(format_report(report))
    print(f"wrote {flags.FLAGS.output} and {Path(flags.FLAGS.output).with_suffix('.png')}")



def cli() -> None:
    """The `pi0-armfix-analyze-action-magnitudes` console script (also `python -m
    pi0_armfix.tools.analyze_action_magnitudes`)."""
    config_flags.DEFINE_config_file("config", None, "experiment config file", lock_config=True)
    flags.DEFINE_string("output", None, "JSON report to write (the PNG goes beside it)",
                        required=True)
    flags.mark_flag_as_required("config")
    app.run(main, flags_parser=console.config_flags_parser("pi0_armfix.tools.analyze_action_magnitudes"))


if __name__ == "__main__":
    cli()
