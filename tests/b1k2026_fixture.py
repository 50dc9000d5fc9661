"""A small BEHAVIOR-1K 2026 dataset in the exact layout of the published one, written here.

Follows `tests/reference/b1k_2026_dataset.md` (`behavior-1k/2026-challenge-demos`), independent
of the project's own LeRobotWriter so that the reader meets the real layout, not its own: LeRobot
v3.0 with **chunk = task** (`data/chunk-{task:03d}/file-000.parquet` holds all of a task's
episodes), global contiguous episode ids `task * DEMOS + demo`, the snake_case task *name* as the
episodes' task with the prompts in `meta/tasks.jsonl`, the 61-D state (two finger positions per
gripper), the 23-D action, `observation.robot2cam_pose.*`, `next.*` columns, and per task and
camera **one concatenated HEVC mp4** with a keyframe every 8 frames and no B-frames, RGB beside
`depth_linear` (which no run reads), each episode located by `videos/<key>/from_timestamp` ..
`to_timestamp` in `meta/episodes`, with B1K's extra episode columns (`raw_episode_id`,
`demo_index_within_task`, `task_instance_id`, `annotation_path`).

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
STATE_WIDTH = 61
DEMOS = 3  # demos per task (200 in the published set)
TASKS = (("turning_on_radio", "turn on the radio"), ("picking_up_trash", "pick up the trash"))
RGB = {"observation.rgb.zed_link_camera_0": 24,
       "observation.rgb.left_realsense_link_camera_0": 16,
       "observation.rgb.right_realsense_link_camera_0": 16}
DEPTH = {key.replace(".rgb.", ".depth_linear."): side for key, side in RGB.items()}
# The published state's blocks (tests/reference/b1k_2026_dataset.md).
STATE_BLOCKS = {"base_qvel": (0, 3), "arm_left_qpos": (3, 10), "gripper_left_qpos": (24, 26),
                "arm_right_qpos": (28, 35), "gripper_right_qpos": (49, 51),
                "trunk_qpos": (53, 57)}


def _encode(path: Path, frames: np.ndarray, pix_fmt: str) -> None:
    """HEVC as B1K 2026's writer: a keyframe every 8 frames, no B-frames, crf 30."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx265", rate=FPS)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = pix_fmt
        stream.options = {"crf": "30", "x265-params":
                          "log-level=none:keyint=8:min-keyint=8:bframes=0:scenecut=0"}
        for image in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


def _list_column(rows: np.ndarray) -> pa.Array:
    return pa.array([r.astype(np.float32).tolist() for r in rows], pa.list_(pa.float32()))


