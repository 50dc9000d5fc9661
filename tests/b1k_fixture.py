"""A small BEHAVIOR-1K 2025 dataset in the exact layout of the published one, written here.

Follows `tests/reference/b1k_2025_dataset.md` (B1K's 2025 writer: pandas + PyAV), independent of
the project's own LeRobotWriter so that the reader meets the real layout, not its own:
`meta/info.json` with B1K's keys and templates (`task-{episode_chunk:04d}` folders, 8-digit
episode files, `chunks_size` 10000, no `total_chunks`, `metainfo_path` / `annotation_path`),
non-contiguous episode ids `task_id * 10000 + instance * 10 + trajectory`, parquet columns in B1K's
order as variable-length `list<float>` with an undeclared `task_index` column, an `index` that
restarts in every episode and no `frame_index`, a per-task width of `observation.task_info`, the
256-D `observation.state`, and nine HEVC videos per episode (RGB head + wrists, 10-bit depth,
segmentation) encoded with x265 defaults (one keyframe per episode, B-frames).

Every RGB frame is a uniform colour that identifies (episode, frame, camera)
(`data_fixtures.frame_colour`), so a test can tell which frame was decoded.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from data_fixtures import frame_colour

FPS = 30
STATE_WIDTH = 256
RGB = ("head", "left_wrist", "right_wrist")
# (task id, instance, trajectory) of each episode; ids 10, 20, 10010, 10020, 20010, 20020.
EPISODES = ((0, 1, 0), (0, 2, 0), (1, 1, 0), (1, 2, 0), (2, 1, 0), (2, 2, 0))
TASKS = ("picking up trash", "turning on radio", "putting away toys")
TASK_INFO_WIDTH = (22, 34, 46)  # 10 robot values + 12 per object


def episode_id(task: int, instance: int, trajectory: int) -> int:
    return task * 10000 + instance * 10 + trajectory


def _encode(path: Path, frames: np.ndarray, pix_fmt: str) -> None:
    """HEVC with x265's defaults (one keyframe, B-frames) and no explicit frame timestamps."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx265", rate=FPS)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = pix_fmt
        stream.options = {"x265-params": "log-level=none"}
        for image in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


def _list_column(rows: list[np.ndarray]) -> pa.Array:
    return pa.array([r.astype(np.float32).tolist() for r in rows], pa.list_(pa.float32()))


