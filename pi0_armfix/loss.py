"""Loss weighting strategies for flow matching on a grouped action space (docs/design.md §3).

Everything here is a pure, jit-able function of arrays. `strategy`, `layout` and `delta_weighting`
are static (Python values); weights may be Python numbers or traced arrays (adaptive weights and
the warmup schedule are computed inside the train step). Weights never carry gradient.

Notation: `e[b, h, d] = (v - u)^2` is the per-dimension flow-matching error `[B, H, D]` with
`D = layout.action_dim`; `a[b, h, d]` the clean normalized action chunk; G the number of groups.

Strategies:
  uniform        mean_d e  (upstream openpi pi0; padding dims included).
  original       the navigation-biased temporal weighting of an earlier version of this fix:
                 w_h = clip(0.2 + min(||a_h - a_{h-1}||, 0.5), 0.1, 3.0), normalized to mean 1 over
                 the whole batch, times mean_d e. Kept for comparison only (its weights depend on the
                 batch composition).
  per_group      static weight per group, 0 on padding and ungrouped dims, optionally scaled per
                 (sample, step, group) by delta weighting; all weights divided by one constant K so
                 that the static weights have mean 1 over all D dims.
  per_dimension  a fixed [D] weight vector, normalized the same way.
  loss_balanced  per_group with the caller's effective group weights (static x clamped inverse EMA
                 of the group losses, see `loss_balanced_weights`).
  uncertainty    sum_g w_g exp(-s_g) L_g + s_g with learned log-variances s_g clamped from below
                 (Kendall et al. 2018); L_g the group's mean error (optionally delta-weighted).

Documented constant: with all group weights equal, no delta weighting and groups that cover the
real dims, `per_group` equals the mean of e over the real dims exactly (K = real_dim / D).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_armfix.action_space import ActionLayout

@dataclasses.dataclass(frozen=True)
class LossStrategy:
    """What a loss strategy weighs by and what it needs: the one place that knows it.

    weighting:         how `compute_weighted_loss` reduces e over the dims: "mean" (uniform),
                       "temporal" (original's per-step weights), "static" (normalized static dim
                       weights), "precision" (learned per-group precisions).
    config_weights:    the static weights it reads from the config (checked, ramped by the warmup
                       schedule): "group" (`loss.group_weights`), "dimension"
                       (`loss.dimension_weights`) or None.
    delta_weighting:   whether `loss.delta_weighting` applies.
    learns_log_vars:   the train state carries learned per-group log-variances (`loss_params`).
    balances:          the train state carries an EMA of the group losses that rescales the weights.
    """
    name: str
    weighting: str
    config_weights: str | None = None
    delta_weighting: bool = False
    learns_log_vars: bool = False
    balances: bool = False


LOSS_STRATEGIES = {s.name: s for s in (
    LossStrategy("uniform", "mean"),
    LossStrategy("original", "temporal"),
    LossStrategy("per_group", "static", "group", delta_weighting=True),
    LossStrategy("per_dimension", "static", "dimension", delta_weighting=True),
    LossStrategy("loss_balanced", "static", "group", delta_weighting=True, balances=True),
    LossStrategy("uncertainty", "precision", "group", delta_weighting=True, learns_log_vars=True),
)}
STRATEGIES = tuple(LOSS_STRATEGIES)


def loss_strategy(name: str, delta_weighting: bool = False) -> LossStrategy:
    """The strategy called `name`; ValueError for an unknown name or a delta weighting it ignores."""
    if name not in LOSS_STRATEGIES:
        raise ValueError(f"unknown loss strategy {name!r}; choose one of {list(STRATEGIES)}")
    strategy = LOSS_STRATEGIES[name]
    if delta_weighting and not strategy.delta_weighting:
        raise ValueError(f"delta_weighting=True has no meaning for loss strategy {name!r}; it "
                         f"applies to {[s.name for s in LOSS_STRATEGIES.values() if s.delta_weighting]}")
    return strategy


def _as_float32(x: Any) -> jax.Array:
    x = jnp.asarray(x)
    return x.astype(jnp.promote_types(x.dtype, jnp.float32))


def group_weight_vector(layout: ActionLayout, group_weights: Mapping[str, Any]) -> jax.Array:
    """Per-dimension static weights `[D]` from `{group: weight}`; 0 on padding and ungrouped dims."""
    layout.check_group_weights(group_weights)
    per_group = jnp.stack([_as_float32(group_weights[g]) for g in layout.group_names])
    return jnp.asarray(layout.membership()) @ per_group


def static_dim_weights(strategy: str, layout: ActionLayout, group_weights=None,
                       dimension_weights=None) -> jax.Array:
    """Normalized static weights `[D]` (mean 1 over all D dims) of a per_group-like strategy.

    This is what a metric should report as the "effective weight" of a dim before delta weighting.
    """
    spec = loss_strategy(strategy)
    if spec.weighting != "static":
        raise ValueError(f"loss strategy {strategy!r} has no static dimension weights")
    if spec.config_weights == "group":
        if group_weights is None:
            raise ValueError(f"loss strategy {strategy!r} needs group_weights "
                             f"(one weight per group: {list(layout.group_names)})")
        w = group_weight_vector(layout, group_weights)
    else:
        if dimension_weights is None:
            raise ValueError(f"loss strategy {strategy!r} needs dimension_weights "
                             f"({layout.action_dim} values)")
        layout.check_dimension_weights(dimension_weights)
        w = _as_float32(dimension_weights)
    return w / jnp.mean(w)


def _valid_weights(valid: jax.Array | None, like: jax.Array) -> jax.Array:
    """`valid` `[B, H]` as 1/0 weights shaped `[B, H, 1...]` against `like` (all 1 if None)."""
    if valid is None:
        return jnp.ones(like.shape[:2] + (1,) * (like.ndim - 2), like.dtype)
    return jnp.asarray(valid, like.dtype).reshape(valid.shape + (1,) * (like.ndim - 2))


def _valid_mean(x: jax.Array, valid: jax.Array | None, axis) -> jax.Array:
    """Mean of `x` `[B, H, ...]` over the valid entries along `axis` (kept); 1 where none is valid,
    so a weight divided by it stays finite (and is masked out of the loss anyway)."""
    v = _valid_weights(valid, x)
    count = jnp.sum(v, axis=axis, keepdims=True)
    return jnp.where(count > 0, jnp.sum(x * v, axis=axis, keepdims=True) / jnp.maximum(count, 1.0),
                     1.0)


def delta_scale(actions: jax.Array, layout: ActionLayout, valid: jax.Array | None = None
                ) -> jax.Array:
    """Per-sample, per-group motion scale `[B, H, G]` of delta weighting.

    c = clip(0.2 + min(||Δa_g||, 0.5), 0.1, 3.0) with Δ over h inside the group's dims (Δ = 0 at
    h = 0), normalized to mean 1 over the valid h (`valid` `[B, H]`, False on `action_is_pad`
    steps; None = all) for each (sample, group), so a sample's weights depend neither on the rest
    of the batch (batch size, composition, sharding) nor on how much of it is episode-end padding.
    """
    a = jax.lax.stop_gradient(_as_float32(actions))
    delta = a - jnp.concatenate([a[:, :1], a[:, :-1]], axis=1)
    group_sq = jnp.einsum("bhd,dg->bhg", jnp.square(delta), jnp.asarray(layout.membership()))
    c = jnp.clip(0.2 + jnp.minimum(jnp.sqrt(group_sq), 0.5), 0.1, 3.0)
    return c / _valid_mean(c, valid, axis=1)


def _delta_dim_scale(actions: jax.Array, layout: ActionLayout, valid: jax.Array | None
                     ) -> jax.Array:
    """Delta scale spread to dims `[B, H, D]`; dims outside every group keep scale 1."""
    membership = jnp.asarray(layout.membership())
    ungrouped = 1.0 - jnp.sum(membership, axis=-1)
    return (jnp.einsum("bhg,dg->bhd", delta_scale(actions, layout, valid), membership)
            + ungrouped)


def original_temporal_weights(actions: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """Weights `[B, H]` of the `original` strategy, normalized to mean 1 over the batch's valid
    (b, h) entries."""
    a = jax.lax.stop_gradient(_as_float32(actions))
    delta = a - jnp.concatenate([a[:, :1], a[:, :-1]], axis=1)
    w = jnp.clip(0.2 + jnp.minimum(jnp.linalg.norm(delta, axis=-1), 0.5), 0.1, 3.0)
    return w / _valid_mean(w, valid, axis=(0, 1))


def switch_emphasis(actions: jax.Array, valid: jax.Array | None, layout: ActionLayout, *,
                    threshold: Any, weight: float, window: int) -> jax.Array:
    """Timestep weights `[B, H]` that emphasize gripper switches: `weight` on the steps within
    `window` steps of a switch of the true chunk, 1 elsewhere (not renormalized: chunks with a
    switch weigh more than chunks without, which is the point).

    A switch at h: a dim of a group with role gripper crosses `threshold` (`[D]` or `[H, D]`, the
    open/close boundary in normalized units) between steps h - 1 and h, both valid.
    """
    dims = np.concatenate([layout.group_dims(g) for g in layout.groups_with_role("gripper")]
                          + [np.zeros(0, int)])
    a = jax.lax.stop_gradient(_as_float32(actions))
    above = (a > jnp.asarray(threshold, a.dtype))[..., dims]
    both_valid = jnp.ones(a.shape[:1] + (a.shape[1] - 1,), bool) if valid is None else \
        valid[:, 1:] & valid[:, :-1]
    switch = jnp.any(above[:, 1:] != above[:, :-1], axis=-1) & both_valid
    switch = jnp.concatenate([jnp.zeros_like(switch[:, :1]), switch], axis=1)  # [B, H]
    padded = jnp.pad(switch, ((0, 0), (window, window)))
    near = jnp.stack([padded[:, k:k + switch.shape[1]] for k in range(2 * window + 1)]).any(0)
    return jnp.where(near, jnp.float32(weight), jnp.float32(1.0))


def _group_means(x: jax.Array, layout: ActionLayout, live: Any = None) -> jax.Array:
    """Mean of `x` `[..., D]` over each group's live dims -> `[..., G]`. `live`: `[D]` or
    `[H, D]` (`x` then `[..., H, D]`), 0 on the dims that carry no loss (the constant dims,
    `data.batching.loss_mask`), so that a group's mean is over the dims it trains; None = all."""
    membership = jnp.asarray(layout.membership(), jnp.float32)  # [D, G]
    if live is None:
        live = jnp.ones(membership.shape[0], jnp.float32)
    weights = jnp.asarray(live, jnp.float32)[..., None] * membership  # [(H,) D, G]
    weights = weights / jnp.maximum(weights.sum(axis=-2, keepdims=True), 1.0)
    return jnp.einsum("...d,...dg->...g", x, weights)


