"""Lists the arm-heavy training episodes, for the curriculum's `arm_heavy` source.

    python -m pi0_armfix.tools.filter_arm_heavy_episodes --config=configs/arm_curriculum.py \
        [--config.data.root=DIR] --output=arm_heavy.json \
        [--arm_ratio_threshold=1.5] [--min_arm_movement=0.1] [--max_base_movement=X] \
        [--episodes=train|all]

Per episode, over its real frame pairs (never across an episode boundary), the motion of each
group in z-score units of the run's norm stats, relative to the group's mean over all analysed
episodes (1 = typical): the frame-to-frame change for a position group (arms, torso, grippers),
the magnitude of the command itself for a velocity group (`layout.velocity_groups`, the B1K base),
so a base driving at a constant speed counts as moving. Manipulation groups: role "arm" or
"gripper" (`layout.roles`); they are compared with the base (role "base") or, on a fixed-base
robot, with the other groups. `arm_movement` / `base_movement` are the mean
relative motion over the arm / base groups, `arm_to_base_ratio` their ratio; an episode is
selected iff ratio >= arm_ratio_threshold, arm_movement >= min_arm_movement and (if given)
base_movement <= max_base_movement. Full definitions: `pi0_armfix.data.statistics.motion`.

Writes `{"episodes": [dataset episode ids], "per_episode": [...], "thresholds": {...}}`; set
`--config.data.arm_heavy_episodes` to it. With that key '' the curriculum selects the same
episodes on the fly with the default thresholds. `--episodes=train` (the default) analyses the
training episodes only, as the curriculum does; `--episodes=all` adds the held-out ones (the
curriculum never trains on them). The tool prints which episodes and how many frames it reads.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import ml_collections
from absl import app, flags
from ml_collections import config_flags

from pi0_armfix import console
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.model import config as model_config_lib


def run(config: ml_collections.ConfigDict, output: str | Path,
        thresholds: motion_lib.ArmHeavyThresholds = motion_lib.ArmHeavyThresholds(),
        episodes: str = "train") -> dict[str, Any]:
    layout = ActionLayout.from_config(config.layout)
    motion_lib.arm_heavy_groups(layout)  # the layout can be filtered, before any pass
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    spec = DataSpec.from_config(config, layout)
    source = sources.open_source(spec.options, layout)
    spec = dataset_lib.reading_spec(spec, episodes)
    chosen = dataset_lib.select_episodes(spec, source, episodes)
    dataset_lib.check_data(spec, source, images=False)
    print(dataset_lib.describe_episodes(spec, source, chosen))
    stats = dataset_lib.load_or_compute_norm_stats(spec, action_horizon=horizon,
                                                   source=source, episodes=chosen)
    summary = dataset_lib.dataset_motion(spec, stats["actions"], source=source,
                                         episodes=chosen)
    selected, per_episode = motion_lib.arm_heavy_episodes(summary, layout, thresholds)
    result = {"episodes": selected.tolist(), "per_episode": per_episode,
              "thresholds": thresholds.to_json()}
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(result, indent=2))
    return result


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    thresholds = motion_lib.ArmHeavyThresholds(
        arm_ratio_threshold=flags.FLAGS.arm_ratio_threshold,
        min_arm_movement=flags.FLAGS.min_arm_movement,
        max_base_movement=flags.FLAGS.max_base_movement)
    with console.user_errors("pi0_armfix.tools.filter_arm_heavy_episodes"):
        result = run(flags.FLAGS.config, flags.FLAGS.output, thresholds, flags.FLAGS.episodes)
    total = len(result["per_episode"])
    print(f"{len(result['episodes'])} of the {total} episodes read are arm-heavy "
          f"({thresholds.to_json()}); wrote {flags.FLAGS.output}")



def cli() -> None:
    """The `pi0-armfix-filter-arm-heavy-episodes` console script (also `python -m
    pi0_armfix.tools.filter_arm_heavy_episodes`)."""
    config_flags.DEFINE_config_file("config", None, "experiment config file", lock_config=True)
    flags.DEFINE_string("output", None, "JSON file to write", required=True)
    flags.DEFINE_float("arm_ratio_threshold", 1.5, "minimum arm-to-base relative motion ratio")
    flags.DEFINE_float("min_arm_movement", 0.1, "minimum relative arm motion")
    flags.DEFINE_float("max_base_movement", None, "maximum relative base motion (unset = none)")
    flags.DEFINE_enum("episodes", "train", dataset_lib.EPISODE_CHOICES,
                      "train: all but the eval.episodes held out (as the curriculum); all: every one")
    flags.mark_flag_as_required("config")
    app.run(main, flags_parser=console.config_flags_parser("pi0_armfix.tools.filter_arm_heavy_episodes"))


if __name__ == "__main__":
    cli()