def write_b1k_dataset(root: Path, *, lengths=(14, 9, 12, 10, 11, 13), head: int = 24,
                      wrist: int = 16, seed: int = 0, timestamp_offset_frames: int = 0
                      ) -> dict[int, dict[str, np.ndarray]]:
    """Writes the dataset; returns `{episode id: {"action" [n, 23], "state" [n, 256]}}`.

    Args:
      root: the dataset root to create.
      lengths: frames of each episode of `EPISODES`.
      head, wrist: RGB image sides (720 / 480 in the real data).
      timestamp_offset_frames: shifts every row's timestamp by this many frames (a known fault of
        converted sets: the last row then lies past the end of its video).
    """
    rng = np.random.default_rng(seed)
    root = Path(root)
    data = {}
    records, stats = [], []
    sizes = {"head": head, "left_wrist": wrist, "right_wrist": wrist}
    for position, ((task, instance, trajectory), n) in enumerate(zip(EPISODES, lengths)):
        index = episode_id(task, instance, trajectory)
        action = rng.normal(size=(n, 23)).astype(np.float32)
        state = rng.normal(size=(n, STATE_WIDTH)).astype(np.float32)
        task_info = rng.normal(size=(n, TASK_INFO_WIDTH[task])).astype(np.float32)
        data[index] = {"action": action, "state": state}
        timestamps = (np.arange(n) + timestamp_offset_frames) / FPS
        table = pa.table({
            "index": pa.array(np.arange(n, dtype=np.int64)),
            "episode_index": pa.array(np.full(n, index, np.int64)),
            "task_index": pa.array(np.full(n, task, np.int64)),
            "timestamp": pa.array(timestamps.astype(np.float64)),
            "observation.state": _list_column(list(state)),
            "observation.cam_rel_poses": _list_column(list(rng.normal(size=(n, 21)))),
            "action": _list_column(list(action)),
            "observation.task_info": _list_column(list(task_info)),
        })
        chunk = f"task-{task:04d}"
        path = root / "data" / chunk / f"episode_{index:08d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        for c, camera in enumerate(RGB):
            side = sizes[camera]
            colours = np.stack([frame_colour(position, i, c) for i in range(n)])
            rgb = np.broadcast_to(colours[:, None, None, :], (n, side, side, 3)).copy()
            video = root / "videos" / chunk / "{}" / f"episode_{index:08d}.mp4"
            _encode(Path(str(video).format(f"observation.images.rgb.{camera}")), rgb, "yuv420p")
            _encode(Path(str(video).format(f"observation.images.depth.{camera}")),
                    255 - rgb, "yuv420p10le")
            _encode(Path(str(video).format(f"observation.images.seg_instance_id.{camera}")),
                    rgb // 2, "yuv420p")
        records.append({"episode_index": index, "tasks": [TASKS[task]], "length": n,
                        "distance_traveled": float(rng.uniform(0, 5)),
                        "left_eef_displacement": float(rng.uniform(0, 1)),
                        "right_eef_displacement": float(rng.uniform(0, 1))})
        stats.append({"episode_index": index, "stats": {
            key: {"min": v.min(0).tolist(), "max": v.max(0).tolist(),
                  "mean": v.mean(0).tolist(), "std": v.std(0).tolist(),
                  "q01": np.quantile(v, 0.01, 0).tolist(), "q99": np.quantile(v, 0.99, 0).tolist(),
                  "count": [n]}
            for key, v in (("action", action), ("observation.state", state))}})
    _write_meta(root, records, stats, sizes)
    return data


def _write_meta(root: Path, records: list[dict], stats: list[dict], sizes: dict[str, int]
                ) -> None:
    def video(side: int, pix_fmt: str, depth: bool = False) -> dict:
        feature = {"dtype": "video", "shape": [side, side, 3],
                   "names": ["height", "width", "channels"],
                   "info": {"video.fps": FPS, "video.height": side, "video.width": side,
                            "video.channels": 3, "video.codec": "hevc",
                            "video.pix_fmt": pix_fmt, "video.is_depth_map": depth,
                            "has_audio": False}}
        return feature

    features = {}
    for camera in RGB:
        side = sizes[camera]
        features[f"observation.images.rgb.{camera}"] = video(side, "yuv420p")
        features[f"observation.images.depth.{camera}"] = video(side, "yuv420p16le", True)
        features[f"observation.images.seg_instance_id.{camera}"] = video(side, "yuv420p")
    features.update({
        "action": {"dtype": "float32", "shape": [23], "names": None},
        "observation.state": {"dtype": "float32", "shape": [STATE_WIDTH], "names": None},
        "observation.cam_rel_poses": {"dtype": "float32", "shape": [21], "names": None},
        "observation.task_info": {"dtype": "float32", "shape": [None], "names": None},
        "timestamp": {"dtype": "float64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
    })
    info = {
        "codebase_version": "v2.1", "robot_type": "R1Pro",
        "total_episodes": len(records), "total_frames": sum(r["length"] for r in records),
        "total_tasks": len({r["tasks"][0] for r in records}), "total_videos": 9 * len(records),
        "chunks_size": 10000, "fps": FPS, "splits": {"train": f"0:{len(records)}"},
        "data_path": "data/task-{episode_chunk:04d}/episode_{episode_index:08d}.parquet",
        "video_path": "videos/task-{episode_chunk:04d}/{video_key}/"
                      "episode_{episode_index:08d}.mp4",
        "metainfo_path": "meta/episodes/task-{episode_chunk:04d}/episode_{episode_index:08d}.json",
        "annotation_path": "annotations/task-{episode_chunk:04d}/"
                           "episode_{episode_index:08d}.json",
        "features": features,
    }
    meta = root / "meta"
    meta.mkdir(parents=True, exist_ok=True)
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    lines = lambda rows: "".join(json.dumps(r) + "\n" for r in rows)  # noqa: E731
    (meta / "episodes.jsonl").write_text(lines(records))
    (meta / "episodes_stats.jsonl").write_text(lines(stats))
    (meta / "tasks.jsonl").write_text(lines(
        {"task_index": t, "task_name": name.replace(" ", "_"), "task": name}
        for t, name in enumerate(TASKS)))


def state_index_map() -> dict[str, tuple[int, int]]:
    """The published 256-D state index map, parsed from `tests/reference/b1k_2025_dataset.md`:
    `{content: (start, stop)}`."""
    text = (Path(__file__).parent / "reference" / "b1k_2025_dataset.md").read_text()
    section = text.split("## observation.state (256-D) index map")[1]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 2 and ":" in cells[0] and cells[0][0].isdigit():
            start, stop = (int(v) for v in cells[0].split(":"))
            rows[cells[1]] = (start, stop)
    return rows
