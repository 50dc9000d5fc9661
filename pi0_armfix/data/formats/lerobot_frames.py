"""A LeRobot dataset's camera frames, decoded lazily by row (`LeRobotFrameImages`): PNG or JPEG
bytes inside parquet, or the video frame at the row's timestamp (within its v3.0 segment,
`segment_time`), with per-thread caches of open decoders and row groups."""

from __future__ import annotations

import collections
import dataclasses
import math
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data.formats.files import unreadable
from pi0_armfix.data.formats.frame_store import FrameColumn
from pi0_armfix.data.formats.lerobot_meta import EpisodeRecord, open_parquet
from pi0_armfix.data.formats.video import TIME_EPSILON_FRAMES, VideoDecoder

LATE_FRAMES = 2  # timestamps this many frames past their video: named with the tolerance to set


class LateTimestamps(ValueError):
    """A row's timestamp lies past its video by up to `LATE_FRAMES` frames: `frames` is the
    `data.video_tolerance_frames` that reads the video's last frame for it."""

    def __init__(self, message: str, frames: int):
        super().__init__(message)
        self.frames = frames


def segment_time(start: float, stop: float, timestamp: float, fps: float, tolerance: float,
                 where: str, path: Path) -> float:
    """The time in the mp4 of a row with `timestamp` whose episode owns the segment
    `[start, stop)` of the file: `start + timestamp`, moved to the segment's last frame (or its
    first) when it lies past it by at most `tolerance` frames.

    Raises:
      ValueError naming `where` (episode, camera, row) and the file when it lies further out.
    """
    seconds = start + timestamp
    last = stop - 1.0 / fps
    slack = (tolerance + TIME_EPSILON_FRAMES) / fps
    if seconds > last + TIME_EPSILON_FRAMES / fps:
        if seconds - last <= slack:
            return last
        over = (seconds - last) * fps
        found = (f"{where}: timestamp {timestamp:.4f} s lies {over:.2f} frames past the episode's "
                 f"segment [{start:.4f} s, {stop:.4f} s) of {path} (its last frame at {last:.4f} "
                 "s; beyond it the file holds the next episode). ")
        frames = math.ceil(over - 1e-6)
        if over <= LATE_FRAMES + 1e-6:
            raise LateTimestamps(
                found + f"If the data's timestamps run late by up to {frames} frame(s), set "
                f"data.video_tolerance_frames={frames} to read the segment's last frame", frames)
        raise ValueError(found + "The episode's meta/episodes record or its timestamps are wrong")
    if seconds < start - TIME_EPSILON_FRAMES / fps:
        if start - seconds <= slack:
            return start
        raise ValueError(f"{where}: timestamp {timestamp:.4f} s lies before the episode's "
                         f"segment [{start:.4f} s, {stop:.4f} s) of {path}")
    return seconds


