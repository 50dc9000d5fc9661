"""LeRobot datasets on disk (codebase v2.0, v2.1, v3.0), read and written with pyarrow and PyAV.

No `lerobot` package is needed. What the three layouts store (`meta/info.json` names the version
in `codebase_version`, the frame rate in `fps`, the file templates in `data_path` / `video_path`
and every column in `features`):

  v2.0 / v2.1  one parquet file per episode at `data_path.format(episode_chunk, episode_index)`,
               `episode_chunk = episode_index // chunks_size`; episodes in `meta/episodes.jsonl`
               (`{"episode_index", "tasks", "length"}`), task strings in `meta/tasks.jsonl`,
               statistics in `meta/stats.json` (v2.0) or per episode in `meta/episodes_stats.jsonl`
               (v2.1); one mp4 per episode and camera at
               `video_path.format(episode_chunk, video_key, episode_index)`.
  v3.0         many episodes per file at `data_path.format(chunk_index, file_index)`; episodes in
               `meta/episodes/chunk-*/file-*.parquet` (rows `dataset_from_index`..`dataset_to_index`
               of data file `data/chunk_index`, `data/file_index`; for every video camera the segment
               `videos/<key>/from_timestamp`..`to_timestamp` of the mp4 `videos/<key>/chunk_index`,
               `file_index`); task strings in `meta/tasks.parquet`.

Frame columns: the action and state features (`action` / `observation.state` by default;
`data.action_key` / `data.state_key` name others, e.g. `actions` / `state`), float32 or float64
lists, fixed- or variable-length; `timestamp` (seconds from the episode start), `frame_index`
(may be missing), `episode_index`, `index`, `task_index`; only the columns a pass needs are read
(B1K's `observation.task_info`, `cam_rel_poses` and depth / segmentation videos never are). An
episode's rows are read in stored order, which LeRobot writes in frame order. Image
features are stored in parquet as structs `{bytes, path}` holding PNG or JPEG bytes; video features
are mp4 files whose frame for a row is the one at the row's timestamp (plus the episode's
`from_timestamp` in v3.0), to within `data.video_tolerance_frames` (default half a frame: the
nearest frame; 1 accepts data whose timestamps run one frame past the video, a known fault of
some converted sets). Decoders are per thread, so any number of Grain threads may read at once.
`LeRobotSource.probe` decodes the first and last frame of a sample of episodes before training.

Files fetched without git-LFS are pointer files of ~130 bytes; they are named as such.

The reader takes an episode's prompt from the `tasks` list of its own metadata record (its first
task); the tasks files map `task_index` to the same strings and are written but not needed to read.

`LeRobotWriter` writes all three layouts (the demo dataset and the tests use it); `LeRobotSource`
reads them: `iter_blocks` streams actions/state one parquet row group at a time without per-row
Python, `load_table` builds an `EpisodeTable` whose images are decoded lazily by
`LeRobotFrameImages`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import fractions
import itertools
import json
import math
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data.episodes import EpisodeTable

ACTION = "action"
STATE = "observation.state"
VERSIONS = ("v2.0", "v2.1", "v3.0")

BLOCK_KEYS = ("actions", "state", "timestamp")
# Data files read ahead of the consumer by a background thread (bounds memory).
_READ_AHEAD = 2

_V2_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
_V2_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
_V3_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
_V3_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
_V3_EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
_LFS_POINTER = b"version https://git-lfs"


# ====================================================================== shared helpers


def _major_version(info: Mapping[str, Any], path: Path) -> int:
    version = str(info["codebase_version"])
    major = version.lstrip("v").split(".")[0]
    if major not in ("2", "3"):
        raise ValueError(f"{path}: codebase_version {version!r} is not supported; "
                         f"supported layouts: {list(VERSIONS)}")
    return int(major)


def lfs_pointer_message(path: Path) -> str | None:
    """"PATH is a git-LFS pointer ..." with the fix, if the file is one; None otherwise."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(_LFS_POINTER))
    except OSError:
        return None
    if head != _LFS_POINTER:
        return None
    return (f"{path} is a git-LFS pointer file ({path.stat().st_size} bytes), not the data: the "
            "dataset was cloned without its LFS objects. Fetch them (`git lfs pull` in the "
            "dataset root, or `huggingface-cli download --repo-type dataset REPO "
            "--local-dir ROOT`)")


def _unreadable(path: Path, what: str, err: Exception) -> ValueError:
    return ValueError(lfs_pointer_message(path) or f"cannot read {what} {path}: {err}")


def _open_parquet(path: Path) -> pq.ParquetFile:
    if not path.is_file():
        raise ValueError(f"missing parquet file {path}")
    try:
        return pq.ParquetFile(path)
    except (pa.ArrowException, OSError) as err:
        raise _unreadable(path, "parquet file", err) from err


