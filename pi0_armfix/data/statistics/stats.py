"""Normalization statistics: streaming mean/std/q01/q99 and openpi's `norm_stats.json`.

Statistics are taken over frames, each frame once, in one streaming pass with memory that does
not grow with the dataset:

- mean and std (population, ddof=0) are exact in float64: each block's mean and sum of squared
  deviations are merged with Chan et al.'s pairwise update, so no sum of squares of large
  numbers is ever formed.
- q01 and q99 come from a per-dim histogram on a *dyadic* grid: bins of width `w = 2**k`, aligned
  to multiples of `w`, `capacity = 2 * bins` of them per dim. When the data seen so far no longer
  fits, the width doubles and neighbouring bins merge exactly (the grid stays aligned), so one pass
  suffices and no frame is counted twice. The width starts at the smallest power of two with
  `range / w <= bins` on the first block and only doubles once `range / w > capacity - 1`, so at
  the end `w < 2 * range / bins` (`range` = max - min of the dim). A quantile is read from the
  histogram by interpolating between the two order statistics numpy's `linear` method uses, each
  placed inside its bin, so its error is below one bin: `|q - np.quantile| < 2 * range / bins`,
  i.e. < 4.9e-4 of the dim's range with the default `bins = 4096`. A constant dim is exact.

Statistics that need whole episodes (delta actions over chunks, see `dataset.block_norm_stats`)
re-cut the stream with `whole_episode_blocks`, and a block transform may expand a block lazily
into pieces (one `[n, D]` array per chunk step), so memory stays one block plus one episode.

`norm_stats.json` is openpi's format, `{"norm_stats": {"state"|"actions": {"mean", "std", "q01",
"q99"}}}`. openpi stores values padded to the model's action_dim; `load_norm_stats` reads padded
and unpadded files alike (padding must be zeros), `save_norm_stats` writes the real width.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import tqdm

from pi0_armfix.data import background, json_files
from pi0_armfix.data.episodes import EpisodeTable

FIELDS = ("mean", "std", "q01", "q99")
# The per-frame statistics of the absolute actions, kept beside openpi's two entries: the
# evaluation's units (`pi0_armfix.evaluation.heldout.evaluation_scale`) whatever the normalization
# (balanced stats rescale "actions") or representation (delta dims hold chunk deltas in "actions"),
# and, for actions relative to the previous command, what an episode's first frame is relative to
# (`start_reference`).
ABSOLUTE_ACTIONS = "actions_absolute"
NORM_MODES = ("zscore", "quantile")

# A dim whose spread in the training data (std under z-scoring, q99 - q01 under quantiles) lies
# below this, in data units (a millimetre, a milliradian), is constant: normalization maps it to
# 0, un-normalization returns its stored mean, the loss ignores it and the evaluation measures it
# in data units. One threshold for all of them: B1K 2025's torso dim 6 (action std 0, state std
# 1.1e-4) is constant, its smallest moving dim (base velocity, std 0.08) is 80x above it.
CONSTANT_SPREAD = 1e-3

# Bins per dim of the quantile histogram: error < 2 / DEFAULT_BINS of the dim's range.
DEFAULT_BINS = 4096
# Values per internal slice of a block (its float64 buffers stay in cache).
_SLICE_VALUES = 1 << 20
# Column reductions handle this many rows per vectorized step (see `_column_reduce`).
_ROW_GROUP = 64
# |x| / w stays below 2**_MAX_BIN_BITS so that bin indices are exact integers in float64.
_MAX_BIN_BITS = 50
# Finest bin width 2**-1000 (1/w stays finite); a dim of zeros starts there and coarsens later.
_MIN_LOG2_WIDTH = -1000


@dataclasses.dataclass(frozen=True)
class NormStats:
    """Per-dim normalization statistics of one array (`actions` or `state`); each `[D]` float64
    (`[H, D]` for per-timestep statistics, `data.chunk_stats`)."""

    mean: np.ndarray
    std: np.ndarray
    q01: np.ndarray
    q99: np.ndarray

    @property
    def width(self) -> int:
        return len(self.mean)

    def to_json(self) -> dict[str, list]:
        """Plain lists (nested for per-timestep `[H, A]` fields)."""
        return {name: np.asarray(getattr(self, name), np.float64).tolist() for name in FIELDS}

    def replace(self, **changes: np.ndarray) -> "NormStats":
        return dataclasses.replace(self, **changes)

    def spread(self, mode: str) -> np.ndarray:
        """What a normalization `mode` divides by: std (zscore) or q99 - q01 (quantile)."""
        if mode == "zscore":
            return np.asarray(self.std, np.float64)
        if mode == "quantile":
            return np.asarray(self.q99, np.float64) - np.asarray(self.q01, np.float64)
        raise ValueError(f"data.norm must be one of {NORM_MODES}, got {mode!r}")

    def constant(self, mode: str) -> np.ndarray:
        """bool, shaped like a field: the dims whose `spread(mode)` is below `CONSTANT_SPREAD`."""
        return self.spread(mode) < CONSTANT_SPREAD


def _column_reduce(ufunc: np.ufunc, x: np.ndarray) -> np.ndarray:
    """`ufunc.reduce(x, axis=0)` of `[n, D]`: numpy reduces a narrow C-ordered array one short
    row at a time, so rows are first combined `_ROW_GROUP` at a time as one long row (~8x faster
    for D = 23)."""
    n, width = x.shape
    head = n - n % _ROW_GROUP
    parts = [ufunc.reduce(x[head:], axis=0)] if head < n else []
    if head:
        wide = ufunc.reduce(x[:head].reshape(-1, _ROW_GROUP * width), axis=0)
        parts.append(ufunc.reduce(wide.reshape(_ROW_GROUP, width), axis=0))
    return ufunc.reduce(np.stack(parts), axis=0)


def _column_sum_of_squares(x: np.ndarray) -> np.ndarray:
    """`(x * x).sum(0)` of `[n, D]` float64, vectorized as `_column_reduce`."""
    n, width = x.shape
    head = n - n % _ROW_GROUP
    total = np.einsum("nd,nd->d", x[head:], x[head:])
    if head:
        wide = x[:head].reshape(-1, _ROW_GROUP * width)
        total += np.einsum("nk,nk->k", wide, wide).reshape(_ROW_GROUP, width).sum(0)
    return total


class StreamingStats:
    """Exact mean/std and histogram quantiles of a stream of `[n, D]` blocks (see module doc)."""

    def __init__(self, width: int, bins: int = DEFAULT_BINS):
        self.width = int(width)
        self.bins = int(bins)
        self.capacity = 2 * self.bins
        self.count = 0
        self.mean = np.zeros(self.width)
        self.m2 = np.zeros(self.width)
        self.min = np.full(self.width, np.inf)
        self.max = np.full(self.width, -np.inf)
        self.log2_width = np.zeros(self.width, np.int64)  # bin width of dim d is 2**log2_width[d]
        self.base = np.zeros(self.width)  # grid index of column 0 (an integer, kept as float64)
        self.counts = np.zeros((self.width, self.capacity), np.int64)
        self._gridded = False  # whether the grid was set from the data yet
        # Reused per-slice buffers: fresh large temporaries would cost a page fault per page.
        self._slice_frames = max(_ROW_GROUP, _SLICE_VALUES // max(self.width, 1) // _ROW_GROUP
                                 * _ROW_GROUP)
        self._x64 = np.empty((self._slice_frames, self.width))
        self._work = np.empty((self._slice_frames, self.width))
        self._index = np.empty((self._slice_frames, self.width), np.intp)

    # ------------------------------------------------------------------ accumulation

    def update(self, x: np.ndarray, what: str = "data") -> None:
        """Adds the frames `x` `[n, D]`. `what` names the array in errors (non-finite values)."""
        x = np.asarray(x)
        if x.ndim != 2 or x.shape[1] != self.width:
            raise ValueError(f"{what}: expected blocks of shape [n, {self.width}], got {x.shape}")
        for start in range(0, len(x), self._slice_frames):
            self._update_slice(x[start:start + self._slice_frames], what)

    def _update_slice(self, x: np.ndarray, what: str) -> None:
        n = len(x)
        if n == 0:
            return
        if self.width == 0:  # a set without a state: frames counted, nothing else to keep
            self.count += n
            return
        block_min, block_max = _column_reduce(np.minimum, x), _column_reduce(np.maximum, x)
        if not (np.isfinite(block_min).all() and np.isfinite(block_max).all()):
            bad = np.flatnonzero(~(np.isfinite(block_min) & np.isfinite(block_max)))
            raise ValueError(f"{what} has non-finite values (NaN or inf) in dim(s) {bad.tolist()}")
        x64, work, index = self._x64[:n], self._work[:n], self._index[:n]
        np.copyto(x64, x)
        block_mean = _column_reduce(np.add, x64) / n
        np.subtract(x64, block_mean, out=work)
        self._merge_moments(n, block_mean, _column_sum_of_squares(work))
        self.min = np.minimum(self.min, block_min)
        self.max = np.maximum(self.max, block_max)
        self._fit_grid()
        # Flat bin index: (x / w - base) + d * (capacity + 1). x / w is exact (w a power of two);
        # the extra column per dim catches a value that rounds up onto the top edge.
        stride = self.capacity + 1
        np.multiply(x64, np.exp2(-self.log2_width.astype(np.float64)), out=work)
        np.subtract(work, self.base - np.arange(self.width) * stride, out=work)
        np.copyto(index, work, casting="unsafe")  # truncation = floor: the values are >= 0
        flat = np.bincount(index.ravel(), minlength=self.width * stride)
        flat = flat.reshape(self.width, stride)
        flat[:, -2] += flat[:, -1]
        self.counts += flat[:, :-1]

    def _merge_moments(self, n: int, mean: np.ndarray, m2: np.ndarray) -> None:
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2 + delta * delta * (self.count * n / total)
        self.count = total

    def _fit_grid(self) -> None:
        """Coarsens / re-bases the dims whose grid no longer covers [min, max]."""
        if self._gridded:
            inverse_width = np.exp2(-self.log2_width.astype(np.float64))
            covered = ((np.floor(self.min * inverse_width) >= self.base)
                       & (np.floor(self.max * inverse_width) < self.base + self.capacity))
        else:
            covered = np.zeros(self.width, bool)
        for d in np.flatnonzero(~covered):
            lo, hi = self.min[d], self.max[d]
            k = self.log2_width[d] if self._gridded else self._initial_log2_width(lo, hi)
            while self._grid_index(hi, k) - self._grid_index(lo, k) >= self.capacity:
                k += 1
            self._regrid(d, k, self._grid_index(lo, k))
        self._gridded = True

    def _initial_log2_width(self, lo: float, hi: float) -> int:
        magnitude = max(abs(lo), abs(hi))
        k = _MIN_LOG2_WIDTH
        if magnitude > 0:
            k = max(k, math.frexp(magnitude)[1] - _MAX_BIN_BITS)
        if hi > lo:
            k = max(k, math.ceil(math.log2((hi - lo) / self.bins)))
        return k

    @staticmethod
    def _grid_index(value: float, log2_width: int) -> float:
        return math.floor(math.ldexp(value, -int(log2_width)))

    def _regrid(self, d: int, log2_width: int, base: float) -> None:
        """Moves dim d's counts onto the grid (2**log2_width, base): exact, bins only merge."""
        old = self.counts[d].copy()
        occupied = np.flatnonzero(old)
        self.counts[d] = 0
        if occupied.size:
            shift = int(log2_width - self.log2_width[d])
            index = np.floor((self.base[d] + occupied) / 2.0**shift) - base
            np.add.at(self.counts[d], index.astype(np.intp), old[occupied])
        self.log2_width[d] = log2_width
        self.base[d] = base

    # ------------------------------------------------------------------ results

    def _bin_edges(self) -> tuple[np.ndarray, np.ndarray]:
        """Left edge of column 0 and bin width, `[D]` each."""
        width = np.exp2(self.log2_width.astype(np.float64))
        return self.base * width, width

    def _order_statistic(self, rank: np.ndarray) -> np.ndarray:
        """Estimate of the `rank`-th smallest value (0-based) of each dim, inside its bin."""
        left, width = self._bin_edges()
        cumulative = np.cumsum(self.counts, axis=1)
        result = np.empty(self.width)
        for d in range(self.width):
            column = int(np.searchsorted(cumulative[d], rank[d], side="right"))
            below = cumulative[d, column - 1] if column else 0
            within = (rank[d] - below + 0.5) / self.counts[d, column]
            result[d] = left[d] + (column + within) * width[d]
        return np.clip(result, self.min, self.max)

    def quantile(self, q: float) -> np.ndarray:
        """`[D]` quantile `q` as `np.quantile(..., method="linear")`, error < one bin."""
        if self.count == 0:
            raise ValueError("no frames were seen: cannot compute quantiles")
        position = q * (self.count - 1)
        lower = math.floor(position)
        fraction = position - lower
        below = self._order_statistic(np.full(self.width, lower))
        above = self._order_statistic(np.full(self.width, min(lower + 1, self.count - 1)))
        return below + fraction * (above - below)

    def fraction_below(self, value: np.ndarray) -> np.ndarray:
        """`[D]` fraction of the frames `<= value[d]`, interpolated inside the bin that holds
        `value[d]` (so off by at most that bin's share of the frames)."""
        left, width = self._bin_edges()
        position = np.clip((np.asarray(value, np.float64) - left) / width, 0, self.capacity)
        column = np.minimum(position.astype(np.intp), self.capacity - 1)
        cumulative = np.cumsum(self.counts, axis=1)
        rows = np.arange(self.width)
        below = np.where(column > 0, cumulative[rows, np.maximum(column - 1, 0)], 0)
        partial = self.counts[rows, column] * np.clip(position - column, 0, 1)
        return (below + partial) / max(self.count, 1)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.m2 / max(self.count, 1))

    def result(self) -> NormStats:
        if self.count == 0:
            raise ValueError("no frames were seen: cannot compute normalization statistics")
        return NormStats(mean=self.mean.copy(), std=self.std, q01=self.quantile(0.01),
                         q99=self.quantile(0.99))


