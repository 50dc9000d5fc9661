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
               of data file `data/chunk_index`, `data/file_index`; for every video camera the
               segment `videos/<key>/from_timestamp`..`to_timestamp` of the mp4
               `videos/<key>/chunk_index`, `file_index`); task strings in `meta/tasks.parquet`.

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
some converted sets). In v3.0 an episode owns only its segment `[from_timestamp, to_timestamp)`
of a file that holds many: a row whose time falls past its segment's last frame is read at that
frame when it overruns by at most `data.video_tolerance_frames`, and is an error naming the
episode, the row and the file otherwise (it would read the next episode's frames). Decoders are per
thread, so any number of Grain threads may read at once.
`LeRobotSource.probe` decodes the first and last frame of a sample of episodes before training.
The metadata (versions, templates, episode records, prompts) is `data/formats/lerobot_meta.py`;
the lazy frame decoding `data/formats/lerobot_frames.py`; this module holds the source.

Files fetched without git-LFS are pointer files of ~130 bytes; they are named as such.

The reader takes an episode's prompt from the `tasks` list of its own metadata record (its first
task). Where that is a task *name* rather than a prompt (B1K 2026 stores the snake_case name,
`turning_on_radio`), `meta/tasks.jsonl` rows `{"task_name": name, "task": prompt}` give the prompt
(B1K 2025 writes the same rows); a name without such a row is its own prompt.

`pi0_armfix.data.formats.lerobot_writer.LeRobotWriter` writes all three layouts; `LeRobotSource`
reads them: `iter_blocks` streams actions/state one parquet row group at a time without per-row
Python (the statistics passes, and the one-time build of the on-disk `FrameStore`), `load_table`
builds an `EpisodeTable` whose columns are read by row from that store and whose images are decoded
lazily by `LeRobotFrameImages`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import itertools
import json
import logging
import math
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.cache import digest
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data import selection as selection_lib
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats import image_store
from pi0_armfix.data.formats.files import lfs_pointer_message, unreadable
from pi0_armfix.data.formats.frame_store import FrameStore
from pi0_armfix.data.formats.lerobot_frames import (LATE_FRAMES, LateTimestamps,
                                                 LeRobotFrameImages, probe_frame, segment_time)
from pi0_armfix.data.formats.lerobot_meta import (
    ACTION, FPS_TOLERANCE, STATE, EpisodeRecord, check_row_rate, episodes_v2, episodes_v3,
    major_version, matrix, open_parquet, task_prompts_of, task_rows, vector, with_prompts)
from pi0_armfix.data.formats.missing_videos import MissingVideos
from pi0_armfix.data.formats.video import TIME_EPSILON_FRAMES, VideoDecoder, keyframe_interval

# Episodes up to this long have their last video frame decoded by the probe (about 1 min at 30 fps).
PROBE_DECODE_FRAMES = 1800