def _read_parquet(path: Path, columns: Sequence[str]) -> pa.Table:
    parquet = _open_parquet(path)
    missing = [c for c in columns if c not in parquet.schema_arrow.names]
    if missing:
        raise ValueError(f"{path} has no column(s) {missing}")
    try:
        return parquet.read(columns=list(columns))
    except (pa.ArrowException, OSError) as err:
        raise _unreadable(path, "parquet file", err) from err


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        raise ValueError(f"missing LeRobot metadata file {path}")
    try:
        with open(path) as f:
            return [json.loads(line) for line in f if line.strip()]
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"cannot read {path}: {err}") from err


def _matrix(column: pa.ChunkedArray | pa.Array, name: str, path: Path) -> np.ndarray:
    """A list column of n rows of equal width w -> [n, w] numpy (zero-copy where arrow allows)."""
    array = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    n = len(array)
    if array.null_count:
        raise ValueError(f"{path}: column {name!r} has {array.null_count} missing values")
    if pa.types.is_fixed_size_list(array.type):
        width = array.type.list_size
    elif pa.types.is_list(array.type) or pa.types.is_large_list(array.type):
        lengths = np.diff(array.offsets.to_numpy())
        width = int(lengths[0]) if n else 0
        if n and (lengths != width).any():
            raise ValueError(f"{path}: column {name!r} has rows of different widths "
                             f"{sorted(set(lengths.tolist()))[:5]}")
    else:
        raise ValueError(f"{path}: column {name!r} has type {array.type}, expected a list of numbers")
    values = array.flatten().to_numpy(zero_copy_only=False)
    return values.reshape(n, width)


def _vector(column: pa.ChunkedArray, name: str, path: Path) -> np.ndarray:
    """A scalar (or one-element list) column -> [n] numpy."""
    array = column.combine_chunks()
    if pa.types.is_list(array.type) or pa.types.is_fixed_size_list(array.type):
        return _matrix(array, name, path)[:, 0]
    return array.to_numpy(zero_copy_only=False)


# ====================================================================== writer


def _list_array(values: np.ndarray) -> pa.Array:
    """[n, w] numpy -> arrow list<dtype> array (what Hugging Face `datasets` writes)."""
    n, width = values.shape
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * width)
    return pa.ListArray.from_arrays(offsets, pa.array(values.reshape(-1)))


def _feature_stats(x: np.ndarray) -> dict[str, list]:
    x = x.astype(np.float64)
    return {"min": x.min(0).tolist(), "max": x.max(0).tolist(), "mean": x.mean(0).tolist(),
            "std": x.std(0).tolist(), "count": [len(x)]}


def _merge_stats(parts: Sequence[Mapping[str, list]]) -> dict[str, list]:
    """Pooled statistics of several parts (count-weighted mean and variance)."""
    counts = np.array([p["count"][0] for p in parts], np.float64)[:, None]
    means = np.array([p["mean"] for p in parts])
    second = np.array([p["std"] for p in parts]) ** 2 + means ** 2
    mean = (counts * means).sum(0) / counts.sum()
    var = np.maximum((counts * second).sum(0) / counts.sum() - mean ** 2, 0.0)
    return {"min": np.min([p["min"] for p in parts], 0).tolist(),
            "max": np.max([p["max"] for p in parts], 0).tolist(),
            "mean": mean.tolist(), "std": np.sqrt(var).tolist(), "count": [int(counts.sum())]}