# ---------------------------------------------------------------------- streaming over blocks

Block = Mapping[str, np.ndarray]


def checked_blocks(blocks: Iterable[Block], locate: Callable[[int], str],
                   name_dim: Callable[[str, int], str] | None = None) -> Iterator[Block]:
    """The blocks, checked as they stream: a NaN or infinite value is a ValueError naming the
    feature, the episode, the dim (`name_dim(key, dim)`: where it is stored, for a selection),
    and (`locate(episode id)`) the file, before any statistic or weight is computed from it."""
    for block in blocks:
        for key, values in block.items():
            values = np.asarray(values)
            if key == "episode_index" or not np.issubdtype(values.dtype, np.floating):
                continue
            bad = ~np.isfinite(values)
            if bad.any():
                row, *dim = (int(i) for i in np.argwhere(bad)[0])
                episode = int(block["episode_index"][row])
                raise ValueError(
                    f"{key} of episode {episode} ({locate(episode)}) holds {values[(row, *dim)]}"
                    + ((f" in {name_dim(key, dim[0])}" if name_dim else f" in dim {dim[0]}")
                       if dim else "")
                    + f" ({int(bad[block['episode_index'] == episode].sum())} non-finite "
                    "value(s) in this part of it): repair the file or leave the episode out of "
                    "the dataset root")
        yield block


