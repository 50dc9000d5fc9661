"""Statistics of whole action chunks: per-timestep normalization and the chunk correlation.

Two levers of B1K 2025's winners look at a chunk as a whole (docs/design.md §3):

  per-timestep normalization (`data.norm_per_timestep`): the actions at chunk position h are
      normalized with statistics of position h, `[H, A]` instead of `[A]`. With delta actions
      the spread of `a[t + h] - s[t]` grows with h; one statistic for every h squeezes the early
      steps to ~0 and leaves the late ones large.
  correlated noise (`loss.noise_beta < 1`): Σ, the correlation of the normalized chunk over its
      flattened (h, a) entries (`model.noise`).

Both are computed in one pass over the training chunks the batches hold (delta actions applied,
in float64), over up to `data.chunk_stats_chunks` chunk starts spread evenly over the training
frames (every frame when there are fewer): a sample, because Σ is `[H A, H A]` and B1K has 119 M
frames. Per-timestep statistics skip the padded steps of a chunk at an episode end (position h of
a chunk that ran out of episode is not an observation of position h); Σ uses the chunks without
padding. A correlation is unchanged by any per-entry affine map, so Σ of the raw chunks is Σ of
the normalized ones whatever the normalization; the entries of a dim the normalizer holds
constant (its pooled stats' spread below `stats.CONSTANT_SPREAD`) are uncorrelated.

Files, beside the run's `norm_stats.json`: `norm_stats_per_timestep.json` (openpi's format with
`[H][A]` lists per field) and `action_chunk_correlation.npy`, each keyed (`*.key.json`) to what it
was computed from, like the norm stats.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix.data import json_files
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import stats as stats_lib

PER_TIMESTEP_FILE = "norm_stats_per_timestep.json"
CORRELATION_FILE = "action_chunk_correlation.npy"


@dataclasses.dataclass(frozen=True)
class ChunkStats:
    """per_timestep: NormStats with `[H, A]` fields; correlation: Σ `[H * A, H * A]` float64."""

    per_timestep: stats_lib.NormStats
    correlation: np.ndarray


def needed(spec: DataSpec, noise_beta: float) -> bool:
    """Whether a run uses chunk statistics (either lever; `noise_beta`: `loss.noise_beta`)."""
    return spec.statistics.norm_per_timestep or float(noise_beta) < 1.0


def chunk_starts(num_frames: int, max_chunks: int) -> np.ndarray:
    """Up to `max_chunks` frame indices spread evenly over `[0, num_frames)`, deterministic."""
    if max_chunks < 1:
        raise ValueError(f"data.chunk_stats_chunks = {max_chunks} must be >= 1")
    if num_frames <= max_chunks:
        return np.arange(num_frames, dtype=np.int64)
    return np.linspace(0, num_frames - 1, max_chunks).round().astype(np.int64)


def compute_chunk_stats(table: EpisodeTable, *, action_horizon: int,
                        delta_mask: np.ndarray | None, max_chunks: int, constant: np.ndarray,
                        delta_reference: str = "state", start: transforms.EpisodeStart | None = None
                        ) -> ChunkStats:
    """Per-timestep statistics and Σ of the chunks of `table` (see the module docstring);
    `constant` `[A]`: the dims the run's normalizer holds constant (`NormStats.constant` of its
    pooled action stats), uncorrelated in Σ; `delta_reference` and `start`: what the relative
    dims are relative to (`transforms.delta_reference`)."""
    frames = chunk_starts(table.num_frames, max_chunks)
    index, is_pad = transforms.chunk_indices(frames, table.episode_starts, action_horizon)
    chunks = np.asarray(table.actions[index], np.float64)  # [N, H, A]
    if delta_mask is not None:
        reference = transforms.delta_reference(delta_reference, table.actions, table.state,
                                               frames, table.episode_starts, start)
        chunks = transforms.to_delta(chunks, np.asarray(reference, np.float64), delta_mask)
    valid = ~is_pad
    fields = {name: np.zeros(chunks.shape[1:]) for name in stats_lib.FIELDS}
    for h in range(action_horizon):
        steps = chunks[valid[:, h], h]
        if not len(steps):  # no episode is this long: position h is only ever padding
            steps = chunks[:, h]
        fields["mean"][h], fields["std"][h] = steps.mean(0), steps.std(0)
        fields["q01"][h], fields["q99"][h] = np.quantile(steps, [0.01, 0.99], axis=0)
    whole = chunks[valid.all(axis=1)]
    if len(whole) < 2:
        raise ValueError(f"the training episodes have {len(whole)} chunks of "
                         f"{action_horizon} steps without padding: too short for the chunk "
                         "correlation of loss.noise_beta")
    flat = whole.reshape(len(whole), -1)
    std = flat.std(0)
    # Constancy per dim as the normalizer decides it, from the pooled stats: a slow joint's
    # first steps move less than the threshold and still belong to the chunk's correlation.
    constant = np.asarray(constant, bool)
    if constant.shape != chunks.shape[-1:]:
        raise ValueError(f"constant has shape {constant.shape}; the actions have "
                         f"{chunks.shape[-1]} dims")
    live = np.tile(~constant, action_horizon) & (std > 0)
    correlation = np.eye(flat.shape[1])
    centred = (flat[:, live] - flat[:, live].mean(0)) / std[live]
    correlation[np.ix_(live, live)] = centred.T @ centred / len(flat)
    np.fill_diagonal(correlation, 1.0)
    return ChunkStats(stats_lib.NormStats(**fields), correlation)


def chunk_stats_key(spec: DataSpec, source, *, action_horizon: int) -> dict[str, Any]:
    """What the chunk statistics are computed from: the norm stats' key (data, selection, delta
    actions), the horizon and the sample size."""
    key = dataset_lib.norm_stats_key(spec, source, action_horizon=action_horizon)
    key["model.action_horizon"] = int(action_horizon)
    key["data.chunk_stats_chunks"] = spec.statistics.chunk_stats_chunks
    return key


def load_or_compute_chunk_stats(spec: DataSpec, *, action_horizon: int, folder: str | Path,
                                constant: np.ndarray, start: np.ndarray | None = None,
                                source=None, resuming: bool = False) -> ChunkStats:
    """The run's chunk statistics: read from `folder` when their key equals this run's, else
    computed from the training episodes and written there (`constant`, `start`: as
    `compute_chunk_stats`'). A run with checkpoints refuses stats of other data (its weights were
    trained with the old ones)."""
    folder = Path(folder)
    source = source if source is not None else sources.open_source(spec.options, spec.layout)
    key = chunk_stats_key(spec, source, action_horizon=action_horizon)
    key_path = folder / (CORRELATION_FILE + ".key.json")
    paths = (folder / PER_TIMESTEP_FILE, folder / CORRELATION_FILE)
    if all(p.is_file() for p in paths):
        cached = dataset_lib.read_key(key_path)
        if cached == key:
            return ChunkStats(load_per_timestep(paths[0]), np.load(paths[1]))
        if resuming:
            differing = dataset_lib.differing_keys(cached, key)
            raise ValueError(f"{paths[1]} was computed from other data or options than this "
                             f"config (differing: {differing}) and the run's checkpoints were "
                             "trained with it: resume with the config it was started with, or "
                             "start a new --workdir")
    table = source.load_table(dataset_lib.training_episodes(spec, source), images=False)
    stats = compute_chunk_stats(table, action_horizon=action_horizon, delta_mask=spec.delta_mask,
                                delta_reference=spec.delta_reference, constant=constant,
                                start=start,
                                max_chunks=spec.statistics.chunk_stats_chunks)
    save_per_timestep(paths[0], stats.per_timestep)
    # Through a temporary file and a rename, like the norm stats: every process of a run writes.
    with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{CORRELATION_FILE}.", suffix=".npy",
                                     delete=False) as tmp:
        np.save(tmp, stats.correlation)
    os.chmod(tmp.name, 0o644)
    Path(tmp.name).replace(paths[1])
    json_files.write_json_atomic(key_path, key)
    return stats


def save_per_timestep(path: str | Path, stats: stats_lib.NormStats) -> None:
    """openpi's `norm_stats.json` layout with `[H][A]` lists: `{"norm_stats": {"actions": ...}}`."""
    json_files.write_json_atomic(path, {"norm_stats": {"actions": stats.to_json()}})


def load_per_timestep(path: str | Path) -> stats_lib.NormStats:
    """Reads `save_per_timestep`'s file; an error names the file and what is wrong."""
    try:
        entry = json.loads(Path(path).read_text())["norm_stats"]["actions"]
        fields = {f: np.asarray(entry[f], np.float64) for f in stats_lib.FIELDS}
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"per-timestep norm stats {path} are unreadable ({err!r}); delete the "
                         "file to recompute it") from None
    shapes = {f: v.shape for f, v in fields.items()}
    if len(set(shapes.values())) != 1 or fields["mean"].ndim != 2:
        raise ValueError(f"per-timestep norm stats {path}: fields must all be [H][A] lists, got "
                         f"shapes {shapes}")
    return stats_lib.NormStats(**fields)