BLOCK_KEYS = ("actions", "state", "timestamp")
_READ_AHEAD = 2


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
      skip_missing_videos: `data.skip_missing_videos`: episodes whose video file of a read camera
        is missing are left out, named in one warning line (True), or (False) are an error naming
        them all as soon as a pass would read images (`probe`, `load_table`); passes that read
        none (statistics, analysis) read every episode.
      frame_cache: `data.frame_cache`: video frames are decoded once, at the size `load_table`
        is asked for, into an on-disk cache (`image_store`) that every later table reads.

    Attributes:
      num_episodes, episode_index ([E] int64 episode ids), episode_lengths ([E] int64),
      tasks ([E] prompts), fps, version, cameras ({batch camera: stored name}),
      camera_names (every stored image/video feature), stored_state_width, state_width,
      stored_action_width, action_width, action_selection and state_selection (the
      `selection.Selection` of each stored vector), missing_videos (`MissingVideos` of the read
      cameras: empty once `skip_missing_videos` has left their episodes out).
    """

    def __init__(self, root: str | Path, layout: ActionLayout, *,
                 cameras: Mapping[str, str] | None = None, action_key: str = ACTION,
                 state_key: str = STATE, state_indices: Sequence[int] | None = None,
                 state_preset: str = "", action_indices: Sequence[int] | None = None,
                 video_tolerance_frames: float = 0.5, images: bool = True,
                 skip_missing_videos: bool = False, frame_cache: bool = False):
        self.root = Path(root)
        self.frame_cache = bool(frame_cache)
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
        major = major_version(info, info_path)
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
        # data.images=False: no camera is matched, so none is read or probed.
        self.cameras = (cameras_lib.match_cameras(list(stored), cameras, str(self.root))
                        if images else {})
        self._camera_kind = {name: stored[name] for name in self.cameras.values()}
        video_keys = [name for name, kind in self._camera_kind.items() if kind == "video"]
        load = episodes_v2 if major == 2 else episodes_v3
        rows = task_rows(self.root)
        self._episodes = with_prompts(load(self.root, info, video_keys), rows)
        if not self._episodes:
            raise ValueError(f"{self.root} lists no episodes")
        self.missing_videos = MissingVideos.find(self.root, self._episodes, video_keys,
                                                  info.get("video_path"))
        self.skipped_episodes: tuple[int, ...] = ()
        if self.missing_videos.message and skip_missing_videos:
            self._episodes, self.skipped_episodes = self.missing_videos.kept(self._episodes)
            logging.warning("%s; left out of training and evaluation (data.skip_missing_videos)",
                            self.missing_videos.found)
            self.missing_videos = MissingVideos()
        self.episode_index = np.array([e.index for e in self._episodes], np.int64)
        self.episode_lengths = np.array([e.length for e in self._episodes], np.int64)
        self.tasks = tuple(e.task for e in self._episodes)
        self.task_prompts = task_prompts_of(rows)
        self._position = {int(i): p for p, i in enumerate(self.episode_index)}

    block_keys = BLOCK_KEYS

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

    def episode_file(self, episode: int) -> str:
        """"file PATH" of the data file holding an episode (for messages)."""
        return f"file {self._episodes[self.positions([episode])[0]].data_file}"

    # ------------------------------------------------------------------ probe

    def probe(self, num_episodes: int = 4, videos: bool = True) -> None:
        """Checks a sample of episodes before any pass over the data: their parquet files read
        (git-LFS pointers named), the action/state columns have the declared widths, and for each
        video camera the frame of the first row decodes and the last row's timestamp lies within
        `video_tolerance_frames` of the video's last frame (decoded for episodes of up to
        `PROBE_DECODE_FRAMES` frames; from the container's frame count beyond, since B1K's HEVC
        files have one keyframe per episode and decoding to the end costs a full pass).

        Args:
          num_episodes: episodes probed, evenly spread over the dataset (first and last included).
          videos: False for a pass that reads no images (the statistics and analysis tools):
            only the parquet files are probed.

        Raises:
          ValueError naming the file, the episode and the time that cannot be read.
        """
        videos = [k for k, kind in self._camera_kind.items() if kind == "video"] if videos else []
        if videos:
            self.missing_videos.check()
        if num_episodes <= 0:
            return
        positions = np.unique(np.linspace(0, self.num_episodes - 1, num_episodes).round())
        for position in positions.astype(int):
            episode = self._episodes[position]
            keys = ("actions", "state") + (("timestamp",) if videos else ())
            blocks = self._read_file(episode.data_file, [episode], keys)
            if not videos:
                continue
            times = np.concatenate([b["timestamp"] for b in blocks]).astype(np.float64)
            check_row_rate(times, self.fps, self.root, episode)
            for key in videos:
                path, start, stop = episode.videos[key]
                decoder = VideoDecoder(path, self.fps, self.video_tolerance_frames)
                try:
                    where = f"episode {episode.index}, camera {key!r}"
                    rate = decoder.rate()
                    if rate is not None and abs(rate - self.fps) > FPS_TOLERANCE * self.fps:
                        raise ValueError(
                            f"{path} plays at {rate:.4g} fps but {self.root / 'meta/info.json'} "
                            f"declares fps {self.fps:g} ({where}): frames would be read at the "
                            "wrong times; fix the declared fps (or the video)")
                    for row in (0, len(times) - 1):
                        segment_time(start, stop, times[row], self.fps,
                                     self.video_tolerance_frames, f"{where}, row {row}", path)
                    probe_frame(decoder, start + times[0], where + ", first row")
                    last = decoder.last_frame_time()
                    if episode.length <= PROBE_DECODE_FRAMES or last is None:
                        probe_frame(decoder, segment_time(
                            start, stop, times[-1], self.fps, self.video_tolerance_frames,
                            where, path), where + ", last row")
                    elif start + times[-1] > (last + self.video_tolerance_frames / self.fps
                                              + TIME_EPSILON_FRAMES / self.fps):
                        found = (f"{path} ends at {last:.4f} s (its last frame) but {where}'s "
                                 f"last row has timestamp {times[-1]:.4f} s"
                                 + (f" (+ from_timestamp {start:.4f} s)" if start else "")
                                 + ": the data's timestamps run past the video")
                        frames = math.ceil((start + times[-1] - last) * self.fps - 1e-6)
                        if frames <= LATE_FRAMES:
                            raise LateTimestamps(
                                f"{found}. Set data.video_tolerance_frames={frames} to read the "
                                "nearest frame", frames)
                        raise ValueError(found)
                finally:
                    decoder.close()

    def video_keyframes(self) -> tuple[str, int | None] | None:
        """`(description, frames between keyframes)` of the first matched video camera's file
        (demuxed from its first packets; the interval None for one keyframe in them, a long
        GOP), or None without video cameras. The description (codec, size, camera) is the
        banner's."""
        videos = [k for k, kind in self._camera_kind.items() if kind == "video"]
        if not videos:
            return None
        self.missing_videos.check()
        path = self._episodes[0].videos[videos[0]][0]
        codec, height, width, interval = keyframe_interval(path)
        return f"{codec} {height}x{width} ({videos[0]})", interval

    def dim_name(self, key: str, dim: int) -> str:
        """`dim N` of the selected `key` ("actions" / "state"), with the stored dims it is read
        from when a selection moved it (`dim 9 (stored 'observation.state' dim 160)`)."""
        selection = self.action_selection if key == "actions" else self.state_selection
        stored = selection.stored_dims(dim)
        if stored == (dim,):
            return f"dim {dim}"
        return (f"dim {dim} (stored {self._columns[key]!r} dim"
                + (f"s {' + '.join(map(str, stored))})" if len(stored) > 1 else f" {stored[0]})"))

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

    def _read_file(self, path: Path, episodes: Sequence[EpisodeRecord],
                   keys: tuple[str, ...]) -> list[dict[str, np.ndarray]]:
        """The blocks (one per row group) of the chosen episodes of one data file."""
        parquet = open_parquet(path)
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
                raise unreadable(path, "parquet file", err) from err
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
                block[key] = vector(table.column("timestamp"), "timestamp", path)
            elif key == "state" and not self._has_state:
                block[key] = np.zeros((n, 0), np.float32)
            else:
                column = self._columns[key]
                values = matrix(table.column(column), column, path)
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

    def identity(self) -> dict[str, Any]:
        """What the frames read from this source depend on (the key of its `FrameStore`): the
        root, layout version, info.json, every data file's size and modification time, the
        episodes, and the feature keys and selections."""
        files = []
        for path in sorted({e.data_file for e in self._episodes}):
            try:
                stat = path.stat()
            except OSError as err:
                raise ValueError(f"missing parquet file {path}: {err}") from err
            files.append((str(path.relative_to(self.root)), stat.st_size, stat.st_mtime_ns))
        info = self.root / "meta" / "info.json"
        return {"root": str(self.root.resolve()), "version": self.version,
                "info.json": digest(info.read_text()), "data files": digest(files),
                "episodes": digest([self.episode_index.tolist(), self.episode_lengths.tolist()]),
                "actions": [self._columns["actions"], repr(self.action_selection)],
                "state": [self._columns["state"] if self._has_state else None,
                          repr(self.state_selection)]}

    def _stored_images(self, positions: Sequence[int], image_size: tuple[int, int] | None
                       ) -> image_store.StoredFrameImages:
        """The images of the episodes at `positions` from the decoded-frame cache of every
        episode (`image_store`; built on first use)."""
        if any(kind != "video" for kind in self._camera_kind.values()):
            raise ValueError(f"{self.root}: data.frame_cache stores video cameras, but "
                             f"{sorted(self._camera_kind)} mixes videos and images; set "
                             "data.frame_cache=False")
        starts = self.frame_store.row_starts
        reader = LeRobotFrameImages(
            self.cameras, self._camera_kind, self._episodes, starts,
            self.frame_store.column("timestamp", range(len(self._episodes))), self.fps,
            video_tolerance_frames=self.video_tolerance_frames, image_size=image_size)
        files = [path for e in self._episodes for path, _, _ in e.videos.values()]
        root = image_store.open_store(self.identity(), reader, self.episode_index,
                                      self.episode_lengths, files, image_size)
        return image_store.stored_images(root, self.cameras, starts, positions)

    @functools.cached_property
    def frame_store(self) -> FrameStore:
        """The on-disk frame columns of this source (built on first use)."""
        return FrameStore.open(self)

    def load_table(self, episodes: Sequence[int] | None = None, *, images: bool = True,
                   image_size: tuple[int, int] | None = None) -> EpisodeTable:
        """The chosen episodes (None = all): actions, state (and the timestamps the video reader
        needs) read by row from the `frame_store`; images lazy (None if `images` is False or
        the dataset has no matched camera). `image_size`: (height, width) video frames are
        resized to fit inside (`video.fit_frames`); None = as stored."""
        positions = self.positions(episodes)
        if not positions:
            raise ValueError(f"{self.root}: load_table needs at least one episode")
        chosen = [self._episodes[p] for p in positions]
        videos = images and any(kind == "video" for kind in self._camera_kind.values())
        if videos:
            self.missing_videos.check()
        store = self.frame_store
        starts = np.concatenate([[0], np.cumsum([e.length for e in chosen])]).astype(np.int64)
        reader = None
        if images and self.cameras and videos and self.frame_cache:
            reader = self._stored_images(positions, image_size)
        elif images and self.cameras:
            reader = LeRobotFrameImages(
                self.cameras, self._camera_kind, chosen, starts,
                store.column("timestamp", positions) if videos else None, self.fps,
                video_tolerance_frames=self.video_tolerance_frames, image_size=image_size)
        return EpisodeTable(actions=store.column("actions", positions),
                            state=store.column("state", positions), episode_starts=starts,
                            episode_index=np.array([e.index for e in chosen], np.int64),
                            tasks=[e.task for e in chosen], images=reader, fps=self.fps)
