"""`open_source(config.data, layout)`: the dataset a config names, behind one Source interface.

Config keys read here (`config.data`):
  root           dataset location; '' = the built-in demo dataset (generated on first use).
  format         "lerobot" (v2.0 / v2.1 / v3.0, detected from meta/info.json) or "rlds"
                 (a TFDS builder directory of array_record files, read with `tfds.data_source`).
  cameras        optional {batch camera: stored camera name}; unset = automatic match
                 (`pi0_armfix.data.cameras`).
  images         False: no camera is read (every batch camera an all-zero image, masked out), for
                 a dataset whose videos are not on this machine; its video files are never probed.
  action_key, state_key     LeRobot: the stored action / state features (default `action`,
                 `observation.state`).
  state_preset, state_indices, action_indices   LeRobot: which stored dims the model sees
                 (`pi0_armfix.data.selection`; B1K's 256-D state needs `state_preset='b1k_r1pro'`).
  video_tolerance_frames    LeRobot: how far a row's timestamp may lie from its video frame.
  skip_missing_videos       LeRobot: leave out the episodes whose video files are missing
                 (named in one line) instead of refusing them.
  frame_cache    LeRobot: decode the video frames once at the model's size into an on-disk
                 cache (`image_store`) and read them from there.
  split          optional, RLDS only: the split to read (default "train").
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data.episodes import EpisodeTable

FORMATS = ("lerobot", "rlds")


class Source(Protocol):
    """What every data source provides. Episodes are named by their ids (`episode_index`)."""

    num_episodes: int
    episode_index: np.ndarray  # [E] int64 episode ids
    episode_lengths: np.ndarray  # [E] int64 frames per episode
    tasks: Sequence[str]  # [E] prompts
    fps: float
    cameras: Mapping[str, str]  # batch camera -> stored camera name
    block_keys: tuple[str, ...]  # the `iter_blocks` keys it has ("timestamp" for video)

    def iter_blocks(self, keys: Sequence[str] = ("actions", "state"),
                    episodes: Sequence[int] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """Bounded-memory stream of `{key: [n, ...], "episode_index": [n] int64}` in episode
        order."""

    def identity(self) -> dict[str, Any]:
        """What its frames depend on (JSON-able): the key of its `FrameStore`."""

    def episode_file(self, episode: int) -> str:
        """Where an episode is stored, for messages ("file PATH")."""

    def load_table(self, episodes: Sequence[int] | None = None, *, images: bool = True,
                   image_size: tuple[int, int] | None = None) -> EpisodeTable:
        """The chosen episodes (None = all) as an EpisodeTable: columns read by row from its
        `frame_store`, lazy images (video decoded to fit inside `image_size`)."""


def open_source(data_cfg: Mapping[str, Any], layout: ActionLayout) -> Source:
    """The Source named by `config.data` (see the module docstring for its keys)."""
    fmt = data_cfg.get("format", "lerobot")
    if fmt not in FORMATS:
        raise ValueError(f"data.format {fmt!r} is not supported; choose one of {list(FORMATS)}")
    root = data_cfg.get("root", "")
    cameras = dict(data_cfg.get("cameras") or {}) or None
    images = bool(data_cfg.get("images", True))
    if fmt == "rlds":
        if not root:
            raise ValueError("data.root is '' (the built-in demo dataset, a LeRobot dataset) but "
                             "data.format is 'rlds'; set data.format='lerobot' or a data.root")
        # TFDS is slow to import: only load it here
        from pi0_armfix.data.formats.rlds import RldsSource

        return RldsSource(root, layout, split=data_cfg.get("split", "train"), cameras=cameras,
                          use_images=images)
    from pi0_armfix.data.formats.lerobot import LeRobotSource

    if not root:
        from pi0_armfix.data.formats.demo import demo_root

        root = demo_root()
    return LeRobotSource(
        root, layout, cameras=cameras, action_key=data_cfg.get("action_key") or "action",
        state_key=data_cfg.get("state_key") or "observation.state",
        state_indices=data_cfg.get("state_indices") or None,
        state_preset=selection_lib.state_preset(data_cfg),
        action_indices=data_cfg.get("action_indices") or None,
        video_tolerance_frames=float(data_cfg.get("video_tolerance_frames") or 0.5),
        images=images, skip_missing_videos=bool(data_cfg.get("skip_missing_videos", False)),
        frame_cache=bool(data_cfg.get("frame_cache", False)))
