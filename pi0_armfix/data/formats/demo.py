"""The built-in demo dataset: B1K-like mobile-manipulation episodes generated from a seed.

Each episode follows a task plan of navigation and manipulation phases, as a BEHAVIOR-1K
teleoperator would: drive to an object with the arms still, stop, reach with one or both arms
(base still), close or open the gripper, retract, drive on. Actions follow the B1K R1Pro layout
(docs/design.md §2): base velocity 0:3, torso 3:7 (dim 6 constant 0), left arm 7:14, left gripper
14, right arm 15:22, right gripper 22; the gripper is +1 open / -1 closed. It is written as a
LeRobot v2.1 dataset with three small PNG cameras and a task prompt per episode.

The world, its physics, its cameras and its task plans live in `pi0_armfix.sim.world` (the one
source of truth, shared with the closed-loop environment `pi0_armfix.sim.env`); the operator is
`pi0_armfix.sim.expert.ScriptedTeleoperator`. An episode is the operator acting in the world,
recorded frame by frame: the cameras and the state before each action, and the action. Parameters
are `DemoSpec`'s; the defaults give 120 episodes of 200-1000 frames, ~66k frames in all, at 30 fps
(~20 s to generate on 2 cores, 27 MiB).

Calibration: arm and torso postures are drawn around the published B1K means with `posture_spread`
times the published standard deviations, inside the published 1%-99% quantiles, from a
low-discrepancy sequence over episode numbers, so even a small demo matches the published statistics
(`pi0_armfix/reference/b1k_2025_norm_stats.json`); the five tasks balance their arm use so that each
gripper is closed about a third of the time, as in B1K. Cameras: the head shows the current target,
the wrists the fingers, a held object and the remaining reach offset (`pi0_armfix.sim.world`). State
(23-D, the official baseline STATE order): base velocity 0:3, torso 3:7, left arm 7:14, right arm
14:21, finger gaps 21, 22 in [0, 0.1].

Same spec -> byte-identical files. `demo_root()` generates the default demo once into a cache
folder, atomically.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pi0_armfix.cache import build_lock, cache_root, digest
from pi0_armfix.data.formats.lerobot_writer import LeRobotWriter
from pi0_armfix.sim import render
from pi0_armfix.sim.expert import demonstration
from pi0_armfix.sim.world import TASKS, DemoSpec, World  # noqa: F401 (TASKS: the demo's tasks)

DEMO_VERSION = "demo-v2"  # v2: recorded from the world of pi0_armfix.sim
CAMERAS = ("observation.images.rgb.head", "observation.images.rgb.left_wrist",
           "observation.images.rgb.right_wrist")

# ====================================================================== episodes and files


def generate_episode(spec: DemoSpec, index: int) -> dict:
    """Episode `index` of the demo: {"actions": [n, 23] float32, "state": [n, 23] float32,
    "task": prompt, "images": {camera name: uint8 [n, S, S, 3]}, "results": [PhaseResult]}.
    Depends only on (spec, index)."""
    world = World(spec, index)
    scenes, states, actions = [], [], []
    for action in demonstration(world):
        scenes.append(world.scene())
        states.append(world.state())
        actions.append(action)
    images = render.render(scenes, world.task.colour, spec.image_size)
    return {"actions": np.asarray(actions, np.float32), "state": np.asarray(states, np.float32),
            "task": world.task.prompt, "results": world.results,
            "images": {CAMERAS[0]: images["head"], CAMERAS[1]: images["left_wrist"],
                       CAMERAS[2]: images["right_wrist"]}}


def _write(root: Path, spec: DemoSpec, version: str, video: VideoSpec | None) -> None:
    size = (spec.image_size, spec.image_size)
    encoding = (dict(image_format="png") if video is None else
                dict(image_format="video", video_codec=video.codec, video_gop=video.gop,
                     video_crf=video.crf, video_options=(
                         {"x265-params": "log-level=none"} if video.codec == "libx265" else None)))
    with LeRobotWriter(root, version=version, fps=spec.fps, cameras={c: size for c in CAMERAS},
                       **encoding) as writer:
        for index in tqdm(range(spec.num_episodes), desc="demo episodes", unit="ep"):
            episode = generate_episode(spec, index)
            writer.add_episode(episode["actions"], episode["state"], episode["task"],
                               episode["images"])


@dataclasses.dataclass(frozen=True)
class VideoSpec:
    """The cameras as mp4 video features instead of PNG images inside the parquet files: `codec`
    (a PyAV encoder; "libx265" is B1K's HEVC), `gop` frames between keyframes (B1K 2025: one
    keyframe per episode, so any gop at least the longest episode; B1K 2026: 8), `crf` the
    encoder's quality (lower is closer to the rendered pixels)."""
    codec: str = "libx265"
    gop: int = 8
    crf: int = 10


def write_demo_dataset(output: str | Path, spec: DemoSpec = DemoSpec(), version: str = "v2.1",
                       video: VideoSpec | None = None) -> Path:
    """Writes the demo as a LeRobot root of `version` (the cached default demo: v2.1, PNG
    cameras; `video`: mp4 cameras) at `output` (which must not exist), atomically: into a
    temporary sibling folder first, renamed when complete."""
    output = Path(output)
    if output.exists():
        raise ValueError(f"{output} already exists; choose a new output folder")
    output.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{output.name}.partial-", dir=output.parent))
    try:
        _write(staging / "dataset", spec, version, video)
        os.rename(staging / "dataset", output)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return output


def demo_root(cache_dir: str | Path | None = None, spec: DemoSpec | None = None) -> Path:
    """The default demo dataset, generated on first use (~30 s).

    Lives in `<cache>/demo-<hash>`, where `<cache>` is `cache_root(cache_dir)` and the hash is of
    the generator version and every field of `spec` (default `DemoSpec()`): a changed generator
    or spec is a new folder, never the old files. Concurrent callers (several training processes)
    wait on a file lock; a crash leaves no half-written dataset.
    """
    spec = spec or DemoSpec()
    root = demo_cache_path(cache_root(cache_dir), spec)
    if (root / "meta" / "info.json").is_file():
        return root
    with build_lock(root):
        if not (root / "meta" / "info.json").is_file():
            write_demo_dataset(root, spec)
    return root


def demo_cache_path(cache: Path, spec: DemoSpec) -> Path:
    """`<cache>/demo-<hash of the generator version and the spec>`."""
    return cache / f"demo-{digest([DEMO_VERSION, dataclasses.asdict(spec)])}"
