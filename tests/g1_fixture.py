"""A small Unitree G1 (Inspire hands) dataset in the exact layout of the published one, written here.

The layout of `YifanTian07/G1-policy-train` (docs/data.md, "A real robot"), independent
of the project's own LeRobotWriter so that the reader meets the real layout, not its own: LeRobot
v2.1, `meta/info.json` with its keys (`robot_type` "Unitree_G1_Inspire", `chunks_size` 1000,
`total_chunks`, `splits`, the joint names of both 26-D vectors), `meta/episodes.jsonl`,
`meta/episodes_stats.jsonl` (per-episode min / max / mean / std / count) and `meta/tasks.jsonl`;
parquet columns `observation.state` and `action` as `fixed_size_list<float>[26]`, `timestamp`
float32, `frame_index`, `episode_index`, `index` (global) and `task_index` int64, in that order;
one camera, `observation.images.cam_high`, AV1 (yuv420p) with a keyframe every 2 frames as the
published files have, at 48x64 instead of 480x640 (the same aspect) to stay small.

The actions follow the published set's structure: the left arm and hand idle, each commanded at a
fixed offset from its measured position (a controller's steady-state error), the right arm and
hand moving. Every frame is a uniform colour that identifies (episode, frame)
(`data_fixtures.frame_colour`), so a test can tell which frame was decoded. `missing_videos`
leaves some episodes' video files out, as the stored snapshot lacks 7 of the published 100.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from data_fixtures import frame_colour

FPS = 30
HEIGHT, WIDTH = 48, 64
CAMERA = "observation.images.cam_high"
TASK = "Pick up the yellow bottle on the table."
JOINTS = [f"k{side}{joint}" for side in ("Left", "Right") for joint in (
    "ShoulderPitch", "ShoulderRoll", "ShoulderYaw", "Elbow", "WristRoll", "WristPitch",
    "WristYaw")] + [f"k{side}Hand{finger}" for side in ("Left", "Right") for finger in (
        "Pinky", "Ring", "Middle", "Index", "ThumbBend", "ThumbRotation")]
LENGTHS = (40, 36, 44, 38, 42, 34)
IDLE = np.r_[0:7, 14:20]  # the left arm and hand


def _vector(name: str) -> dict:
    return {"dtype": "float32", "shape": [len(JOINTS)], "names": [JOINTS]}


def _scalar(dtype: str) -> dict:
    return {"dtype": dtype, "shape": [1], "names": None}


def info(lengths=LENGTHS) -> dict:
    return {
        "codebase_version": "v2.1", "robot_type": "Unitree_G1_Inspire",
        "total_episodes": len(lengths), "total_frames": int(sum(lengths)), "total_tasks": 1,
        "total_videos": len(lengths), "total_chunks": 1, "chunks_size": 1000, "fps": FPS,
        "splits": {"train": f"0:{len(lengths)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": ("videos/chunk-{episode_chunk:03d}/{video_key}/"
                       "episode_{episode_index:06d}.mp4"),
        "features": {
            "observation.state": _vector("observation.state"), "action": _vector("action"),
            CAMERA: {"dtype": "video", "shape": [HEIGHT, WIDTH, 3],
                     "names": ["height", "width", "channel"],
                     "info": {"video.height": HEIGHT, "video.width": WIDTH,
                              "video.codec": "av1", "video.pix_fmt": "yuv420p",
                              "video.is_depth_map": False, "video.fps": FPS,
                              "video.channels": 3, "has_audio": False}},
            "timestamp": _scalar("float32"), "frame_index": _scalar("int64"),
            "episode_index": _scalar("int64"), "index": _scalar("int64"),
            "task_index": _scalar("int64")},
    }


def episode_arrays(episode: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """`(state, action)` `[T, 26]` float32: idle left side at an offset, moving right side; the
    action leads the state by one frame on the moving side."""
    rng = np.random.default_rng(episode)
    t = np.arange(length + 1)[:, None] / FPS
    position = rng.uniform(-0.5, 0.5, size=26) + 0.4 * np.sin(
        2 * np.pi * rng.uniform(0.2, 0.6, size=26) * t + rng.uniform(0, 6, size=26))
    position[:, IDLE] = position[0, IDLE] + rng.normal(scale=2e-4, size=(length + 1, len(IDLE)))
    offset = np.zeros(26)
    offset[IDLE] = rng.uniform(0.01, 0.06, size=len(IDLE))
    state = position[:-1]
    action = np.where(np.isin(np.arange(26), IDLE), position[:-1] + offset, position[1:])
    return state.astype(np.float32), action.astype(np.float32)


def _stats(x: np.ndarray) -> dict:
    return {"min": x.min(0).tolist(), "max": x.max(0).tolist(), "mean": x.mean(0).tolist(),
            "std": x.std(0).tolist(), "count": [len(x)]}


def _encode_av1(path: Path, frames: np.ndarray) -> None:
    """AV1 (SVT-AV1, as LeRobot's encoder writes it) with a keyframe every 2 frames."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libsvtav1", rate=FPS)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv420p"
        stream.options = {"g": "2", "preset": "12", "svtav1-params": "log-level=0"}
        for image in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


def write_g1_dataset(root: Path, lengths=LENGTHS, missing_videos=()) -> dict[int, tuple]:
    """Writes the dataset; returns `{episode: (state, action)}` as written."""
    root = Path(root)
    (root / "meta").mkdir(parents=True, exist_ok=True)
    (root / "meta" / "info.json").write_text(json.dumps(info(lengths), indent=4))
    (root / "meta" / "tasks.jsonl").write_text(
        json.dumps({"task_index": 0, "task": TASK}) + "\n")
    written, episodes, stats, index = {}, [], [], 0
    for episode, length in enumerate(lengths):
        state, action = episode_arrays(episode, length)
        written[episode] = (state, action)
        vector = pa.list_(pa.float32(), len(JOINTS))
        table = pa.table({
            "observation.state": pa.array(state.tolist(), vector),
            "action": pa.array(action.tolist(), vector),
            "timestamp": pa.array(np.arange(length, dtype=np.float32) / FPS, pa.float32()),
            "frame_index": pa.array(np.arange(length), pa.int64()),
            "episode_index": pa.array(np.full(length, episode), pa.int64()),
            "index": pa.array(np.arange(index, index + length), pa.int64()),
            "task_index": pa.array(np.zeros(length, np.int64), pa.int64())})
        path = root / "data" / "chunk-000" / f"episode_{episode:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        index += length
        episodes.append({"episode_index": episode, "tasks": [TASK], "length": length})
        stats.append({"episode_index": episode, "stats": {
            "observation.state": _stats(state), "action": _stats(action)}})
        if episode not in missing_videos:
            frames = np.stack([np.broadcast_to(frame_colour(episode, f, 0), (HEIGHT, WIDTH, 3))
                               for f in range(length)]).astype(np.uint8)
            _encode_av1(root / "videos" / "chunk-000" / CAMERA / f"episode_{episode:06d}.mp4",
                        frames)
    for name, rows in (("episodes.jsonl", episodes), ("episodes_stats.jsonl", stats)):
        (root / "meta" / name).write_text("".join(json.dumps(r) + "\n" for r in rows))
    return written
