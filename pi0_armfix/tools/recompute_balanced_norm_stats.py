"""Balanced normalization statistics (docs/design.md §4) -> openpi `norm_stats.json`.

    python -m pi0_armfix.tools.recompute_balanced_norm_stats --config=configs/arm_focused.py \
        [--config.data.root=DIR] --output=balanced_norm_stats.json [--max_scale=10]

Per-dim means stay; each group's spread is multiplied by one factor so that every group's RMS of
frame-to-frame motion within episodes, in normalized units, equals the median over the groups, the
factor capped to [1/max_scale, max_scale] (`pi0_armfix.data.statistics.motion.balanced_norm_stats`),
separately for z-score (std) and quantile (q01/q99) normalization, so the file serves either
`data.norm`. Groups that move little next to their spread (the arms) get a smaller spread: their
motion is amplified, not the imbalance (an earlier tool multiplied std by target/group_std, which
does the opposite). Prints each group's motion RMS before and after. Two streaming passes over the
training episodes.
"""

from __future__ import annotations

from pathlib import Path

import ml_collections
from absl import app, flags
from ml_collections import config_flags

from pi0_armfix import console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import config as model_config_lib


def run(config: ml_collections.ConfigDict, output: str | Path, max_scale: float | None = None,
        episodes: str = "train"
        ) -> tuple[dict[str, stats_lib.NormStats], list[motion_lib.BalanceReport]]:
    """max_scale: the cap on each group's change of scale; None = `data.balanced_max_scale`.
    episodes: "train" (all but the held-out ones, as training) or "all"."""
    layout = ActionLayout.from_config(config.layout)
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    spec = DataSpec.from_config(config, layout)
    if max_scale is None:  # the config's, its default the base config's (one default)
        max_scale = spec.statistics.balanced_max_scale
    source = sources.open_source(spec.options, layout)
    spec = dataset_lib.reading_spec(spec, episodes)
    chosen = dataset_lib.select_episodes(spec, source, episodes)
    dataset_lib.check_data(spec, source, images=False)
    print(dataset_lib.describe_episodes(spec, source, chosen))
    stats, reports = dataset_lib.balanced_dataset_norm_stats(
        spec, max_scale, action_horizon=horizon, source=source, episodes=chosen)
    stats_lib.save_norm_stats(output, stats)
    return stats, reports


def format_reports(reports: list[motion_lib.BalanceReport]) -> str:
    lines = []
    for report in reports:
        lines.append(f"{report.mode}: motion RMS per group (normalized units), target "
                     f"{report.target:.4g}")
        lines.append(f"  {'group':<16}{'before':>10}{'after':>10}{'spread x':>10}")
        for group, before in report.before.items():
            lines.append(f"  {group:<16}{before:>10.4g}{report.after[group]:>10.4g}"
                         f"{report.scale_change[group]:>10.3g}")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    with console.user_errors("pi0_armfix.tools.recompute_balanced_norm_stats"):
        _, reports = run(flags.FLAGS.config, flags.FLAGS.output, flags.FLAGS.max_scale,
                         flags.FLAGS.episodes)
    print(format_reports(reports))
    print(f"wrote {flags.FLAGS.output}")



def cli() -> None:
    """The `pi0-armfix-recompute-balanced-norm-stats` console script (also `python -m
    pi0_armfix.tools.recompute_balanced_norm_stats`)."""
    config_flags.DEFINE_config_file("config", None, "experiment config file", lock_config=True)
    flags.DEFINE_string("output", None, "norm_stats.json to write", required=True)
    flags.DEFINE_float("max_scale", None, "cap on each group's change of scale "
                       "(unset = config.data.balanced_max_scale)")
    flags.DEFINE_enum("episodes", "train", dataset_lib.EPISODE_CHOICES,
                      "train: all but the eval.episodes held out (as training); all: every one")
    flags.mark_flag_as_required("config")
    app.run(main, flags_parser=console.config_flags_parser("pi0_armfix.tools.recompute_balanced_norm_stats"))


if __name__ == "__main__":
    cli()
