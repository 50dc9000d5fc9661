"""Normalization in numpy (docs/design.md §4), per dim, written as one affine map
`y = (x - offset) * scale + shift`:
  zscore:   (x - mean) / (std + eps)
  quantile: (x - q01) / (q99 - q01 + eps) * 2 - 1
A constant dim (`NormStats.constant`: its spread below `stats.CONSTANT_SPREAD`, e.g. B1K's torso
dim 6) has scale 0: it normalizes to 0, never blown up by 1/eps, and `inverse` returns its stored
mean whatever the model put there, so a policy's leftover noise never lands on a joint the data
never moves. Constancy is a property of a dim, never of a chunk position: per-timestep statistics
take it from the dim's pooled statistics, because the first steps of a slow joint's delta actions
(a real robot at 30 fps moves a joint ~1e-4 per frame) have a spread below the threshold and would
otherwise be pinned to their mean with no loss. Works on any number of leading batch dims.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pi0_armfix.data.statistics.stats import NORM_MODES, NormStats

EPS = 1e-6  # openpi's epsilon in both normalizations


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """`y = (x - offset) * scale + shift` per dim; each field `[D]` float32, or `[H, D]` per chunk
    position (per-timestep normalization of `[..., H, D]` chunks). A constant dim has scale 0,
    offset its mean and shift 0."""

    offset: np.ndarray
    scale: np.ndarray
    shift: np.ndarray

    @classmethod
    def from_stats(cls, stats: NormStats, mode: str,
                   constant: np.ndarray | None = None) -> "Normalizer":
        """`constant`: bool `[D]`, the constant dims (of the pooled statistics when `stats` are
        per chunk position `[H, D]`); None = `stats.constant(mode)`."""
        spread = stats.spread(mode)
        constant = np.broadcast_to(stats.constant(mode) if constant is None else constant,
                                   spread.shape)
        if mode == "zscore":
            offset, shift = stats.mean, 0.0
        else:
            offset, shift = stats.q01, -1.0
        scale = np.where(constant, 0.0, (2.0 if mode == "quantile" else 1.0) / (spread + EPS))
        offset = np.where(constant, stats.mean, offset)
        shift = np.where(constant, 0.0, np.broadcast_to(shift, constant.shape))
        return cls(*(np.asarray(v, np.float32) for v in (offset, scale, shift)))

    @property
    def constant(self) -> np.ndarray:
        """bool `[D]` (or `[H, D]`): the constant dims."""
        return self.scale == 0

    @property
    def width(self) -> int:
        return self.offset.shape[-1]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """`[..., D]` raw -> normalized float32."""
        return ((np.asarray(x, np.float32) - self.offset) * self.scale + self.shift)

    def inverse(self, y: np.ndarray) -> np.ndarray:
        """`[..., D]` normalized -> raw float32 (the first D dims of a padded array)."""
        y = np.asarray(y, np.float32)[..., :self.width]
        unscale = np.divide(1.0, self.scale, out=np.zeros_like(self.scale), where=~self.constant)
        return (y - self.shift) * unscale + self.offset


def openpi_normalize(x: np.ndarray, stats: NormStats, mode: str) -> np.ndarray:
    """`[..., D]` raw -> normalized exactly as openpi computes it: float64, `(x - q01) / (q99 -
    q01 + 1e-6) * 2 - 1` or `(x - mean) / (std + 1e-6)`, with no constant-dim rule (a constant
    dim lands where openpi's arithmetic puts it). What pi0.5 digitizes into 256 bins for its
    prompt's state tokens, where float32 rounding moves values across a bin edge."""
    x = np.asarray(x, np.float64)
    if mode == "quantile":
        return (x - stats.q01) / (stats.q99 - stats.q01 + EPS) * 2.0 - 1.0
    if mode == "zscore":
        return (x - stats.mean) / (stats.std + EPS)
    raise ValueError(f"data.norm must be one of {NORM_MODES}, got {mode!r}")