def write_b1k2026_dataset(root: Path, *, lengths=(14, 9, 12, 10, 11, 13), seed: int = 0
                          ) -> dict[int, dict[str, np.ndarray]]:
    """Writes the dataset; returns `{episode id: {"action" [n, 23], "state" [n, 61]}}`.

    Args:
      root: the dataset root to create.
      lengths: frames of each episode, task-major (`DEMOS` per task).
    """
    rng = np.random.default_rng(seed)
    root = Path(root)
    data, records, first = {}, [], 0
    for task, (name, _) in enumerate(TASKS):
        episodes = range(task * DEMOS, (task + 1) * DEMOS)
        tables, frames = [], {key: [] for key in (*RGB, *DEPTH)}
        start_time = 0.0
        for episode in episodes:
            n = lengths[episode]
            action = rng.normal(size=(n, 23)).astype(np.float32)
            state = rng.normal(size=(n, STATE_WIDTH)).astype(np.float32)
            data[episode] = {"action": action, "state": state}
            columns = {
                "index": pa.array(np.arange(first, first + n, dtype=np.int64)),
                "episode_index": pa.array(np.full(n, episode, np.int64)),
                "frame_index": pa.array(np.arange(n, dtype=np.int64)),
                "timestamp": pa.array((np.arange(n) / FPS).astype(np.float32)),
                "task_index": pa.array(np.full(n, task, np.int64)),
                "observation.state": _list_column(state),
                "action": _list_column(action),
            }
            for key in RGB:
                pose = rng.normal(size=(n, 7))
                columns[key.replace("observation.rgb.", "observation.robot2cam_pose.")] = \
                    _list_column(pose)
            columns |= {"next.reward": pa.array(np.zeros(n, np.float32)),
                        "next.terminated": pa.array(np.arange(n) == n - 1),
                        "next.truncated": pa.array(np.zeros(n, bool))}
            tables.append(pa.table(columns))
            for c, (key, side) in enumerate(RGB.items()):
                colours = np.stack([frame_colour(episode, i, c) for i in range(n)])
                rgb = np.broadcast_to(colours[:, None, None, :], (n, side, side, 3))
                frames[key].append(rgb)
                frames[key.replace(".rgb.", ".depth_linear.")].append(255 - rgb)
            record = {"episode_index": episode, "tasks": [name], "length": n,
                      "data/chunk_index": task, "data/file_index": 0,
                      "dataset_from_index": first, "dataset_to_index": first + n,
                      "raw_episode_id": (task + 1) * 10000 + (episode % DEMOS) * 10,
                      "demo_index_within_task": episode % DEMOS,
                      "task_instance_id": episode % DEMOS + 1,
                      "annotation_path": f"annotations/task-{task:04d}/episode_{episode:08d}.json",
                      "meta/episodes/chunk_index": task, "meta/episodes/file_index": 0}
            for key in (*RGB, *DEPTH):
                record |= {f"videos/{key}/chunk_index": task, f"videos/{key}/file_index": 0,
                           f"videos/{key}/from_timestamp": start_time,
                           f"videos/{key}/to_timestamp": start_time + n / FPS}
            records.append(record)
            start_time += n / FPS
            first += n
        path = root / "data" / f"chunk-{task:03d}" / "file-000.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.concat_tables(tables), path)
        for key, parts in frames.items():
            video = root / "videos" / key / f"chunk-{task:03d}" / "file-000.mp4"
            _encode(video, np.concatenate(parts), "yuv420p" if key in RGB else "yuv420p10le")
        episodes_file = root / "meta" / "episodes" / f"chunk-{task:03d}" / "file-000.parquet"
        episodes_file.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist([r for r in records
                                             if r["data/chunk_index"] == task]), episodes_file)
    _write_meta(root, records)
    return data


def _write_meta(root: Path, records: list[dict]) -> None:
    def video(side: int, depth: bool) -> dict:
        return {"dtype": "video", "shape": [side, side, 1 if depth else 3],
                "names": ["height", "width", "channels"],
                "info": {"video.fps": FPS, "video.height": side, "video.width": side,
                         "video.channels": 1 if depth else 3, "video.codec": "hevc",
                         "video.pix_fmt": "gray12le" if depth else "yuv420p",
                         "video.is_depth_map": depth, "has_audio": False}}

    features = {key: video(side, False) for key, side in RGB.items()}
    features |= {key: video(side, True) for key, side in DEPTH.items()}
    features |= {key.replace("observation.rgb.", "observation.robot2cam_pose."):
                 {"dtype": "float32", "shape": [7], "names": None} for key in RGB}
    features |= {
        "observation.state": {"dtype": "float32", "shape": [STATE_WIDTH], "names": None},
        "action": {"dtype": "float32", "shape": [23], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
        "next.reward": {"dtype": "float32", "shape": [1], "names": None},
        "next.terminated": {"dtype": "bool", "shape": [1], "names": None},
        "next.truncated": {"dtype": "bool", "shape": [1], "names": None},
    }
    info = {
        "codebase_version": "v3.0", "robot_type": "R1Pro",
        "total_episodes": len(records), "total_frames": sum(r["length"] for r in records),
        "total_tasks": len(TASKS), "chunks_size": 1000, "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 500, "fps": FPS, "splits": {"train": f"0:{len(records)}"},
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
        "features": features,
    }
    meta = root / "meta"
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    pq.write_table(pa.table({"task_index": list(range(len(TASKS))),
                             "task": [name for name, _ in TASKS]}), meta / "tasks.parquet")
    (meta / "tasks.jsonl").write_text("".join(
        json.dumps({"task_index": t, "task_name": name, "task": prompt}) + "\n"
        for t, (name, prompt) in enumerate(TASKS)))
    (meta / "stats.json").write_text(json.dumps({}))