def table_blocks(table: EpisodeTable, keys: Sequence[str] = ("actions", "state"),
                 block_frames: int = 65536) -> Iterator[dict[str, np.ndarray]]:
    """Blocks of a table (in memory or on disk) in the format of `Source.iter_blocks`:
    `{key: [n, ...], "episode_index": [n] int64 (dataset episode index of each frame)}`."""
    for start in range(0, table.num_frames, block_frames):
        stop = min(start + block_frames, table.num_frames)
        block = {key: np.asarray(getattr(table, key)[start:stop]) for key in keys}
        block["episode_index"] = table.episode_index[table.episode_of_frame(
            np.arange(start, stop))]
        yield block


def whole_episode_blocks(blocks: Iterable[Block]) -> Iterator[dict[str, np.ndarray]]:
    """Re-cuts a stream of blocks (episodes contiguous and in order, each block with
    `"episode_index"` `[n]`) so that every block holds whole episodes: the last episode of a block
    is carried into the next one. Memory: one block plus one episode."""
    carry: dict[str, np.ndarray] | None = None
    for block in blocks:
        if carry is not None:
            block = {key: np.concatenate([carry[key], block[key]]) for key in block}
        episode = np.asarray(block["episode_index"])
        if not len(episode):
            continue
        changes = np.flatnonzero(episode[1:] != episode[:-1])
        cut = int(changes[-1]) + 1 if len(changes) else 0
        if cut:
            yield {key: value[:cut] for key, value in block.items()}
        carry = {key: value[cut:] for key, value in block.items()}
    if carry is not None:
        yield carry