def compute_weighted_loss(per_dim_loss: jax.Array, actions: jax.Array, *, strategy: str,
                          layout: ActionLayout, group_weights: Mapping[str, Any] | None = None,
                          dimension_weights: Any = None, delta_weighting: bool = False,
                          log_vars: jax.Array | None = None, min_log_var: float = -5.0,
                          valid: jax.Array | None = None,
                          timestep_weights: jax.Array | None = None,
                          live: Any = None) -> jax.Array:
    """Weighted loss per (sample, step).

    Args:
      per_dim_loss: e `[B, H, D]`.
      actions: clean normalized target chunk `[B, H, D]` (for the motion-based weights).
      strategy: one of `STRATEGIES`.
      layout: the action layout; `D` must equal `layout.action_dim`.
      group_weights: `{group: weight}` for per_group / loss_balanced (optional for uncertainty).
      dimension_weights: `[D]` for per_dimension.
      delta_weighting: scale each (b, h, g) by the group's per-sample normalized motion.
      log_vars: `[G]` learned log-variances for uncertainty (these DO carry gradient).
      min_log_var: lower clamp of the log-variances.
      valid: `[B, H]` bool, False on `action_is_pad` steps: the normalizations over time (delta
        weighting, `original`) ignore them. None = all valid.
      timestep_weights: `[B, H]` extra weights on every dim of a step (`switch_emphasis`).
      live: `[D]` or `[H, D]`, 0 on the dims that carry no loss: the group means of
        `uncertainty` are over the others (`_group_means`). None = all.
    Returns:
      `[B, H]` float32.
    """
    weighting = loss_strategy(strategy, delta_weighting).weighting
    e = _as_float32(per_dim_loss)
    if e.ndim != 3 or e.shape[-1] != layout.action_dim:
        raise ValueError(f"per_dim_loss has shape {e.shape}; expected [B, H, {layout.action_dim}] "
                         "(the layout's action_dim)")
    if tuple(np.shape(actions)) != e.shape:
        raise ValueError(f"actions shape {tuple(np.shape(actions))} != per_dim_loss shape {e.shape}")
    if timestep_weights is not None:
        e = jax.lax.stop_gradient(_as_float32(timestep_weights))[..., None] * e

    if weighting == "mean":
        return jnp.mean(e, axis=-1)
    if weighting == "temporal":
        return original_temporal_weights(actions, valid) * jnp.mean(e, axis=-1)
    if delta_weighting:
        e_scaled = jax.lax.stop_gradient(_delta_dim_scale(actions, layout, valid)) * e
    else:
        e_scaled = e
    if weighting == "precision":
        if log_vars is None or np.shape(log_vars) != (layout.num_groups,):
            raise ValueError(f"loss strategy {strategy!r} needs log_vars of shape "
                             f"({layout.num_groups},), got {None if log_vars is None else np.shape(log_vars)}")
        if group_weights is None:
            weights = jnp.ones((layout.num_groups,), jnp.float32)
        else:
            layout.check_group_weights(group_weights)
            weights = jnp.stack([_as_float32(group_weights[g]) for g in layout.group_names])
        s = jnp.maximum(_as_float32(log_vars), min_log_var)
        precision = jax.lax.stop_gradient(weights) * jnp.exp(-s)
        return jnp.sum(precision * _group_means(e_scaled, layout, live), axis=-1) + jnp.sum(s)
    w = jax.lax.stop_gradient(static_dim_weights(strategy, layout, group_weights, dimension_weights))
    return jnp.mean(w * e_scaled, axis=-1)