def _write_video(path: Path, frames: np.ndarray, fps: int, codec: str) -> None:
    """uint8 [n, h, w, 3] -> mp4, one keyframe every 2 frames as LeRobot encodes (fast seeking)."""
    import av  # PyAV is only needed for video features

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=fps)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv420p"
        stream.options = {"g": "2", "crf": "10"}
        for i, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts, frame.time_base = i, fractions.Fraction(1, fps)
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


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
      action_key, state_key: names of the action and state features.
    """

    def __init__(self, root: str | Path, *, version: str = "v2.1", fps: int = 30,
                 cameras: Mapping[str, tuple[int, int]] | None = None, image_format: str = "png",
                 float_dtype: Any = np.float32, frame_index: bool = True,
                 episodes_per_file: int = 100, row_group_size: int | None = None,
                 chunks_size: int = 1000, robot_type: str = "R1Pro", video_codec: str = "libx264",
                 action_key: str = ACTION, state_key: str = STATE):
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
        self.action_key, self.state_key = action_key, state_key
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
        self._records.append({
            "episode_index": episode.index, "tasks": [task], "length": n,
            "dataset_from_index": self._num_frames, "dataset_to_index": self._num_frames + n,
            "stats": {self.action_key: _feature_stats(actions),
                      self.state_key: _feature_stats(state)},
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
        return pa.table(columns)

    def _write_table(self, table: pa.Table, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path, row_group_size=self.row_group_size)

    def _write_v2(self, episode: _PendingEpisode) -> None:
        chunk = episode.index // self.chunks_size
        self._write_table(self._frames_table([episode]), self.root / _V2_DATA_PATH.format(
            episode_chunk=chunk, episode_index=episode.index))
        if self.image_format == "video":
            for name, frames in episode.images.items():
                _write_video(self.root / _V2_VIDEO_PATH.format(
                    episode_chunk=chunk, video_key=name, episode_index=episode.index),
                    frames, self.fps, self.video_codec)

    def _flush_v3(self) -> None:
        chunk, file = divmod(self._num_files, self.chunks_size)
        self._write_table(self._frames_table(self._pending), self.root / _V3_DATA_PATH.format(
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
                _write_video(self.root / _V3_VIDEO_PATH.format(
                    video_key=name, chunk_index=chunk, file_index=file),
                    frames, self.fps, self.video_codec)
        self._num_files += 1
        self._pending = []

    # ------------------------------------------------------------------ metadata

    def _info(self) -> dict[str, Any]:
        num_episodes = len(self._records)
        action_width, state_width = self._widths or (0, 0)
        dtype = self.float_dtype.name
        scalar = lambda d: {"dtype": d, "shape": [1], "names": None}  # noqa: E731
        features: dict[str, Any] = {
            self.action_key: {"dtype": dtype, "shape": [action_width], "names": None},
            self.state_key: {"dtype": dtype, "shape": [state_width], "names": None},
        }
        for name, (height, width) in self.cameras.items():
            feature = {"dtype": "video" if self.image_format == "video" else "image",
                       "shape": [height, width, 3], "names": ["height", "width", "channels"]}
            if self.image_format == "video":
                feature["info"] = {"video.fps": self.fps, "video.codec": self.video_codec,
                                   "video.pix_fmt": "yuv420p", "has_audio": False}
            features[name] = feature
        features["timestamp"] = scalar("float32")
        if self.frame_index:
            features["frame_index"] = scalar("int64")
        for name in ("episode_index", "index", "task_index"):
            features[name] = scalar("int64")
        video = self.image_format == "video" and self.cameras
        info: dict[str, Any] = {"codebase_version": self.version, "robot_type": self.robot_type,
                                "total_episodes": num_episodes, "total_frames": self._num_frames,
                                "total_tasks": len(self._tasks)}
        if self.version == "v3.0":
            info.update(chunks_size=self.chunks_size, data_files_size_in_mb=100,
                        video_files_size_in_mb=500, fps=self.fps,
                        splits={"train": f"0:{num_episodes}"}, data_path=_V3_DATA_PATH,
                        video_path=_V3_VIDEO_PATH if video else None)
        else:
            info.update(total_videos=num_episodes * len(self.cameras) if video else 0,
                        total_chunks=math.ceil(num_episodes / self.chunks_size),
                        chunks_size=self.chunks_size, fps=self.fps,
                        splits={"train": f"0:{num_episodes}"}, data_path=_V2_DATA_PATH,
                        video_path=_V2_VIDEO_PATH if video else None)
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
            stats = {key: _merge_stats([r["stats"][key] for r in self._records])
                     for key in (self.action_key, self.state_key)}
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
                          self.root / _V3_EPISODES_PATH.format(chunk_index=0, file_index=0))
        self._write_table(pa.table({"task_index": [i for _, i in tasks],
                                    "task": [t for t, _ in tasks]}),
                          self.root / "meta" / "tasks.parquet")


# ====================================================================== reader


@dataclasses.dataclass(frozen=True)
class _Episode:
    """Where one episode's frames are: rows [first_row, first_row + length) of data_file."""

    index: int
    length: int
    task: str
    data_file: Path
    first_row: int
    videos: Mapping[str, tuple[Path, float]]  # camera feature -> (mp4 file, from_timestamp)


def _first_task(tasks: Any, where: str) -> str:
    if isinstance(tasks, str):
        return tasks
    if not tasks:
        raise ValueError(f"{where} lists no task")
    return str(tasks[0])


def _template(info: Mapping[str, Any], field: str, path: Path, **values) -> str:
    template = info.get(field)
    if not template:
        raise ValueError(f"{path} has no {field!r} template")
    try:
        return template.format(**values)
    except (KeyError, IndexError, ValueError) as err:
        raise ValueError(f"{path}: cannot fill {field!r} = {template!r}: {err}") from err