def compute_stats(blocks: Iterable[Block], keys: Sequence[str] = ("actions", "state"), *,
                  bins: int = DEFAULT_BINS, total_frames: int | None = None,
                  transform: Callable[[Block], Block] | None = None,
                  progress: bool = True) -> dict[str, StreamingStats]:
    """One streaming pass over `blocks` (each `{key: [n, D]}`) -> an accumulator per key.

    `transform` is applied to each block first (e.g. delta actions); it may give a key an
    iterator of `[m, D]` pieces instead of one array, all of which that key's accumulator takes,
    so a block that expands (into chunk steps) is never held whole. `total_frames` only sizes the
    progress bar, which counts the frames of the blocks before `transform`. Memory: one block (or
    piece) plus `[D, 2 * bins]` counts per key.
    """
    accumulators: dict[str, StreamingStats] = {}
    with tqdm.tqdm(total=total_frames, unit="frame", unit_scale=True, desc="norm stats",
                   disable=not progress) as bar:
        for block in background.prefetched(blocks):
            frames = len(next(iter(block.values())))
            if transform is not None:
                block = transform(block)
            for key in keys:
                value = block[key]
                for piece in value if isinstance(value, Iterator) else (value,):
                    piece = np.asarray(piece)
                    if key not in accumulators:
                        accumulators[key] = StreamingStats(piece.shape[-1], bins)
                    accumulators[key].update(piece, what=key)
            bar.update(frames)
    missing = [key for key in keys if key not in accumulators]
    if missing:
        raise ValueError(f"no frames were seen: the data is empty (keys {missing})")
    return accumulators


