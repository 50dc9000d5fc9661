"""Tiny datasets for the data-source tests, written through the library's own LeRobot writer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pi0_armfix.data.formats.lerobot_writer import LeRobotWriter

# B1K's stored camera names (RGB only; depth is added where a test needs it).
B1K_CAMERAS = {
    "observation.images.rgb.head": (16, 16),
    "observation.images.rgb.left_wrist": (16, 16),
    "observation.images.rgb.right_wrist": (16, 16),
}
TASKS = ("pick up the trash", "turn on the radio")


def frame_colour(episode: int, frame: int, camera: int) -> np.ndarray:
    """[3] uint8 colour that identifies (episode, frame, camera); far apart so that lossy codecs
    keep frames distinguishable."""
    return np.array([16 * (frame % 16), 40 * episode % 256, 60 * camera + 8], np.uint8)


def make_episodes(num_episodes: int, *, seed: int = 0, action_width: int = 23,
                  state_width: int = 23, cameras=B1K_CAMERAS, min_length: int = 6,
                  max_length: int = 14) -> list[dict]:
    """Random episodes: {"actions": [n, A] float64, "state": [n, S], "task": str,
    "images": {camera: uint8 [n, h, w, 3]}}; every frame's image is a uniform `frame_colour`."""
    rng = np.random.default_rng(seed)
    episodes = []
    for e in range(num_episodes):
        n = int(rng.integers(min_length, max_length + 1))
        images = {}
        for c, (name, (h, w)) in enumerate(cameras.items()):
            colours = np.stack([frame_colour(e, i, c) for i in range(n)])
            images[name] = np.broadcast_to(colours[:, None, None, :], (n, h, w, 3)).copy()
        episodes.append({"actions": rng.normal(size=(n, action_width)),
                         "state": rng.normal(size=(n, state_width)),
                         "task": TASKS[e % len(TASKS)], "images": images})
    return episodes


def write_dataset(root: Path, episodes: list[dict], version: str, **writer_kwargs) -> Path:
    """Writes `episodes` as a LeRobot root of `version`; returns the root."""
    cameras = {name: images.shape[1:3] for name, images in episodes[0]["images"].items()}
    with LeRobotWriter(root, version=version, fps=10, cameras=cameras, **writer_kwargs) as writer:
        for episode in episodes:
            writer.add_episode(episode["actions"], episode["state"], episode["task"],
                               episode["images"])
    return root


def identify_frame(image: np.ndarray, episode: int, length: int, camera: int) -> int:
    """The frame of `episode` whose colour is nearest to the (decoded) image's mean colour."""
    colours = np.stack([frame_colour(episode, i, camera) for i in range(length)]).astype(float)
    return int(np.argmin(np.abs(colours - image.reshape(-1, 3).mean(0)).sum(-1)))


def late_by_one_frame(root):
    """Rewrites every data file's timestamps one frame late (as some converters write them)."""
    fps = json.loads((root / "meta" / "info.json").read_text())["fps"]
    for path in root.glob("data/chunk-*/*.parquet"):
        table = pq.read_table(path)
        late = pa.array(table.column("timestamp").to_numpy() + np.float32(1 / fps))
        pq.write_table(table.set_column(table.schema.get_field_index("timestamp"), "timestamp",
                                        late), path)