def masked_mean(x: jax.Array, valid: jax.Array | None) -> jax.Array:
    """Mean of `x` `[B, H, ...]` over the entries where `valid` `[B, H]` is True (0 if none)."""
    x = _as_float32(x)
    v = _valid_weights(valid, x)
    return jnp.sum(x * v, axis=(0, 1)) / jnp.maximum(jnp.sum(v, axis=(0, 1)), 1.0)


def per_group_losses(per_dim_loss: jax.Array, layout: ActionLayout,
                     valid: jax.Array | None = None, live: Any = None) -> dict[str, jax.Array]:
    """Unweighted mean squared error of each group over the valid (b, h) entries and its live
    dims, for metrics and the `loss_balanced` EMA.

    Args:
      per_dim_loss: e `[B, H, D]`.
      valid: `[B, H]` bool, True where the timestep is real (not `action_is_pad`); None = all.
      live: `[D]` or `[H, D]`, 0 on the dims that carry no loss; None = all.
    Returns:
      `{group: scalar}`.
    """
    means = masked_mean(_group_means(_as_float32(per_dim_loss), layout, live), valid)
    return {g: means[i] for i, g in enumerate(layout.group_names)}


def training_loss(per_dim_loss: jax.Array, actions: jax.Array, action_is_pad: jax.Array, *,
                  layout: ActionLayout, strategy: str, group_weights=None, dimension_weights=None,
                  delta_weighting: bool = False, log_vars=None, min_log_var: float = -5.0,
                  switch_threshold=None, switch_weight: float = 1.0, switch_window: int = 0,
                  live: Any = None):
    """The scalar training loss over valid timesteps, and the per-group unweighted losses.

    Args:
      per_dim_loss: e `[B, H, D]`; actions `[B, H, D]`; action_is_pad `[B, H]` bool.
      switch_threshold, switch_weight, switch_window: gripper-switch emphasis
        (`switch_emphasis`), on when `switch_weight != 1`.
      live: `[D]` or `[H, D]`, 0 on the dims that carry no loss (whose e is 0): group means are
        over the others. None = all.
    Returns:
      `(loss scalar, {"group_loss": {group: scalar}})`.
    """
    valid = jnp.logical_not(action_is_pad)
    timestep_weights = None
    if switch_weight != 1.0:
        timestep_weights = switch_emphasis(actions, valid, layout, threshold=switch_threshold,
                                           weight=switch_weight, window=switch_window)
    weighted = compute_weighted_loss(
        per_dim_loss, actions, strategy=strategy, layout=layout, group_weights=group_weights,
        dimension_weights=dimension_weights, delta_weighting=delta_weighting, log_vars=log_vars,
        min_log_var=min_log_var, valid=valid, timestep_weights=timestep_weights, live=live)
    return masked_mean(weighted, valid), {
        "group_loss": per_group_losses(jax.lax.stop_gradient(per_dim_loss), layout, valid, live)}


