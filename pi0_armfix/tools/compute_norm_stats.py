"""Normalization statistics of a config's training data -> openpi `norm_stats.json`.

    python -m pi0_armfix.tools.compute_norm_stats --config=configs/arm_focused.py \
        [--config.data.root=DIR] --output=norm_stats.json [--episodes=train|all]

One streaming pass over the training episodes (`--episodes=train`, the default: all but the
`eval.episodes` held out, as training computes them) or every episode (`--episodes=all`); the tool
prints which episodes and how many frames it reads. Exact float64 mean/std, q01/q99 within 5e-4 of
each dim's range (`pi0_armfix.data.statistics.stats`), for actions (in the model's action space: the
dims of `data.delta_action_mask` relative to the state, over every step of the model's chunks of
`model.action_horizon`, see `dataset.block_norm_stats`) and state. These are plain statistics
whatever `data.balanced_norm` says; `recompute_balanced_norm_stats` writes balanced ones. Point
`--config.data.norm_stats` at the output to train with them.
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
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import config as model_config_lib


def run(config: ml_collections.ConfigDict, output: str | Path, episodes: str = "train"
        ) -> dict[str, stats_lib.NormStats]:
    """Writes the stats of the `episodes` ("train" | "all") of the config's data to `output`."""
    layout = ActionLayout.from_config(config.layout)
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    spec = DataSpec.from_config(config, layout)
    source = sources.open_source(spec.options, layout)
    spec = dataset_lib.reading_spec(spec, episodes)
    chosen = dataset_lib.select_episodes(spec, source, episodes)
    dataset_lib.check_data(spec, source, images=False)
    print(dataset_lib.describe_episodes(spec, source, chosen))
    stats = dataset_lib.dataset_norm_stats(spec, action_horizon=horizon, source=source,
                                           episodes=chosen)
    stats_lib.save_norm_stats(output, stats)
    return stats


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    with console.user_errors("pi0_armfix.tools.compute_norm_stats"):
        stats = run(flags.FLAGS.config, flags.FLAGS.output, flags.FLAGS.episodes)
    for key, value in stats.items():
        print(f"{key} ({value.width} dims)")
        for name in stats_lib.FIELDS:
            print(f"  {name:>4}: " + " ".join(f"{v:8.3f}" for v in getattr(value, name)))
    print(f"wrote {flags.FLAGS.output}")



def cli() -> None:
    """The `pi0-armfix-compute-norm-stats` console script (also `python -m
    pi0_armfix.tools.compute_norm_stats`)."""
    config_flags.DEFINE_config_file("config", None, "experiment config file", lock_config=True)
    flags.DEFINE_string("output", None, "norm_stats.json to write", required=True)
    flags.DEFINE_enum("episodes", "train", dataset_lib.EPISODE_CHOICES,
                      "train: all but the eval.episodes held out (as training); all: every one")
    flags.mark_flag_as_required("config")
    app.run(main, flags_parser=console.config_flags_parser("pi0_armfix.tools.compute_norm_stats"))


if __name__ == "__main__":
    cli()
