"""Camera frames decoded once, at the model's image size, into columns on disk
(`data.frame_cache`): what lets a small model train on 640x480 AV1 without spending a core on
decoding every sample again.

Each matched video camera of a LeRobot source becomes one column

    <cache_root()>/images/<hash>/<camera>.npy   uint8 [N, h, w, 3]   (every episode, source order)
    <cache_root()>/images/<hash>/index.json     {"identity": ..., "episode_lengths": [E], ...}

written by reading every episode front to back with the project's own video path
(`LeRobotFrameImages.episode_reader`: the row's frame by its timestamp, then `video.fit_frames`),
so a stored frame is the pixels a request would have decoded, and read by row (`FrameColumn`,
positioned reads through the page cache that every worker shares). The key names the source's
`identity()`, every video file's size and modification time, the cameras, the image size, the
timestamp tolerance and the PyAV / FFmpeg versions: another file, size or decoder is another
entry, never the old one. Disk: h * w * 3 bytes per frame and camera (the G1 set at 32x24:
~75 MB; B1K 2025 at 224x224 would be ~18 TB, which the free-space check refuses).
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pi0_armfix.cache import build_lock, cache_root, digest
from pi0_armfix.data.formats.frame_store import FrameColumn, FrameStore

_FORMAT = 1  # bump when the entry layout or the decoding path changes


class StoredFrameImages:
    """The images of an EpisodeTable's frames read from an `ImageStore` (a FrameImages):
    `{camera: uint8 [h, w, 3]}` per table row. Picklable (its columns pickle as file names)."""

    def __init__(self, columns: Mapping[str, FrameColumn]):
        self.cameras = tuple(columns)
        self._columns = dict(columns)

    def __call__(self, frame: int) -> dict[str, np.ndarray]:
        return {camera: column[frame] for camera, column in self._columns.items()}


def open_store(identity: Mapping[str, Any], reader, episode_index: np.ndarray, lengths: np.ndarray,
               video_files: Sequence[Path], image_size: tuple[int, int] | None, *,
               cache_dir: str | os.PathLike | None = None, progress: bool = True) -> Path:
    """The folder of the decoded frames of every episode of a source (built on first use).

    Args:
      identity: the source's `identity()`.
      reader: a `LeRobotFrameImages` of all the source's episodes (its `episode_reader`), decoding
        to fit inside `image_size`.
      episode_index, lengths: `[E]` episode ids and frames per episode, source order.
      video_files: every video file the reader reads (their sizes and times join the key).
      image_size: (H, W) the frames are fit inside; None = as stored.
    Raises:
      ValueError naming `data.frame_cache` when the frames would not fit on the cache's disk, or
      an episode's frames change size.
    """
    import av

    files = []
    for path in sorted(set(map(str, video_files))):
        stat = os.stat(path)
        files.append((path, stat.st_size, stat.st_mtime_ns))
    key = {"format": _FORMAT, "source": dict(identity), "videos": digest(files),
           "cameras": list(reader.cameras), "image_size": list(image_size or ()),
           "tolerance": reader.tolerance, "decoder": [av.__version__,
                                                      av.library_versions.get("libavcodec")]}
    key = json.loads(json.dumps(key, default=str))
    root = cache_root(cache_dir) / "images" / digest(key)
    if not (root / "index.json").is_file():
        with build_lock(root):
            if not (root / "index.json").is_file():
                _build(reader, key, root, np.asarray(episode_index), np.asarray(lengths, np.int64),
                       progress)
    try:
        index = json.loads((root / "index.json").read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"the frame cache {root} is unreadable ({err}); delete the folder to "
                         "rebuild it") from err
    if index["identity"] != key or index["episode_lengths"] != np.asarray(lengths).tolist():
        raise ValueError(f"the frame cache {root} was built from other data; delete the folder "
                         "to rebuild it")
    return root


def stored_images(root: Path, cameras: Sequence[str], row_starts: np.ndarray,
                  positions: Sequence[int]) -> StoredFrameImages:
    """The stored frames of the episodes at `positions` (source order, in the order given);
    `row_starts`: `[E + 1]` first row of each of the source's episodes. The entry's columns are
    laid out as a `FrameStore`'s, one per camera."""
    store = FrameStore(root, cameras, row_starts)
    return StoredFrameImages({camera: store.column(camera, positions) for camera in cameras})


def _build(reader, key: dict[str, Any], root: Path, episode_index: np.ndarray,
           lengths: np.ndarray, progress: bool) -> None:
    """Decodes every episode into a staging folder (episodes in parallel threads: PyAV decodes
    without the GIL), then renames it to `root`."""
    total = int(lengths.sum())
    first = reader.episode_reader(0)
    try:  # every frame of a camera has its first frame's size (checked as they are written)
        shapes = {camera: image.shape for camera, image in first.images(0).items()}
    finally:
        first.close()
    need = sum(total * int(np.prod(s)) for s in shapes.values())
    root.parent.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(root.parent).free
    if need > 0.9 * free:
        raise ValueError(
            f"data.frame_cache: the decoded frames need {need / 2**30:.1f} GiB but "
            f"{root.parent} has {free / 2**30:.1f} GiB free; set data.frame_cache=False (decode "
            "on request), a smaller model image size, or PI0_ARMFIX_CACHE on a larger disk")
    for stale in root.parent.glob(f".{root.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
        logging.warning("removed %s, a frame cache a killed build left unfinished", stale)
    staging = Path(tempfile.mkdtemp(prefix=f".{root.name}.partial-", dir=root.parent))
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    try:
        columns = {}
        for camera, shape in shapes.items():
            path = staging / f"{camera}.npy"
            with open(path, "wb") as f:
                np.lib.format.write_array_header_1_0(f, {
                    "descr": "|u1", "fortran_order": False, "shape": (total, *shape)})
                header = f.tell()
                f.truncate(header + total * int(np.prod(shape)))
            columns[camera] = (os.open(path, os.O_WRONLY), header, int(np.prod(shape)))

        def decode(position: int) -> int:
            episode = reader.episode_reader(position)
            try:
                for offset in range(episode.length):
                    for camera, image in episode.images(offset).items():
                        fd, header, row_bytes = columns[camera]
                        if image.shape != shapes[camera]:
                            raise ValueError(
                                f"data.frame_cache: camera {camera!r} of episode "
                                f"{int(episode_index[position])} decodes to {image.shape[:2]}, "
                                f"not {shapes[camera][:2]} as the first episode's; a cache needs "
                                "one size per camera: set data.frame_cache=False")
                        os.pwrite(fd, np.ascontiguousarray(image).tobytes(),
                                  header + (int(starts[position]) + offset) * row_bytes)
            finally:
                episode.close()
            return episode.length

        bar = tqdm(total=total, unit="frame", unit_scale=True, disable=not progress, delay=1.0,
                   desc=f"decoding frames once ({', '.join(reader.cameras)})")
        with concurrent.futures.ThreadPoolExecutor(os.cpu_count() or 1) as pool:
            for frames in pool.map(decode, range(len(lengths))):
                bar.update(frames)
        bar.close()
        for fd, _, _ in columns.values():
            os.fsync(fd)
            os.close(fd)
        columns = {}
        (staging / "index.json").write_text(json.dumps({
            "identity": key, "cameras": list(shapes),
            "episode_lengths": lengths.tolist()}))
        os.rename(staging, root)
    finally:
        for fd, _, _ in columns.values():
            os.close(fd)
        shutil.rmtree(staging, ignore_errors=True)