def compute_norm_stats(blocks: Iterable[Block], keys: Sequence[str] = ("actions", "state"),
                       **kwargs) -> dict[str, NormStats]:
    """`compute_stats` -> `{key: NormStats}`."""
    return {key: acc.result() for key, acc in compute_stats(blocks, keys, **kwargs).items()}


# ---------------------------------------------------------------------- norm_stats.json

def save_norm_stats(path: str | Path, stats: Mapping[str, NormStats]) -> None:
    """Writes openpi's `norm_stats.json` (real widths, no padding), atomically: several processes
    of a run may write the same file at once, and a reader never sees a partial file."""
    json_files.write_json_atomic(path, {"norm_stats": {key: value.to_json() for key, value in stats.items()}})


def load_norm_stats(path: str | Path, widths: Mapping[str, int] | None = None,
                    optional: Mapping[str, int | None] | None = None) -> dict[str, NormStats]:
    """Reads openpi's `norm_stats.json`.

    Args:
      path: the file.
      widths: `{key: real width or None}` of the keys to read (e.g. `{"actions": 23}`): a padded
        entry is cut to the width (see `fit_width`); None keeps the stored width. `widths=None`
        reads every key at its stored width.
      optional: like `widths`, for keys read only when the file has them (`actions_absolute`,
        which openpi's files lack).

    Raises:
      ValueError naming the file and key for a missing file, bad JSON, a missing key or field,
      fields of different lengths, non-finite values, a negative std, or a width mismatch.
    """
    path = Path(path)
    payload = json_files.read_json(path, f"norm stats file {path}")
    entries = payload.get("norm_stats") if isinstance(payload, dict) else None
    if not isinstance(entries, dict):
        raise ValueError(f"norm stats file {path} has no 'norm_stats' object (openpi format: "
                         '{"norm_stats": {"state": {...}, "actions": {...}}})')
    stats = {}
    wanted = dict(widths) if widths is not None else dict.fromkeys(entries)
    wanted.update({k: w for k, w in (optional or {}).items() if k in entries})
    for key, width in wanted.items():
        where = f"norm stats file {path}, norm_stats[{key!r}]"
        stats[key] = _parse_entry(entries.get(key), where, sorted(entries))
        if width is not None:
            stats[key] = fit_width(stats[key], width, where)
    return stats