def _episodes_v2(root: Path, info: Mapping[str, Any], video_keys: Sequence[str]) -> list[_Episode]:
    path = root / "meta" / "episodes.jsonl"
    info_path = root / "meta" / "info.json"
    chunks_size = int(info.get("chunks_size", 1000))
    episodes = []
    for line, row in enumerate(_read_jsonl(path), 1):
        if "episode_index" not in row or "length" not in row:
            raise ValueError(f"{path} line {line} lacks 'episode_index' or 'length'")
        index = int(row["episode_index"])
        names = dict(episode_chunk=index // chunks_size, episode_index=index)
        episodes.append(_Episode(
            index=index, length=int(row["length"]),
            task=_first_task(row.get("tasks"), f"{path} line {line}"),
            data_file=root / _template(info, "data_path", info_path, **names), first_row=0,
            videos={key: (root / _template(info, "video_path", info_path, video_key=key, **names),
                          0.0) for key in video_keys}))
    return sorted(episodes, key=lambda e: e.index)


def _episodes_v3(root: Path, info: Mapping[str, Any], video_keys: Sequence[str]) -> list[_Episode]:
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise ValueError(f"{root / 'meta' / 'episodes'} holds no chunk-*/file-*.parquet files")
    info_path = root / "meta" / "info.json"
    columns = ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index",
               "dataset_from_index"]
    for key in video_keys:
        columns += [f"videos/{key}/chunk_index", f"videos/{key}/file_index",
                    f"videos/{key}/from_timestamp"]
    rows = []
    for file in files:
        table = _read_parquet(file, columns)
        rows += [(file, row) for row in table.to_pylist()]
    # v3.0 rows are addressed by the dataset-global `index`; a data file starts at the smallest
    # `dataset_from_index` of the episodes it holds.
    file_start: dict[tuple[int, int], int] = {}
    for _, row in rows:
        key = (row["data/chunk_index"], row["data/file_index"])
        file_start[key] = min(file_start.get(key, row["dataset_from_index"]),
                              row["dataset_from_index"])
    episodes = []
    for file, row in rows:
        chunk, number = row["data/chunk_index"], row["data/file_index"]
        videos = {}
        for key in video_keys:
            video = _template(info, "video_path", info_path, video_key=key,
                              chunk_index=row[f"videos/{key}/chunk_index"],
                              file_index=row[f"videos/{key}/file_index"])
            videos[key] = (root / video, float(row[f"videos/{key}/from_timestamp"]))
        episodes.append(_Episode(
            index=int(row["episode_index"]), length=int(row["length"]),
            task=_first_task(row["tasks"], f"{file} episode {row['episode_index']}"),
            data_file=root / _template(info, "data_path", info_path, chunk_index=chunk,
                                       file_index=number),
            first_row=int(row["dataset_from_index"]) - file_start[(chunk, number)],
            videos=videos))
    return sorted(episodes, key=lambda e: e.index)