# ---------------------------------------------------------------------- schedules and adaptive state


def warmup_fraction(step: Any, warmup_steps: int) -> jax.Array:
    """Linear ramp 0 -> 1 over `warmup_steps` (1 from the start when warmup_steps == 0)."""
    if warmup_steps <= 0:
        return jnp.float32(1.0)
    return jnp.clip(_as_float32(step) / warmup_steps, 0.0, 1.0)


def warmup_group_weights(target: Mapping[str, Any], step: Any, warmup_steps: int) -> dict:
    """Group weights ramped linearly from 1.0 to `target` over `warmup_steps`."""
    frac = warmup_fraction(step, warmup_steps)
    return {g: 1.0 + (_as_float32(w) - 1.0) * frac for g, w in target.items()}


def warmup_dimension_weights(target: Any, step: Any, warmup_steps: int,
                             layout: ActionLayout) -> jax.Array:
    """Dimension weights `[D]` ramped from 1.0 on real dims (0 on padding, which is never trained)
    to `target` over `warmup_steps`."""
    start = jnp.asarray(layout.real_mask(), jnp.float32)
    return start + (_as_float32(target) - start) * warmup_fraction(step, warmup_steps)


def update_group_loss_ema(ema: jax.Array, count: jax.Array, group_losses: jax.Array,
                          decay: float) -> tuple[jax.Array, jax.Array]:
    """One EMA update of the group losses `[G]`; the first update takes the losses as they are
    (no bias towards the zero initial state). Returns `(ema [G], count)`."""
    group_losses = jax.lax.stop_gradient(_as_float32(group_losses))
    updated = jnp.where(count > 0, decay * ema + (1.0 - decay) * group_losses, group_losses)
    return updated, count + 1


def loss_balanced_weights(ema: jax.Array, static: jax.Array, w_min: float,
                          w_max: float, eps: float = 1e-8) -> jax.Array:
    """Effective group weights `[G]` of `loss_balanced`: static x clamp(inverse EMA loss).

    The inverse losses are normalized to mean 1 over groups before the clamp to [w_min, w_max], so
    the clamp bounds the *relative* boost a group can get, whatever the loss scale.
    """
    inverse = 1.0 / jnp.maximum(jax.lax.stop_gradient(_as_float32(ema)), eps)
    return _as_float32(static) * jnp.clip(inverse / jnp.mean(inverse), w_min, w_max)