def _parse_entry(entry: Any, where: str, available: list[str]) -> NormStats:
    if not isinstance(entry, dict):
        raise ValueError(f"{where} is missing (the file has {available})")
    values = {}
    for field in FIELDS:
        if field not in entry:
            raise ValueError(f"{where} has no {field!r} (needs {list(FIELDS)})")
        try:
            array = np.asarray(entry[field], np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}[{field!r}] is not a list of numbers") from None
        if array.ndim != 1 or not np.isfinite(array).all():
            raise ValueError(f"{where}[{field!r}] must be a flat list of finite numbers")
        values[field] = array
    lengths = {field: len(v) for field, v in values.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"{where} has fields of different lengths {lengths}")
    if (values["std"] < 0).any():
        raise ValueError(f"{where}['std'] has negative values at dims "
                         f"{np.flatnonzero(values['std'] < 0).tolist()}")
    return NormStats(**values)


def fit_width(stats: NormStats, width: int, where: str) -> NormStats:
    """Cuts padded statistics (openpi pads to action_dim) to the data's `width`.

    Raises:
      ValueError naming `where` if the stats are narrower than the data, or if the dims past
      `width` are not zero padding (then they are the statistics of other data).
    """
    if stats.width == width:
        return stats
    if stats.width < width:
        raise ValueError(f"{where} has {stats.width} values but the data has {width} dims")
    padding = np.stack([getattr(stats, field)[width:] for field in FIELDS])
    if padding.any():
        raise ValueError(f"{where} has {stats.width} values for {width} data dims and dims "
                         f"{width}..{stats.width - 1} are not zero padding: the stats belong to "
                         "other data")
    return NormStats(*(getattr(stats, field)[:width] for field in FIELDS))


def start_reference(norm_stats: Mapping[str, NormStats], width: int) -> np.ndarray:
    """`[width]` the training split's mean absolute action: where a dim relative to the previous
    command starts an episode when the state does not hold its joint (`transforms.EpisodeStart`),
    in the action's own units.

    Raises:
      ValueError where the stats lack `ABSOLUTE_ACTIONS` (stats computed elsewhere).
    """
    entry = norm_stats.get(ABSOLUTE_ACTIONS)
    if entry is None:
        raise ValueError(f"the norm stats have no {ABSOLUTE_ACTIONS!r} entry, which actions "
                         "relative to the previous command start from (data.delta_reference="
                         "'previous_action'): let the run compute its own stats "
                         "(data.norm_stats='')")
    return np.asarray(fit_width(entry, width, f"norm stats {ABSOLUTE_ACTIONS!r}").mean)
