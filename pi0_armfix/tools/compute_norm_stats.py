"""Normalization statistics of a config's training data -> openpi `norm_stats.json`.

    python -m pi0_armfix.tools.compute_norm_stats --config=configs/arm_focused.py \
        [--config.data.root=DIR] --output=norm_stats.json

One streaming pass over the training episodes (all but the `eval.episodes` held out): exact
float64 mean/std, q01/q99 within 5e-4 of each dim's range (`pi0_armfix.data.stats`), for actions
(in the model's action space: the dims of `data.delta_action_mask` relative to the state, over
every step of the model's chunks of `model.action_horizon`, see `pipeline.block_norm_stats`) and
state. These are plain statistics whatever `data.balanced_norm` says;
`recompute_balanced_norm_stats` writes balanced ones. Point `--config.data.norm_stats` at the
output to train with them.
"""

from __future__ import annotations

from pathlib import Path

import ml_collections
from absl import app, flags
from ml_collections import config_flags

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import pipeline
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.data import stats as stats_lib


def run(config: ml_collections.ConfigDict, output: str | Path
        ) -> dict[str, stats_lib.NormStats]:
    layout = ActionLayout.from_config(config.layout)
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    stats = pipeline.dataset_norm_stats(config, layout, action_horizon=horizon)
    stats_lib.save_norm_stats(output, stats)
    return stats


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    stats = run(flags.FLAGS.config, flags.FLAGS.output)
    for key, value in stats.items():
        print(f"{key} ({value.width} dims)")
        for name in stats_lib.FIELDS:
            print(f"  {name:>4}: " + " ".join(f"{v:8.3f}" for v in getattr(value, name)))
    print(f"wrote {flags.FLAGS.output}")


if __name__ == "__main__":
    config_flags.DEFINE_config_file("config", None, "experiment config file", lock_config=True)
    flags.DEFINE_string("output", None, "norm_stats.json to write", required=True)
    flags.mark_flag_as_required("config")
    app.run(main)
