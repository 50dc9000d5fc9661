"""The flow's noise law: independent N(0, I), or correlated over the action chunk
(docs/design.md §3).

B1K 2025's first place drew the flow-matching noise from `N(0, β I + (1 - β) Σ)`, with Σ the
correlation of normalized action chunks over (h, d): noise that moves like the data (neighbouring
steps and coupled joints together) makes the flow from noise to a smooth arm trajectory shorter.
Σ is estimated from the training chunks (`data.chunk_stats`), stored beside the norm stats, and
turned here into one Cholesky factor L with `L L^T = β I + (1 - β) Σ`; training and sampling both
draw `noise = L z`, z ~ N(0, I). With a correlation (unit diagonal) every entry keeps variance 1,
as in pi0. β = 1 is pi0's independent noise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def correlated_noise_factor(correlation: np.ndarray, beta: float, *, horizon: int | None = None,
                            real_dim: int | None = None, action_dim: int | None = None
                            ) -> np.ndarray:
    """L `[H * D, H * D]` float32 with `L L^T = β I + (1 - β) Σ`.

    Args:
      correlation: Σ `[H * A, H * A]`, the chunk correlation over the A = `real_dim` real dims,
        flattened (h, a) -> h * A + a.
      beta: in (0, 1]: the share of independent noise (keeps the covariance positive definite).
      horizon, real_dim, action_dim: when given, Σ is embedded into the padded `[H, D]` chunk
        (D = action_dim), the padding dims independent.
    """
    if not 0.0 < beta <= 1.0:
        raise ValueError(f"loss.noise_beta = {beta} must be in (0, 1] (1 = independent noise)")
    sigma = np.asarray(correlation, np.float64)
    if horizon is not None and action_dim is not None and real_dim is not None:
        index = (np.arange(horizon)[:, None] * action_dim + np.arange(real_dim)).reshape(-1)
        full = np.eye(horizon * action_dim)
        full[np.ix_(index, index)] = sigma
        sigma = full
    cov = beta * np.eye(len(sigma)) + (1.0 - beta) * sigma
    return np.linalg.cholesky(cov).astype(np.float32)


def flow_noise(rng: jax.Array, shape: tuple[int, int, int], factor: jax.Array | None = None
               ) -> jax.Array:
    """The flow's noise `[N, H, A]`: N(0, I), or `L z` over each flattened chunk with `factor` L
    `[H * A, H * A]` (`correlated_noise_factor`)."""
    z = jax.random.normal(rng, shape)
    if factor is None:
        return z
    n, horizon, width = shape
    return (z.reshape(n, horizon * width) @ jnp.asarray(factor, z.dtype).T).reshape(shape)