class LeRobotSource:
    """A LeRobot dataset root (v2.0, v2.1 or v3.0, detected from meta/info.json).

    Args:
      root: the dataset root (holds `meta/info.json`).
      layout: the action layout; the (selected) action width must equal `layout.real_dim`.
      cameras: `data.cameras` (`{batch camera: stored name}`); None = automatic match
        (see `pi0_armfix.data.cameras`).
      action_key, state_key: the stored action and state features (`data.action_key`,
        `data.state_key`); a dataset without the state feature gets a 0-D state.
      state_indices, state_preset: `data.state_indices` / `data.state_preset`, the selection of
        the stored state (`pi0_armfix.data.selection`; e.g. B1K's 256-D proprioception -> 23-D in
        the action order); both unset = all dims.
      action_indices: `data.action_indices`, dims of the stored actions to keep (() = all).
      video_tolerance_frames: `data.video_tolerance_frames`, how far (in frames) a row's
        timestamp may lie from the video frame it reads.

    Attributes:
      num_episodes, episode_index ([E] int64 episode ids), episode_lengths ([E] int64),
      tasks ([E] prompts), fps, version, cameras ({batch camera: stored name}),
      camera_names (every stored image/video feature), stored_state_width, state_width,
      stored_action_width, action_width, action_selection and state_selection (the
      `selection.Selection` of each stored vector).
    """

    def __init__(self, root: str | Path, layout: ActionLayout, *,
                 cameras: Mapping[str, str] | None = None, action_key: str = ACTION,
                 state_key: str = STATE, state_indices: Sequence[int] | None = None,
                 state_preset: str = "", action_indices: Sequence[int] | None = None,
                 video_tolerance_frames: float = 0.5):
        self.root = Path(root)
        info_path = self.root / "meta" / "info.json"
        if not info_path.is_file():
            raise ValueError(f"{self.root} is not a LeRobot dataset root: {info_path} is missing")
        try:
            info = json.loads(info_path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(lfs_pointer_message(info_path)
                             or f"cannot read {info_path}: {err}") from err
        for field in ("codebase_version", "fps", "features"):
            if field not in info:
                raise ValueError(f"{info_path} has no {field!r} field")
        major = _major_version(info, info_path)
        self.version, self.fps = str(info["codebase_version"]), float(info["fps"])
        if not video_tolerance_frames > 0:
            raise ValueError(f"data.video_tolerance_frames = {video_tolerance_frames} must be > 0 "
                             "(0.5 = the nearest frame)")
        self.video_tolerance_frames = float(video_tolerance_frames)
        features = info["features"]
        vectors = sorted(n for n, f in features.items()
                         if f.get("dtype") not in ("image", "video", "string"))
        if action_key not in features:
            raise ValueError(f"{info_path}: the dataset has no {action_key!r} feature "
                             f"(data.action_key); its features: {vectors}")
        self._columns = {"actions": action_key, "state": state_key, "timestamp": "timestamp"}
        self.stored_action_width = int(np.prod(features[action_key]["shape"]))
        self.action_selection = selection_lib.make_selection(
            self.stored_action_width, indices=action_indices or None, field="data.action_indices",
            feature=action_key, where=str(self.root))
        self.action_width = self.action_selection.width
        source = f"{self.root} (feature {action_key!r}" + (
            f", data.action_indices of {self.stored_action_width} dims)" if action_indices
            else ")")
        layout.check_real_dim(self.action_width, source=source)
        self._has_state = state_key in features
        if not self._has_state and (state_indices or state_preset):
            raise ValueError(f"{info_path}: the dataset has no {state_key!r} feature "
                             f"(data.state_key) to select from; its features: {vectors}")
        self.stored_state_width = (int(np.prod(features[state_key]["shape"])) if self._has_state
                                   else 0)
        self.state_selection = selection_lib.make_selection(
            self.stored_state_width, indices=state_indices or None, preset=state_preset or "",
            field="data.state_indices", feature=state_key, where=str(self.root))
        self.state_width = self.state_selection.width

        stored = {name: f["dtype"] for name, f in features.items()
                  if f.get("dtype") in ("image", "video")}
        self.camera_names = tuple(stored)
        self.cameras = cameras_lib.match_cameras(list(stored), cameras, str(self.root))
        self._camera_kind = {name: stored[name] for name in self.cameras.values()}
        video_keys = [name for name, kind in self._camera_kind.items() if kind == "video"]
        load = _episodes_v2 if major == 2 else _episodes_v3
        self._episodes = load(self.root, info, video_keys)
        if not self._episodes:
            raise ValueError(f"{self.root} lists no episodes")
        self.episode_index = np.array([e.index for e in self._episodes], np.int64)
        self.episode_lengths = np.array([e.length for e in self._episodes], np.int64)
        self.tasks = tuple(e.task for e in self._episodes)
        self._position = {int(i): p for p, i in enumerate(self.episode_index)}

    @property
    def num_episodes(self) -> int:
        return len(self._episodes)

    def __repr__(self) -> str:
        return (f"LeRobotSource({str(self.root)!r}, {self.version}, {self.num_episodes} episodes, "
                f"cameras={self.cameras})")

    def positions(self, episodes: Sequence[int] | None) -> list[int]:
        """Episode ids (values of `episode_index`) -> positions; None = all, in dataset order."""
        if episodes is None:
            return list(range(self.num_episodes))
        positions = []
        for episode in episodes:
            if int(episode) not in self._position:
                raise ValueError(
                    f"episode {int(episode)} is out of range: {self.root} has {self.num_episodes} "
                    f"episodes with indices {int(self.episode_index.min())}.."
                    f"{int(self.episode_index.max())}")
            positions.append(self._position[int(episode)])
        return positions

    # ------------------------------------------------------------------ probe

    def probe(self, num_episodes: int = 4) -> None:
        """Checks a sample of episodes before any pass over the data: their parquet files read
        (git-LFS pointers named), the action/state columns have the declared widths, and for each
        video camera the frame of the first row decodes and the last row's timestamp lies within
        `video_tolerance_frames` of the video's last frame (decoded for episodes of up to
        `_PROBE_DECODE_FRAMES` frames; from the container's frame count beyond, since B1K's HEVC
        files have one keyframe per episode and decoding to the end costs a full pass).

        Args:
          num_episodes: episodes probed, evenly spread over the dataset (first and last included).

        Raises:
          ValueError naming the file, the episode and the time that cannot be read.
        """
        if num_episodes <= 0:
            return
        positions = np.unique(np.linspace(0, self.num_episodes - 1, num_episodes).round())
        videos = [k for k, kind in self._camera_kind.items() if kind == "video"]
        for position in positions.astype(int):
            episode = self._episodes[position]
            keys = ("actions", "state") + (("timestamp",) if videos else ())
            blocks = self._read_file(episode.data_file, [episode], keys)
            if not videos:
                continue
            times = np.concatenate([b["timestamp"] for b in blocks]).astype(np.float64)
            for key in videos:
                path, start = episode.videos[key]
                if not path.is_file():
                    raise ValueError(f"missing video file {path} (episode {episode.index})")
                decoder = _VideoDecoder(path, self.fps, self.video_tolerance_frames)
                try:
                    where = f"episode {episode.index}, camera {key!r}"
                    _probe_frame(decoder, start + times[0], where + ", first row")
                    last = decoder.last_frame_time()
                    if episode.length <= _PROBE_DECODE_FRAMES or last is None:
                        _probe_frame(decoder, start + times[-1], where + ", last row")
                    elif start + times[-1] > last + self.video_tolerance_frames / self.fps:
                        raise ValueError(
                            f"{path} ends at {last:.4f} s (its last frame) but {where}'s last "
                            f"row has timestamp {times[-1]:.4f} s"
                            + (f" (+ from_timestamp {start:.4f} s)" if start else "")
                            + ": the data's timestamps run past the video. If by up to a frame, "
                            "set data.video_tolerance_frames=1 to read the nearest frame")
                finally:
                    decoder.close()

    # ------------------------------------------------------------------ streaming

    def iter_blocks(self, keys: Sequence[str] = ("actions", "state"),
                    episodes: Sequence[int] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """Streams frames of the chosen episodes, one parquet row group at a time.

        Args:
          keys: any of "actions", "state", "timestamp".
          episodes: episode ids in the order wanted; None = all.

        Yields:
          `{"actions": [n, A], "state": [n, S], "timestamp": [n], "episode_index": [n] int64}`
          (the keys asked for), in the stored float dtype (float32 or float64), in episode order;
          a block may hold the end of one episode and the start of the next.
        """
        unknown = [k for k in keys if k not in BLOCK_KEYS]
        if unknown:
            raise ValueError(f"unknown block key(s) {unknown}; known: {list(BLOCK_KEYS)}")
        positions = self.positions(episodes)
        runs = [(path, [self._episodes[p] for p in run]) for path, run in
                itertools.groupby(positions, key=lambda p: self._episodes[p].data_file)]
        # pyarrow reads without the GIL: a second thread reads the next files meanwhile.
        with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
            ahead: collections.deque = collections.deque()
            try:
                for path, run in runs:
                    ahead.append(pool.submit(self._read_file, path, run, tuple(keys)))
                    if len(ahead) > _READ_AHEAD:
                        yield from ahead.popleft().result()
                while ahead:
                    yield from ahead.popleft().result()
            finally:
                for future in ahead:
                    future.cancel()

    def _read_file(self, path: Path, episodes: Sequence[_Episode],
                   keys: tuple[str, ...]) -> list[dict[str, np.ndarray]]:
        """The blocks (one per row group) of the chosen episodes of one data file."""
        parquet = _open_parquet(path)
        columns = [self._columns[k] for k in keys if k != "state" or self._has_state]
        missing = [c for c in columns if c not in parquet.schema_arrow.names]
        if missing:
            raise ValueError(f"{path} has no column(s) {missing}")
        metadata = parquet.metadata
        starts = np.cumsum([0] + [metadata.row_group(i).num_rows
                                  for i in range(metadata.num_row_groups)])
        # Split every episode's rows at row-group boundaries: (row group, start, stop, episode).
        segments = []
        for episode in episodes:
            row, end = episode.first_row, episode.first_row + episode.length
            if end > starts[-1]:
                raise ValueError(f"{path} has {starts[-1]} rows but episode {episode.index} needs "
                                 f"rows {row}..{end - 1}")
            while row < end:
                group = int(np.searchsorted(starts, row, side="right")) - 1
                stop = min(end, int(starts[group + 1]))
                segments.append((group, int(row - starts[group]), int(stop - starts[group]),
                                 episode.index))
                row = stop
        blocks = []
        for group, parts in itertools.groupby(segments, key=lambda s: s[0]):
            parts = list(parts)
            try:
                table = parquet.read_row_group(group, columns=columns, use_threads=False)
            except (pa.ArrowException, OSError) as err:
                raise _unreadable(path, "parquet file", err) from err
            ranges = []  # contiguous row ranges, so that whole row groups are never copied
            for _, a, b, _ in parts:
                if ranges and ranges[-1][1] == a:
                    ranges[-1][1] = b
                else:
                    ranges.append([a, b])
            if ranges != [[0, table.num_rows]]:
                table = pa.concat_tables([table.slice(a, b - a) for a, b in ranges])
            blocks.append(self._block(table, keys, parts, path))
        return blocks

    def _block(self, table: pa.Table, keys: tuple[str, ...], parts, path: Path
               ) -> dict[str, np.ndarray]:
        n = table.num_rows
        block: dict[str, np.ndarray] = {}
        for key in keys:
            if key == "timestamp":
                block[key] = _vector(table.column("timestamp"), "timestamp", path)
            elif key == "state" and not self._has_state:
                block[key] = np.zeros((n, 0), np.float32)
            else:
                column = self._columns[key]
                values = _matrix(table.column(column), column, path)
                selection = (self.action_selection if key == "actions"
                             else self.state_selection)
                if values.shape[1] != selection.stored_width:
                    raise ValueError(f"{path}: column {column!r} has width {values.shape[1]} but "
                                     f"meta/info.json declares {selection.stored_width}")
                block[key] = selection(values)
        block["episode_index"] = np.repeat(np.array([p[3] for p in parts], np.int64),
                                           [b - a for _, a, b, _ in parts])
        return block

    # ------------------------------------------------------------------ tables

    def load_table(self, episodes: Sequence[int] | None = None, *,
                   images: bool = True) -> EpisodeTable:
        """Actions and state of the chosen episodes in memory; images lazy (None if `images` is
        False or the dataset has no matched camera)."""
        positions = self.positions(episodes)
        if not positions:
            raise ValueError(f"{self.root}: load_table needs at least one episode")
        chosen = [self._episodes[p] for p in positions]
        videos = images and any(kind == "video" for kind in self._camera_kind.values())
        if videos:
            for episode in chosen:
                for path, _ in episode.videos.values():
                    if not path.is_file():
                        raise ValueError(f"missing video file {path} (episode {episode.index})")
        keys = ("actions", "state") + (("timestamp",) if videos else ())
        blocks = list(self.iter_blocks(keys, [e.index for e in chosen]))
        starts = np.concatenate([[0], np.cumsum([e.length for e in chosen])]).astype(np.int64)
        actions = np.concatenate([b["actions"] for b in blocks]).astype(np.float32, copy=False)
        state = np.concatenate([b["state"] for b in blocks]).astype(np.float32, copy=False)
        reader = None
        if images and self.cameras:
            timestamps = (np.concatenate([b["timestamp"] for b in blocks]).astype(np.float64)
                          if videos else None)
            reader = LeRobotFrameImages(self.cameras, self._camera_kind, chosen, starts,
                                        timestamps, self.fps,
                                        video_tolerance_frames=self.video_tolerance_frames)
        return EpisodeTable(actions=actions, state=state, episode_starts=starts,
                            episode_index=np.array([e.index for e in chosen], np.int64),
                            tasks=[e.task for e in chosen], images=reader, fps=self.fps)


# ====================================================================== lazy images

# Episodes up to this long have their last video frame decoded by the probe (about 1 min at 30 fps).
_PROBE_DECODE_FRAMES = 1800


def _probe_frame(decoder: "_VideoDecoder", seconds: float, where: str) -> None:
    try:
        decoder.frame_at(seconds)
    except ValueError as err:
        raise ValueError(f"{err} ({where})") from None


class _VideoDecoder:
    """Frames of one mp4 by timestamp. Not thread-safe: one per thread (`LeRobotFrameImages`).

    Keeps the container open and the last `max_frames` decoded frames. A request a little ahead
    of the decoder's position (within `max_gap` frames) continues decoding forward; any other miss
    seeks to the keyframe before the requested time and decodes from there. A request is served
    by the frame nearest to it when that lies within `tolerance` frames (0.5: the nearest frame);
    otherwise it is an error naming the file, the time and the video's last frame.
    """

    def __init__(self, path: Path, fps: float, tolerance: float = 0.5, max_frames: int = 32,
                 max_gap: int = 32):
        import av  # PyAV is only needed for video features

        self.path, self.fps, self.tolerance = path, fps, tolerance
        self.max_frames, self.max_gap = max_frames, max_gap
        try:
            self._container = av.open(str(path))
            self._stream = self._container.streams.video[0]
        except (av.FFmpegError, IndexError) as err:
            raise _unreadable(path, "video file", err) from err
        self._frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._decoder = None
        self._position = -1  # number of the last frame the decoder returned

    def close(self) -> None:
        self._container.close()

    def _seek(self, seconds: float) -> None:
        offset = int(max(seconds, 0.0) / self._stream.time_base)
        self._container.seek(offset, stream=self._stream, backward=True, any_frame=False)
        self._decoder = self._container.decode(self._stream)
        self._position = -1

    def frame_at(self, seconds: float) -> np.ndarray:
        """uint8 [h, w, 3], the frame nearest to `seconds` (within `tolerance` frames)."""
        import av

        wanted = int(round(seconds * self.fps))
        if wanted in self._frames:
            self._frames.move_to_end(wanted)
            return self._frames[wanted]
        if self._decoder is None or not (self._position < wanted <= self._position + self.max_gap):
            self._seek(seconds)
        try:
            for frame in self._decoder:
                # A stream without timestamps is numbered by decoding order from its start.
                number = (int(round(frame.time * self.fps)) if frame.time is not None
                          else self._position + 1)
                self._position = number
                self._frames[number] = frame.to_ndarray(format="rgb24")
                while len(self._frames) > self.max_frames:
                    self._frames.popitem(last=False)
                if number >= wanted:
                    break
        except av.FFmpegError as err:
            self._decoder = None
            raise _unreadable(self.path, "video file", err) from err
        if wanted in self._frames:
            return self._frames[wanted]
        nearest = min(self._frames, key=lambda n: abs(n - seconds * self.fps), default=None)
        if nearest is not None and abs(nearest - seconds * self.fps) <= self.tolerance:
            return self._frames[nearest]
        self._decoder = None
        last = "no frame" if nearest is None else f"frame {nearest} at {nearest / self.fps:.4f} s"
        raise ValueError(
            f"{self.path} has no frame at {seconds:.4f} s (frame {seconds * self.fps:.2f} at "
            f"{self.fps:g} fps; decoding ended at {last}). If the data's timestamps run past the "
            f"video by up to a frame, set data.video_tolerance_frames=1 to read the nearest frame")

    def last_frame_time(self) -> float | None:
        """Time of the video's last frame from the container's metadata (None if unknown)."""
        stream = self._stream
        if stream.frames:
            start = float(stream.start_time * stream.time_base) if stream.start_time else 0.0
            return start + (stream.frames - 1) / self.fps
        return None


class LeRobotFrameImages:
    """Lazy images of the frames of an EpisodeTable built from a LeRobot root (a FrameImages).

    Parquet images: one row group of one camera column (still encoded) is read at a time and kept
    in an LRU cache of at most `cache_bytes`; a request decodes one PNG/JPEG. Videos: one
    `_VideoDecoder` per file (LRU of `max_open_videos`). Picklable for worker processes: files are
    reopened lazily and every process starts with empty caches.
    """

    def __init__(self, cameras: Mapping[str, str], kinds: Mapping[str, str],
                 episodes: Sequence[_Episode], episode_starts: np.ndarray,
                 timestamps: np.ndarray | None, fps: float, cache_bytes: int = 256 << 20,
                 max_open_videos: int = 8, video_tolerance_frames: float = 0.5):
        self.cameras = tuple(cameras)
        self._features = dict(cameras)
        self._kinds = dict(kinds)
        self._episodes = list(episodes)
        self._starts = np.asarray(episode_starts)
        self._timestamps = timestamps
        self._fps, self._cache_bytes, self._max_open = fps, cache_bytes, max_open_videos
        self._tolerance = video_tolerance_frames
        self._local = threading.local()

    # Decoders and caches are per thread: a PyAV container and its frame generator must never be
    # used by two threads at once (Grain reads with several threads when data.num_workers = 0).
    @property
    def _caches(self) -> _Caches:
        caches = getattr(self._local, "caches", None)
        if caches is None:
            caches = self._local.caches = _Caches()
        return caches

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_local")
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def __call__(self, frame: int) -> dict[str, np.ndarray]:
        if not 0 <= frame < self._starts[-1]:
            raise IndexError(f"frame {frame} outside [0, {int(self._starts[-1])})")
        position = int(np.searchsorted(self._starts, frame, side="right")) - 1
        episode = self._episodes[position]
        offset = frame - int(self._starts[position])
        out = {}
        for camera, feature in self._features.items():
            if self._kinds[feature] == "video":
                path, start = episode.videos[feature]
                out[camera] = self._video(path).frame_at(start + self._timestamps[frame])
            else:
                out[camera] = self._image(feature, episode.data_file, episode.first_row + offset)
        return out

    def _image(self, feature: str, path: Path, row: int) -> np.ndarray:
        caches = self._caches
        starts = caches.row_groups.get(path)
        if starts is None:
            metadata = _open_parquet(path).metadata
            starts = np.cumsum([0] + [metadata.row_group(i).num_rows
                                      for i in range(metadata.num_row_groups)])
            caches.row_groups[path] = starts
        group = int(np.searchsorted(starts, row, side="right")) - 1
        key = (path, group, feature)
        column = caches.columns.get(key)
        if column is None:
            try:
                table = _open_parquet(path).read_row_group(group, columns=[feature])
            except (pa.ArrowException, OSError) as err:
                raise _unreadable(path, "parquet file", err) from err
            column = table.column(0).combine_chunks().field("bytes")
            caches.columns[key] = column
            caches.cached_bytes += column.nbytes
            while caches.cached_bytes > self._cache_bytes and len(caches.columns) > 1:
                _, dropped = caches.columns.popitem(last=False)
                caches.cached_bytes -= dropped.nbytes
        else:
            caches.columns.move_to_end(key)
        data = column[row - int(starts[group])].as_py()
        if data is None:
            raise ValueError(f"{path}: camera {feature!r} row {row} holds no image bytes")
        return cameras_lib.decode_image(data, f"{path} camera {feature!r} row {row}")

    def _video(self, path: Path) -> _VideoDecoder:
        videos = self._caches.videos
        decoder = videos.get(path)
        if decoder is None:
            if not path.is_file():
                raise ValueError(f"missing video file {path}")
            decoder = _VideoDecoder(path, self._fps, self._tolerance)
            videos[path] = decoder
            if len(videos) > self._max_open:
                videos.popitem(last=False)[1].close()
        else:
            videos.move_to_end(path)
        return decoder


@dataclasses.dataclass
class _Caches:
    """One thread's open files of a LeRobotFrameImages."""

    row_groups: dict = dataclasses.field(default_factory=dict)  # parquet -> row group starts
    columns: collections.OrderedDict = dataclasses.field(
        default_factory=collections.OrderedDict)  # (parquet, group, feature) -> encoded images
    cached_bytes: int = 0
    videos: collections.OrderedDict = dataclasses.field(
        default_factory=collections.OrderedDict)  # mp4 -> _VideoDecoder