class LeRobotFrameImages:
    """Lazy images of the frames of an EpisodeTable built from a LeRobot root (a FrameImages).

    Parquet images: one row group of one camera column (still encoded) is read at a time and kept
    in an LRU cache of at most `cache_bytes`; a request decodes one PNG/JPEG. Videos: one
    `VideoDecoder` per file (LRU of `max_open_videos`), resizing to fit inside `image_size` in the
    decoder. `timestamps` ([N] row timestamps, for videos) is a `FrameColumn`. Picklable
    for worker processes: files are reopened lazily and every process starts with empty caches.
    """

    def __init__(self, cameras: Mapping[str, str], kinds: Mapping[str, str],
                 episodes: Sequence[EpisodeRecord], episode_starts: np.ndarray,
                 timestamps: FrameColumn | None, fps: float, cache_bytes: int = 256 << 20,
                 max_open_videos: int = 8, video_tolerance_frames: float = 0.5,
                 image_size: tuple[int, int] | None = None):
        self.cameras = tuple(cameras)
        self._features = dict(cameras)
        self._kinds = dict(kinds)
        self._episodes = list(episodes)
        self._starts = np.asarray(episode_starts)
        self._timestamps = timestamps
        self._fps, self._cache_bytes, self._max_open = fps, cache_bytes, max_open_videos
        self.tolerance = video_tolerance_frames
        self._image_size = tuple(image_size) if image_size else None
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
        return self._read(position, frame, self._video)

    def episode_length(self, position: int) -> int:
        """Frames of the table's episode at `position`."""
        return int(self._starts[position + 1] - self._starts[position])

    def episode_reader(self, position: int) -> "EpisodeReader":
        """The frames of the table's episode at `position` read front to back, with decoders of
        its own (`EpisodeReader`): a stream of one episode never disturbs another's decoders."""
        return EpisodeReader(self, position)

    def _read(self, position: int, frame: int, video) -> dict[str, np.ndarray]:
        """The images of table row `frame` of the episode at `position`; `video(path)`: the
        decoder to read a video file with."""
        episode = self._episodes[position]
        offset = frame - int(self._starts[position])
        out = {}
        for camera, feature in self._features.items():
            if self._kinds[feature] == "video":
                path, start, stop = episode.videos[feature]
                seconds = segment_time(start, stop, float(self._timestamps[frame]), self._fps,
                                       self.tolerance, f"episode {episode.index}, camera "
                                       f"{feature!r}, row {offset}", path)
                out[camera] = video(path).frame_at(seconds)
            else:
                out[camera] = self._image(feature, episode.data_file, episode.first_row + offset)
        return out

    def _open_video(self, path: Path, forward_only: bool = False) -> VideoDecoder:
        """A decoder of `path`; `forward_only` for one of many streams read front to back at
        once: no decoder threads (they only add CPU per frame there), and only the frames the
        timestamps' tolerance can reach back to kept converted, so that the frames a stride
        steps over are decoded without being converted."""
        if not path.is_file():
            raise ValueError(f"missing video file {path}")
        if forward_only:
            return VideoDecoder(path, self._fps, self.tolerance, size=self._image_size,
                                threads=False, max_frames=math.ceil(self.tolerance) + 2)
        return VideoDecoder(path, self._fps, self.tolerance, size=self._image_size)

    def _image(self, feature: str, path: Path, row: int) -> np.ndarray:
        caches = self._caches
        starts = caches.row_groups.get(path)
        if starts is None:
            metadata = open_parquet(path).metadata
            starts = np.cumsum([0] + [metadata.row_group(i).num_rows
                                      for i in range(metadata.num_row_groups)])
            caches.row_groups[path] = starts
        group = int(np.searchsorted(starts, row, side="right")) - 1
        key = (path, group, feature)
        column = caches.columns.get(key)
        if column is None:
            try:
                table = open_parquet(path).read_row_group(group, columns=[feature])
            except (pa.ArrowException, OSError) as err:
                raise unreadable(path, "parquet file", err) from err
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

    def _video(self, path: Path) -> VideoDecoder:
        videos = self._caches.videos
        decoder = videos.get(path)
        if decoder is None:
            decoder = videos[path] = self._open_video(path)
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
        default_factory=collections.OrderedDict)  # mp4 -> VideoDecoder


class EpisodeReader:
    """One episode's images read front to back, with one single-threaded decoder per camera of
    its own (for streaming many episodes at once: one process decoding several streams gains
    nothing from decoder threads on few cores and spends more CPU per frame with them).

    `images(offset)` of the episode's frames in increasing order decodes each frame once; any
    other order seeks (from the keyframe before it). `close()` releases the decoders."""

    def __init__(self, frames: LeRobotFrameImages, position: int):
        self._frames, self._position = frames, position
        self.start = int(frames._starts[position])  # noqa: SLF001 - its own table's layout
        self.length = frames.episode_length(position)
        self._decoders: dict[Path, VideoDecoder] = {}

    def _video(self, path: Path) -> VideoDecoder:
        decoder = self._decoders.get(path)
        if decoder is None:
            decoder = self._decoders[path] = self._frames._open_video(  # noqa: SLF001
                path, forward_only=True)
        return decoder

    def images(self, offset: int) -> dict[str, np.ndarray]:
        """`{camera: uint8 [h, w, 3]}` of the episode's frame `offset`."""
        if not 0 <= offset < self.length:
            raise IndexError(f"frame {offset} outside the episode's [0, {self.length})")
        return self._frames._read(self._position, self.start + offset, self._video)  # noqa: SLF001

    @property
    def decoded(self) -> int:
        """Frames decoded so far by this reader's decoders (what its reads cost)."""
        return sum(d.decoded for d in self._decoders.values())

    def close(self) -> None:
        for decoder in self._decoders.values():
            decoder.close()
        self._decoders.clear()


def probe_frame(decoder: VideoDecoder, seconds: float, where: str) -> None:
    """Decodes the frame at `seconds`; an error names `where` (the episode and row)."""
    try:
        decoder.frame_at(seconds)
    except ValueError as err:
        raise ValueError(f"{err} ({where})") from None
