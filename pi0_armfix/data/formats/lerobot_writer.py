"""`LeRobotWriter`: writes LeRobot dataset roots (v2.0, v2.1, v3.0) one episode at a time.

The demo dataset, the benchmarks, the re-encode tool and the tests write with it; what the three
layouts hold is described in `pi0_armfix.data.formats.lerobot`, which reads them. The metadata is
written as LeRobot's own writer writes it, so that LeRobot's loader and tools take the root as their
own:
  - every data parquet file declares its features in the schema metadata (`huggingface`:
    `{"info": {"features": ...}}` in Hugging Face `datasets`' form, cameras stored in the
    parquet as `Image`), without which LeRobot 0.3 reads an image column as `{bytes, path}` dicts;
  - statistics of every feature, cameras per channel (`data.lerobot_stats`): v2.1
    `meta/episodes_stats.jsonl`, v3.0 `meta/stats.json` and the `stats/<feature>/<stat>` columns
    of `meta/episodes`, v2.0 `meta/stats.json`;
  - v3.0 `meta/tasks.parquet` as pandas writes a frame indexed by the task string (LeRobot reads
    the task from the index), `task_index` its column;
  - a video feature's `info`: `video.height`, `video.width`, `video.codec` (the codec, `h264`, not
    the encoder), `video.pix_fmt`, `video.fps`, `video.channels`, `video.is_depth_map`,
    `has_audio`; v3.0's file-size settings are LeRobot's defaults (100 MB data, 200 MB video).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data.formats import lerobot_stats
from pi0_armfix.data.formats.lerobot_meta import (ACTION, STATE, V2_DATA_PATH, V2_VIDEO_PATH,
                                          V3_DATA_PATH, V3_EPISODES_PATH, V3_VIDEO_PATH,
                                          VERSIONS)
from pi0_armfix.data.formats.video import write_video


def _list_array(values: np.ndarray) -> pa.Array:
    """[n, w] numpy -> arrow fixed_size_list<dtype>[w] (what Hugging Face `datasets` stores for a
    `Sequence` of fixed length, the type the schema metadata declares)."""
    flat = pa.array(values.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, type=pa.list_(flat.type, values.shape[1]))


def codec_name(encoder: str) -> str:
    """The codec an encoder writes (`libx264` -> `h264`), as LeRobot records `video.codec`."""
    try:
        return av.Codec(encoder, "w").canonical_name
    except Exception:  # noqa: BLE001 - an encoder this PyAV build lacks keeps its own name
        return {"libaom-av1": "av1"}.get(encoder, encoder)


def hf_feature(feature: Mapping[str, Any]) -> dict[str, Any]:
    """A LeRobot feature (`info.json` form) as Hugging Face `datasets` declares it in a parquet
    schema (what LeRobot's `get_hf_features_from_features` makes of it; `Sequence`, which every
    `datasets` version reads)."""
    if feature["dtype"] == "image":
        return {"_type": "Image"}
    value = {"dtype": feature["dtype"], "_type": "Value"}
    if list(feature["shape"]) == [1]:
        return value
    return {"feature": value, "length": int(feature["shape"][0]), "_type": "Sequence"}


@dataclasses.dataclass
class _PendingEpisode:
    index: int
    task: str
    task_index: int
    actions: np.ndarray
    state: np.ndarray
    images: dict[str, Any]  # camera -> list of encoded bytes, or uint8 [n, h, w, 3] for video


class LeRobotWriter:
    """Writes a LeRobot dataset root one episode at a time, in any of the three layouts.

    Use as a context manager (or call `close`): the metadata is written at the end.

    Args:
      root: output folder; must not contain `meta/info.json` yet.
      version: "v2.0", "v2.1" or "v3.0".
      fps: frames per second.
      cameras: stored camera name (e.g. "observation.images.rgb.head") -> (height, width).
      image_format: "png" / "jpeg" (image features inside parquet) or "video" (mp4 features).
      float_dtype: dtype of the `action` and `observation.state` list columns.
      frame_index: whether to write the `frame_index` column.
      episodes_per_file: v3.0 only: episodes per data (and video) file.
      row_group_size: parquet rows per row group; None = pyarrow's default.
      chunks_size: files per chunk folder.
      robot_type: written to info.json.
      video_codec: PyAV encoder for video features.
      video_gop: frames between keyframes (2 as LeRobot encodes, for fast seeking; B1K 2025's
        HEVC files have one keyframe per episode).
      video_crf: the encoder's constant rate factor.
      video_options: further encoder options (e.g. {"preset": "ultrafast"}).
      action_key, state_key: names of the action and state features.
      action_names, state_names: the features' per-dim names, as `info.json`'s `names` (a flat
        list, LeRobot v3.0's form: `["shoulder_pan.pos", ...]`); None writes `null`.
    """

    def __init__(self, root: str | Path, *, version: str = "v2.1", fps: int = 30,
                 cameras: Mapping[str, tuple[int, int]] | None = None, image_format: str = "png",
                 float_dtype: Any = np.float32, frame_index: bool = True,
                 episodes_per_file: int = 100, row_group_size: int | None = None,
                 chunks_size: int = 1000, robot_type: str = "R1Pro", video_codec: str = "libx264",
                 video_gop: int = 2, video_crf: int = 10,
                 video_options: Mapping[str, str] | None = None,
                 action_key: str = ACTION, state_key: str = STATE,
                 action_names: Sequence[str] | None = None,
                 state_names: Sequence[str] | None = None):
        if version not in VERSIONS:
            raise ValueError(f"version must be one of {list(VERSIONS)}, got {version!r}")
        if image_format not in ("png", "jpeg", "video"):
            raise ValueError(f"image_format must be 'png', 'jpeg' or 'video', got {image_format!r}")
        self.root = Path(root)
        if (self.root / "meta" / "info.json").exists():
            raise ValueError(f"{self.root} already holds a LeRobot dataset")
        self.version, self.fps, self.cameras = version, int(fps), dict(cameras or {})
        self.image_format, self.float_dtype = image_format, np.dtype(float_dtype)
        self.frame_index, self.episodes_per_file = frame_index, int(episodes_per_file)
        self.row_group_size, self.chunks_size = row_group_size, int(chunks_size)
        self.robot_type, self.video_codec = robot_type, video_codec
        self.video_gop, self.video_crf = int(video_gop), int(video_crf)
        self.video_options = dict(video_options or {})
        self.action_key, self.state_key = action_key, state_key
        self.action_names = list(action_names) if action_names is not None else None
        self.state_names = list(state_names) if state_names is not None else None
        self._tasks: dict[str, int] = {}
        self._records: list[dict[str, Any]] = []  # per-episode metadata
        self._pending: list[_PendingEpisode] = []  # v3.0: episodes of the file being filled
        self._num_files = 0  # v3.0 data files written
        self._num_frames = 0
        self._widths: tuple[int, int] | None = None
        self._closed = False

    def __enter__(self) -> "LeRobotWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()

    def add_episode(self, actions: np.ndarray, state: np.ndarray, task: str,
                    images: Mapping[str, np.ndarray] | None = None) -> None:
        """Appends one episode.

        Args:
          actions: [n, A] float.
          state: [n, S] float.
          task: the episode's prompt.
          images: stored camera name -> uint8 [n, h, w, 3], for every camera given at construction.
        """
        actions, state = np.asarray(actions), np.asarray(state)
        n = len(actions)
        if actions.ndim != 2 or state.ndim != 2 or len(state) != n or n == 0:
            raise ValueError(f"episode {len(self._records)}: actions {actions.shape} and state "
                             f"{state.shape} must be [n, A] and [n, S] with the same n > 0")
        widths = (actions.shape[1], state.shape[1])
        if self._widths not in (None, widths):
            raise ValueError(f"episode {len(self._records)}: action/state widths {widths} differ "
                             f"from the first episode's {self._widths}")
        self._widths = widths
        images = dict(images or {})
        if set(images) != set(self.cameras):
            raise ValueError(f"episode {len(self._records)}: images for {sorted(images)}, "
                             f"expected {sorted(self.cameras)}")
        encoded = {}
        for name, frames in images.items():
            expected = (n, *self.cameras[name], 3)
            if frames.shape != expected or frames.dtype != np.uint8:
                raise ValueError(f"episode {len(self._records)}: camera {name!r} has "
                                 f"{frames.dtype} {frames.shape}, expected uint8 {expected}")
            encoded[name] = (frames if self.image_format == "video" else
                             [cameras_lib.encode_image(f, self.image_format) for f in frames])
        task_index = self._tasks.setdefault(task, len(self._tasks))
        episode = _PendingEpisode(len(self._records), task, task_index,
                                  actions.astype(self.float_dtype), state.astype(self.float_dtype),
                                  encoded)
        frame = np.arange(n)
        columns = {self.action_key: episode.actions, self.state_key: episode.state,
                   "timestamp": (frame / self.fps).astype(np.float32)}
        if self.frame_index:
            columns["frame_index"] = frame
        columns |= {"episode_index": np.full(n, episode.index),
                    "index": self._num_frames + frame, "task_index": np.full(n, task_index)}
        stats = {key: lerobot_stats.feature_stats(values) for key, values in columns.items()}
        stats |= {name: lerobot_stats.image_stats(frames) for name, frames in images.items()}
        self._records.append({
            "episode_index": episode.index, "tasks": [task], "length": n,
            "dataset_from_index": self._num_frames, "dataset_to_index": self._num_frames + n,
            "stats": stats,
        })
        self._num_frames += n
        if self.version == "v3.0":
            self._pending.append(episode)
            if len(self._pending) == self.episodes_per_file:
                self._flush_v3()
        else:
            self._write_v2(episode)

    # ------------------------------------------------------------------ frames

    def _frames_table(self, episodes: Sequence[_PendingEpisode]) -> pa.Table:
        lengths = [len(e.actions) for e in episodes]
        first = self._records[episodes[0].index]["dataset_from_index"]
        columns: dict[str, pa.Array] = {
            self.action_key: _list_array(np.concatenate([e.actions for e in episodes])),
            self.state_key: _list_array(np.concatenate([e.state for e in episodes])),
        }
        if self.image_format != "video":
            for name in self.cameras:
                data = pa.array([b for e in episodes for b in e.images[name]], pa.binary())
                paths = pa.nulls(len(data), pa.string())
                columns[name] = pa.StructArray.from_arrays([data, paths], names=["bytes", "path"])
        frame = np.concatenate([np.arange(n) for n in lengths])
        columns["timestamp"] = pa.array((frame / self.fps).astype(np.float32))
        if self.frame_index:
            columns["frame_index"] = pa.array(frame.astype(np.int64))
        columns["episode_index"] = pa.array(np.repeat([e.index for e in episodes], lengths))
        columns["index"] = pa.array(np.arange(first, first + sum(lengths), dtype=np.int64))
        columns["task_index"] = pa.array(np.repeat([e.task_index for e in episodes], lengths))
        table = pa.table(columns)
        features = {name: hf_feature(f) for name, f in self._features().items()
                    if f["dtype"] != "video"}
        return table.replace_schema_metadata({"huggingface": json.dumps(
            {"info": {"features": {name: features[name] for name in table.column_names}}})})

    def _write_table(self, table: pa.Table, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path, row_group_size=self.row_group_size)

    def _write_v2(self, episode: _PendingEpisode) -> None:
        chunk = episode.index // self.chunks_size
        self._write_table(self._frames_table([episode]), self.root / V2_DATA_PATH.format(
            episode_chunk=chunk, episode_index=episode.index))
        if self.image_format == "video":
            for name, frames in episode.images.items():
                write_video(self.root / V2_VIDEO_PATH.format(
                    episode_chunk=chunk, video_key=name, episode_index=episode.index),
                    frames, self.fps, self.video_codec, gop=self.video_gop,
                    crf=self.video_crf, options=self.video_options)

    def _flush_v3(self) -> None:
        chunk, file = divmod(self._num_files, self.chunks_size)
        self._write_table(self._frames_table(self._pending), self.root / V3_DATA_PATH.format(
            chunk_index=chunk, file_index=file))
        start = 0.0
        for episode in self._pending:
            record = self._records[episode.index]
            record.update({"data/chunk_index": chunk, "data/file_index": file})
            duration = len(episode.actions) / self.fps
            if self.image_format == "video":
                for name in self.cameras:
                    record.update({f"videos/{name}/chunk_index": chunk,
                                   f"videos/{name}/file_index": file,
                                   f"videos/{name}/from_timestamp": start,
                                   f"videos/{name}/to_timestamp": start + duration})
            start += duration
        if self.image_format == "video":
            for name in self.cameras:
                frames = np.concatenate([e.images[name] for e in self._pending])
                write_video(self.root / V3_VIDEO_PATH.format(
                    video_key=name, chunk_index=chunk, file_index=file),
                    frames, self.fps, self.video_codec, gop=self.video_gop,
                    crf=self.video_crf, options=self.video_options)
        self._num_files += 1
        self._pending = []

    # ------------------------------------------------------------------ metadata

    def _features(self) -> dict[str, Any]:
        """`info.json`'s features, in the parquet's column order."""
        action_width, state_width = self._widths or (0, 0)
        dtype = self.float_dtype.name
        scalar = lambda d: {"dtype": d, "shape": [1], "names": None}  # noqa: E731
        features: dict[str, Any] = {
            self.action_key: {"dtype": dtype, "shape": [action_width],
                              "names": self.action_names},
            self.state_key: {"dtype": dtype, "shape": [state_width], "names": self.state_names},
        }
        for name, (height, width) in self.cameras.items():
            feature = {"dtype": "video" if self.image_format == "video" else "image",
                       "shape": [height, width, 3], "names": ["height", "width", "channels"]}
            if self.image_format == "video":
                feature["info"] = {"video.height": height, "video.width": width,
                                   "video.codec": codec_name(self.video_codec),
                                   "video.pix_fmt": "yuv420p", "video.fps": self.fps,
                                   "video.channels": 3, "video.is_depth_map": False,
                                   "has_audio": False}
            features[name] = feature
        features["timestamp"] = scalar("float32")
        if self.frame_index:
            features["frame_index"] = scalar("int64")
        for name in ("episode_index", "index", "task_index"):
            features[name] = scalar("int64")
        return features

    def _info(self) -> dict[str, Any]:
        num_episodes = len(self._records)
        features = self._features()
        video = self.image_format == "video" and self.cameras
        info: dict[str, Any] = {"codebase_version": self.version, "robot_type": self.robot_type,
                                "total_episodes": num_episodes, "total_frames": self._num_frames,
                                "total_tasks": len(self._tasks)}
        if self.version == "v3.0":
            info.update(chunks_size=self.chunks_size, data_files_size_in_mb=100,
                        video_files_size_in_mb=200, fps=self.fps,
                        splits={"train": f"0:{num_episodes}"}, data_path=V3_DATA_PATH,
                        video_path=V3_VIDEO_PATH if video else None)
        else:
            info.update(total_videos=num_episodes * len(self.cameras) if video else 0,
                        total_chunks=math.ceil(num_episodes / self.chunks_size),
                        chunks_size=self.chunks_size, fps=self.fps,
                        splits={"train": f"0:{num_episodes}"}, data_path=V2_DATA_PATH,
                        video_path=V2_VIDEO_PATH if video else None)
        info["features"] = features
        return info

    def close(self) -> None:
        """Writes any buffered v3.0 file and the metadata."""
        if self._closed:
            return
        if not self._records:
            raise ValueError(f"{self.root}: no episodes were added")
        if self._pending:
            self._flush_v3()
        meta = self.root / "meta"
        meta.mkdir(parents=True, exist_ok=True)
        (meta / "info.json").write_text(json.dumps(self._info(), indent=4))
        tasks = sorted(self._tasks.items(), key=lambda kv: kv[1])
        if self.version != "v2.1":  # v2.1 replaced stats.json by per-episode statistics
            stats = {key: lerobot_stats.merge_stats([r["stats"][key] for r in self._records])
                     for key in self._records[0]["stats"]}
            (meta / "stats.json").write_text(json.dumps(stats, indent=4))
        if self.version == "v3.0":
            self._write_v3_meta(tasks)
        else:
            lines = lambda rows: "".join(json.dumps(r) + "\n" for r in rows)  # noqa: E731
            (meta / "episodes.jsonl").write_text(lines(
                {k: r[k] for k in ("episode_index", "tasks", "length")} for r in self._records))
            (meta / "tasks.jsonl").write_text(lines(
                {"task_index": i, "task": t} for t, i in tasks))
            if self.version == "v2.1":
                (meta / "episodes_stats.jsonl").write_text(lines(
                    {"episode_index": r["episode_index"], "stats": r["stats"]}
                    for r in self._records))
        self._closed = True

    def _write_v3_meta(self, tasks: Sequence[tuple[str, int]]) -> None:
        columns: dict[str, Any] = {"episode_index": [], "tasks": [], "length": []}
        for record in self._records:
            for key, value in record.items():
                if key == "stats":
                    for feature, stats in value.items():
                        for stat, v in stats.items():
                            columns.setdefault(f"stats/{feature}/{stat}", []).append(v)
                else:
                    columns.setdefault(key, []).append(value)
        columns["meta/episodes/chunk_index"] = [0] * len(self._records)
        columns["meta/episodes/file_index"] = [0] * len(self._records)
        self._write_table(pa.table(columns),
                          self.root / V3_EPISODES_PATH.format(chunk_index=0, file_index=0))
        self._write_table(tasks_table(tasks), self.root / "meta" / "tasks.parquet")


def tasks_table(tasks: Sequence[tuple[str, int]]) -> pa.Table:
    """v3.0's `meta/tasks.parquet` as pandas writes LeRobot's frame: `task_index` a column, the
    task string its index (a `task` column named as the index in the `pandas` schema metadata)."""
    table = pa.table({"task_index": pa.array([i for _, i in tasks], pa.int64()),
                      "task": pa.array([t for t, _ in tasks], pa.string())})
    pandas = {"index_columns": ["task"],
              "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode",
                                  "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
              "columns": [{"name": "task_index", "field_name": "task_index",
                           "pandas_type": "int64", "numpy_type": "int64", "metadata": None},
                          {"name": "task", "field_name": "task", "pandas_type": "unicode",
                           "numpy_type": "object", "metadata": None}],
              "creator": {"library": "pyarrow", "version": pa.__version__},
              "pandas_version": "2.2.3"}
    return table.replace_schema_metadata({"pandas": json.dumps(pandas)})
