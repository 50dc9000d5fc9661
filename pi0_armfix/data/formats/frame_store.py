"""Frame columns on disk: what lets a 119 M-frame dataset train in bounded memory.

A source's selected actions and state (float32) and its rows' timestamps (float64, for video) are
written once, for every episode of the source in its order, into

    <cache_root()>/frames/<hash of source.identity()>/
        actions.npy  [N, A] float32     state.npy  [N, S] float32     timestamp.npy  [N] float64
        index.json   {"identity": ..., "episode_index": [E], "episode_lengths": [E]}

and read by row (`FrameColumn`, positioned reads). A training process and all its data workers
then hold an index per episode (not per frame) and share the frames through the host's page
cache; pickling a `FrameColumn` (for a Grain worker) sends its file name and row ranges, not its
rows.

The key (`source.identity()`) names the dataset root, layout version, every data file's size and
modification time, the episodes, the feature keys and selections: a changed file or another
selection is another entry, never the old one. Building streams `source.iter_blocks` (one parquet
row group at a time) into a staging folder renamed when complete, under a lock shared by the
processes of a host (and hosts on a shared file system), with a progress bar. Disk: 4 bytes per
selected dim per frame plus 8 per frame for timestamps (B1K 2025, 23 + 23 dims: ~23 GB).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pi0_armfix.cache import build_lock, cache_root, digest
from pi0_armfix.data.statistics import stats as stats_lib

COLUMNS = ("actions", "state", "timestamp")
_DTYPES = {"actions": np.float32, "state": np.float32, "timestamp": np.float64}
_FORMAT = 1  # bump when the entry layout changes


class FrameColumn:
    """Rows of an `.npy` column on disk, as a read-only array-like that indexes like numpy.

    The rows are runs `[start, start + length)` of the file, concatenated; row i of the column
    maps to its file row through the runs (searchsorted over the runs, one per episode at most),
    so memory is per run, not per row. Reads are `os.pread`s of the rows asked for (neighbouring
    rows merged into one read): they go through the host's page cache, shared by every process,
    but nothing is mapped into the process, so its resident memory does not grow with the rows
    it has read (a memory map's pages would count towards every reader's RSS). The file is
    opened lazily per process; a column pickles as its recipe (file name and runs).

    Supports `column[int | slice | int array]` (and a tuple whose first item is one of those),
    `len`, `shape`, `dtype`, `ndim` and `np.asarray(column)` (reads every row).
    """

    # Rows closer than this are read in one call (fewer system calls; a few spare bytes).
    _MERGE_GAP = 16

    def __init__(self, path: str | Path, starts: Sequence[int], lengths: Sequence[int]):
        self.path = str(path)
        starts, lengths = np.asarray(starts, np.int64), np.asarray(lengths, np.int64)
        if len(starts):  # merge touching runs: a contiguous selection is one run
            breaks = np.flatnonzero(starts[1:] != starts[:-1] + lengths[:-1]) + 1
            bounds = np.concatenate([[0], breaks, [len(starts)]])
            lengths = np.add.reduceat(lengths, bounds[:-1])
            starts = starts[bounds[:-1]]
        self._starts, self._lengths = starts, lengths
        self._offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        with open(self.path, "rb") as f:
            np.lib.format.read_magic(f)
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            self._header = f.tell()
        if fortran:
            raise ValueError(f"{self.path} is stored in Fortran order")
        self.dtype, self._row_shape = np.dtype(dtype), tuple(shape[1:])
        self._row_bytes = self.dtype.itemsize * int(np.prod(self._row_shape, dtype=np.int64))
        self._fd: int | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_fd": None}

    def __del__(self) -> None:
        if getattr(self, "_fd", None) is not None:
            os.close(self._fd)

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self), *self._row_shape)

    @property
    def ndim(self) -> int:
        return 1 + len(self._row_shape)

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def rows(self, index: np.ndarray) -> np.ndarray:
        """Column rows `[...]` int -> file rows `[...]` int64."""
        index = np.asarray(index, np.int64)
        n = len(self)
        if index.size and (index.min() < -n or index.max() >= n):
            raise IndexError(f"row index out of range for a column of {n} rows ({self.path})")
        index = np.where(index < 0, index + n, index)
        if len(self._starts) == 1:
            return index + self._starts[0]
        run = np.searchsorted(self._offsets, index, side="right") - 1
        return self._starts[run] + index - self._offsets[run]

    def _read(self, first: int, count: int) -> np.ndarray:
        """File rows [first, first + count) -> `[count, *row_shape]`."""
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDONLY)
        size = count * self._row_bytes
        data = os.pread(self._fd, size, self._header + first * self._row_bytes)
        if len(data) != size:
            raise ValueError(f"{self.path} is truncated (row {first + count - 1} is past its "
                             "end); delete its frame cache folder to rebuild it")
        return np.frombuffer(data, self.dtype).reshape(count, *self._row_shape)

    def _take(self, file_rows: np.ndarray) -> np.ndarray:
        """File rows `[...]` -> values `[..., *row_shape]`, one read per group of close rows."""
        flat = file_rows.ravel()
        if not flat.size:
            return np.empty((*file_rows.shape, *self._row_shape), self.dtype)
        unique, inverse = np.unique(flat, return_inverse=True)
        bounds = np.concatenate([[0], np.flatnonzero(np.diff(unique) > self._MERGE_GAP) + 1,
                                 [len(unique)]])  # unique[bounds[i]:bounds[i + 1]]: one read
        firsts, lasts = unique[bounds[:-1]], unique[bounds[1:] - 1]
        parts = [self._read(int(a), int(b - a + 1)) for a, b in zip(firsts, lasts)]
        values = parts[0] if len(parts) == 1 else np.concatenate(parts)
        # Position of each unique row inside the concatenated reads.
        run = np.repeat(np.arange(len(firsts)), np.diff(bounds))
        read_offsets = np.concatenate([[0], np.cumsum(lasts - firsts + 1)])[:-1]
        where = read_offsets[run] + unique - firsts[run]
        return values[where[inverse]].reshape(*file_rows.shape, *self._row_shape)

    def __getitem__(self, key: Any) -> np.ndarray:
        if isinstance(key, tuple):
            if not key:
                return self[:]
            rows = self[key[0]]
            leading = 1 if isinstance(key[0], slice) else np.ndim(key[0])
            return rows[(slice(None),) * leading + key[1:]]
        if isinstance(key, slice):
            start, stop, step = key.indices(len(self))
            if step == 1 and len(self._starts) == 1:
                return self._read(int(self._starts[0]) + start, max(stop - start, 0)).copy()
            return self._take(self.rows(np.arange(start, stop, step)))
        if np.ndim(key) == 0:
            return self._take(self.rows(np.array([key])))[0]
        return self._take(self.rows(np.asarray(key)))

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        values = self[:]
        return values if dtype is None else values.astype(dtype)

    def __repr__(self) -> str:
        return f"FrameColumn({self.path!r}, {len(self)} rows of {len(self._starts)} run(s))"


class FrameStore:
    """The on-disk frame columns of one source (see the module docstring).

    Attributes:
      root: the entry's folder.
      columns: the column names stored ("actions", "state", and "timestamp" when the source
        has timestamps).
      row_starts: `[E + 1]` int64, first row of each episode (source order) and the total.
    """

    def __init__(self, root: Path, columns: Sequence[str], row_starts: np.ndarray):
        self.root, self.columns, self.row_starts = root, tuple(columns), row_starts

    @classmethod
    def open(cls, source, *, cache_dir: str | os.PathLike | None = None,
             progress: bool = True) -> "FrameStore":
        """The store of `source` (built on first use; see the module docstring).

        `source` provides `identity()`, `episode_index`, `episode_lengths`, `block_keys` (the
        `iter_blocks` keys it has, of `COLUMNS`), `iter_blocks` and `episode_file`."""
        identity = {"format": _FORMAT, **source.identity()}
        root = cache_root(cache_dir) / "frames" / digest(identity)
        if not (root / "index.json").is_file():
            with build_lock(root):
                if not (root / "index.json").is_file():
                    _build(source, identity, root, progress)
        try:
            index = json.loads((root / "index.json").read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"the frame cache {root} is unreadable ({err}); delete the folder "
                             "to rebuild it") from err
        lengths = np.asarray(index["episode_lengths"], np.int64)
        if (index["identity"] != json.loads(json.dumps(identity, default=str))
                or not np.array_equal(lengths, source.episode_lengths)):
            raise ValueError(f"the frame cache {root} was built from other data than "
                             f"{identity.get('root', 'this source')}; delete the folder to "
                             "rebuild it")
        row_starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        return cls(root, index["columns"], row_starts)

    def column(self, name: str, positions: Sequence[int]) -> FrameColumn:
        """Rows of the episodes at `positions` (source order positions, in the order given)."""
        if name not in self.columns:
            raise ValueError(f"the frame cache {self.root} has no {name!r} column "
                             f"(it has {list(self.columns)})")
        positions = np.asarray(positions, np.int64)
        return FrameColumn(self.root / f"{name}.npy", self.row_starts[positions],
                            self.row_starts[positions + 1] - self.row_starts[positions])


def _build(source, identity: dict[str, Any], root: Path, progress: bool) -> None:
    """Streams every episode of `source` into a staging folder, then renames it to `root`."""
    lengths = np.asarray(source.episode_lengths, np.int64)
    total = int(lengths.sum())
    keys = [k for k in COLUMNS if k in source.block_keys]
    root.parent.mkdir(parents=True, exist_ok=True)
    # Under the build lock no other process builds this store: a staging folder of it is what a
    # killed build left (as large as the store itself).
    for stale in root.parent.glob(f".{root.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
        logging.warning("removed %s, a frame cache a killed build left unfinished", stale)
    staging = Path(tempfile.mkdtemp(prefix=f".{root.name}.partial-", dir=root.parent))
    files: dict[str, Any] = {}
    try:
        row = 0
        bar = tqdm(total=total, unit="frame", unit_scale=True, disable=not progress, delay=1.0,
                   desc=f"frame cache {root.name}")
        for block in stats_lib.checked_blocks(source.iter_blocks(tuple(keys)),
                                              source.episode_file,
                                              getattr(source, "dim_name", None)):
            n = len(block["episode_index"])
            for key in keys:
                values = np.ascontiguousarray(block[key], _DTYPES[key])
                if key not in files:  # appended in order: no mapping, so no resident pages
                    shape = (total,) if key == "timestamp" else (total, values.shape[1])
                    files[key] = open(staging / f"{key}.npy", "wb")
                    np.lib.format.write_array_header_1_0(files[key], {
                        "descr": np.lib.format.dtype_to_descr(np.dtype(_DTYPES[key])),
                        "fortran_order": False, "shape": shape})
                files[key].write(values.tobytes())
            row += n
            bar.update(n)
        bar.close()
        if row != total:
            raise ValueError(f"{identity.get('root')}: the data files hold {row} frames but the "
                             f"episode metadata lists {total}")
        for f in files.values():
            f.flush()
            os.fsync(f.fileno())
            f.close()
        (staging / "index.json").write_text(json.dumps({
            "identity": identity, "columns": keys,
            "episode_index": np.asarray(source.episode_index).tolist(),
            "episode_lengths": lengths.tolist()}, default=str))
        os.rename(staging, root)
    finally:
        for f in files.values():
            f.close()
        shutil.rmtree(staging, ignore_errors=True)
