"""Writes the B1K-like demo dataset (see `pi0_armfix.data.formats.demo`) to a new folder.

  python -m pi0_armfix.tools.make_demo_dataset --output=/tmp/demo [--episodes=100] [--seed=0] \
      [--version=v2.1|v3.0] [--video_codec=libx265 --video_gop=8]

`--video_codec` writes the cameras as mp4 video (as B1K publishes them) instead of PNG images in
the parquet files; `--video_gop` is the number of frames between keyframes (B1K 2026: 8; B1K 2025:
one keyframe per episode, e.g. `--video_gop=100000`).

`--version=v3.0` writes LeRobot's current layout (LeRobot 0.4 reads it); the default, v2.1, is
the layout of the cached demo the study's results were measured on (LeRobot 0.3 reads it).

Training on it: `--config.data.root=/tmp/demo` (an empty data.root uses the cached default demo).
"""

from __future__ import annotations

import dataclasses

from absl import app, flags

from pi0_armfix import console
from pi0_armfix.data.formats import demo

_OUTPUT = flags.DEFINE_string("output", None, "New folder to write the dataset into.",
                              required=True)
_EPISODES = flags.DEFINE_integer("episodes", demo.DemoSpec.num_episodes, "Number of episodes.")
_SEED = flags.DEFINE_integer("seed", demo.DemoSpec.seed, "Generator seed.")
_VERSION = flags.DEFINE_enum("version", "v2.1", ["v2.0", "v2.1", "v3.0"],
                             "LeRobot layout version.")
_VIDEO_CODEC = flags.DEFINE_string("video_codec", "", "PyAV encoder of mp4 cameras (e.g. "
                                   "libx265, libx264); empty: PNG images in the parquet files.")
_VIDEO_GOP = flags.DEFINE_integer("video_gop", demo.VideoSpec.gop,
                                  "Frames between keyframes of mp4 cameras.")


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    with console.user_errors("pi0_armfix.tools.make_demo_dataset"):
        if _EPISODES.value < 1:
            raise ValueError(f"--episodes must be >= 1, got {_EPISODES.value}")
        if _VIDEO_GOP.value < 1:
            raise ValueError(f"--video_gop must be >= 1, got {_VIDEO_GOP.value}")
        spec = dataclasses.replace(demo.DemoSpec(), num_episodes=_EPISODES.value,
                                   seed=_SEED.value)
        video = (demo.VideoSpec(codec=_VIDEO_CODEC.value, gop=_VIDEO_GOP.value)
                 if _VIDEO_CODEC.value else None)
        root = demo.write_demo_dataset(_OUTPUT.value, spec, _VERSION.value, video)
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    print(f"wrote {spec.num_episodes} episodes to {root} (LeRobot {_VERSION.value}, "
          f"{'PNG images' if video is None else f'{video.codec} video, GOP {video.gop}'}, "
          f"{size / 2**20:.1f} MiB)")



def cli() -> None:
    """The `pi0-armfix-make-demo-dataset` console script (also `python -m
    pi0_armfix.tools.make_demo_dataset`)."""
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.make_demo_dataset"))


if __name__ == "__main__":
    cli()
