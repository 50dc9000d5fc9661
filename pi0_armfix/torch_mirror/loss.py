"""PyTorch mirror of `pi0_armfix.loss`: the same functions, names and arguments on torch tensors.

The semantics are documented once, in `pi0_armfix/loss.py`; this file follows it line for line so
that a checkpoint trained in JAX reproduces its loss in PyTorch (tests check values and gradients
to 1e-6 relative in float32). Validation is shared: it lives on `ActionLayout`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.loss import STRATEGIES, loss_strategy  # noqa: F401


def _as_float32(x: Any, like: torch.Tensor | None = None) -> torch.Tensor:
    device = like.device if like is not None else None
    t = torch.as_tensor(x, device=device)
    if not torch.is_floating_point(t) or t.dtype in (torch.float16, torch.bfloat16):
        t = t.to(torch.float32)
    return t


def _membership(layout: ActionLayout, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(layout.membership(), dtype=like.dtype, device=like.device)


def group_weight_vector(layout: ActionLayout, group_weights: Mapping[str, Any],
                        like: torch.Tensor | None = None) -> torch.Tensor:
    """Per-dimension static weights `[D]` from `{group: weight}`; 0 on padding and ungrouped dims."""
    layout.check_group_weights(group_weights)
    per_group = torch.stack([_as_float32(group_weights[g], like).reshape(()) for g in layout.group_names])
    return _membership(layout, per_group) @ per_group


def static_dim_weights(strategy: str, layout: ActionLayout, group_weights=None,
                       dimension_weights=None, like: torch.Tensor | None = None) -> torch.Tensor:
    """Normalized static weights `[D]` (mean 1 over all D dims) of a per_group-like strategy."""
    spec = loss_strategy(strategy)
    if spec.weighting != "static":
        raise ValueError(f"loss strategy {strategy!r} has no static dimension weights")
    if spec.config_weights == "group":
        if group_weights is None:
            raise ValueError(f"loss strategy {strategy!r} needs group_weights "
                             f"(one weight per group: {list(layout.group_names)})")
        w = group_weight_vector(layout, group_weights, like)
    else:
        if dimension_weights is None:
            raise ValueError(f"loss strategy {strategy!r} needs dimension_weights "
                             f"({layout.action_dim} values)")
        layout.check_dimension_weights(
            dimension_weights.detach().cpu().numpy() if torch.is_tensor(dimension_weights)
            else dimension_weights)
        w = _as_float32(dimension_weights, like)
    return w / torch.mean(w)


def _shifted_delta(actions: torch.Tensor) -> torch.Tensor:
    a = _as_float32(actions).detach()
    return a - torch.cat([a[:, :1], a[:, :-1]], dim=1)


def _valid_weights(valid: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """`valid` `[B, H]` as 1/0 weights shaped `[B, H, 1...]` against `like` (all 1 if None)."""
    shape = tuple(like.shape[:2]) + (1,) * (like.ndim - 2)
    if valid is None:
        return torch.ones(shape, dtype=like.dtype, device=like.device)
    return valid.to(like.dtype).reshape(shape)


def _valid_mean(x: torch.Tensor, valid: torch.Tensor | None, dim) -> torch.Tensor:
    """Mean over the valid entries along `dim` (kept); 1 where none is valid."""
    v = _valid_weights(valid, x)
    count = torch.sum(v, dim=dim, keepdim=True)
    mean = torch.sum(x * v, dim=dim, keepdim=True) / torch.clamp(count, min=1.0)
    return torch.where(count > 0, mean, torch.ones_like(mean))


def delta_scale(actions: torch.Tensor, layout: ActionLayout,
                valid: torch.Tensor | None = None) -> torch.Tensor:
    """Per-sample, per-group motion scale `[B, H, G]` of delta weighting (see the JAX docstring)."""
    delta = _shifted_delta(actions)
    group_sq = torch.einsum("bhd,dg->bhg", delta.square(), _membership(layout, delta))
    c = torch.clamp(0.2 + torch.clamp(torch.sqrt(group_sq), max=0.5), 0.1, 3.0)
    return c / _valid_mean(c, valid, dim=1)


def _delta_dim_scale(actions: torch.Tensor, layout: ActionLayout,
                     valid: torch.Tensor | None) -> torch.Tensor:
    scale = delta_scale(actions, layout, valid)
    membership = _membership(layout, scale)
    ungrouped = 1.0 - membership.sum(-1)
    return torch.einsum("bhg,dg->bhd", scale, membership) + ungrouped


def original_temporal_weights(actions: torch.Tensor,
                              valid: torch.Tensor | None = None) -> torch.Tensor:
    """Weights `[B, H]` of the `original` strategy, mean 1 over the batch's valid entries."""
    delta = _shifted_delta(actions)
    w = torch.clamp(0.2 + torch.clamp(torch.linalg.vector_norm(delta, dim=-1), max=0.5), 0.1, 3.0)
    return w / _valid_mean(w, valid, dim=(0, 1))


def switch_emphasis(actions: torch.Tensor, valid: torch.Tensor | None, layout: ActionLayout, *,
                    threshold: Any, weight: float, window: int) -> torch.Tensor:
    """Timestep weights `[B, H]`: `weight` within `window` steps of a gripper switch, else 1."""
    dims = np.concatenate([layout.group_dims(g) for g in layout.groups_with_role("gripper")]
                          + [np.zeros(0, int)])
    a = _as_float32(actions).detach()
    above = (a > torch.as_tensor(np.asarray(threshold), dtype=a.dtype, device=a.device))
    above = above[..., torch.as_tensor(dims, dtype=torch.long)]
    both_valid = (torch.ones(a.shape[0], a.shape[1] - 1, dtype=torch.bool, device=a.device)
                  if valid is None else valid[:, 1:] & valid[:, :-1])
    switch = torch.any(above[:, 1:] != above[:, :-1], dim=-1) & both_valid
    switch = torch.cat([torch.zeros_like(switch[:, :1]), switch], dim=1)
    padded = torch.nn.functional.pad(switch, (window, window))
    near = torch.stack([padded[:, k:k + switch.shape[1]] for k in range(2 * window + 1)]).any(0)
    return torch.where(near, torch.tensor(float(weight)), torch.tensor(1.0))


def _group_means(x: torch.Tensor, layout: ActionLayout, live: Any = None) -> torch.Tensor:
    membership = torch.as_tensor(layout.membership(), dtype=x.dtype, device=x.device)
    live = (torch.ones(membership.shape[0], dtype=x.dtype, device=x.device) if live is None
            else torch.as_tensor(np.asarray(live), dtype=x.dtype, device=x.device))
    weights = live[..., None] * membership
    weights = weights / torch.clamp(weights.sum(dim=-2, keepdim=True), min=1.0)
    return torch.einsum("...d,...dg->...g", x, weights)


def compute_weighted_loss(per_dim_loss: torch.Tensor, actions: torch.Tensor, *, strategy: str,
                          layout: ActionLayout, group_weights: Mapping[str, Any] | None = None,
                          dimension_weights: Any = None, delta_weighting: bool = False,
                          log_vars: torch.Tensor | None = None,
                          min_log_var: float = -5.0, valid: torch.Tensor | None = None,
                          timestep_weights: torch.Tensor | None = None,
                          live: Any = None) -> torch.Tensor:
    """Weighted loss per (sample, step) `[B, H]`; mirrors `pi0_armfix.loss.compute_weighted_loss`."""
    weighting = loss_strategy(strategy, delta_weighting).weighting
    e = _as_float32(per_dim_loss)
    if e.ndim != 3 or e.shape[-1] != layout.action_dim:
        raise ValueError(f"per_dim_loss has shape {tuple(e.shape)}; expected [B, H, "
                         f"{layout.action_dim}] (the layout's action_dim)")
    if tuple(actions.shape) != tuple(e.shape):
        raise ValueError(f"actions shape {tuple(actions.shape)} != per_dim_loss shape {tuple(e.shape)}")
    if timestep_weights is not None:
        e = _as_float32(timestep_weights).detach().to(e.dtype)[..., None] * e

    if weighting == "mean":
        return torch.mean(e, dim=-1)
    if weighting == "temporal":
        return original_temporal_weights(actions, valid).to(e.dtype) * torch.mean(e, dim=-1)
    e_scaled = (_delta_dim_scale(actions, layout, valid).to(e.dtype) * e if delta_weighting
                else e)
    if weighting == "precision":
        if log_vars is None or tuple(log_vars.shape) != (layout.num_groups,):
            raise ValueError(f"loss strategy {strategy!r} needs log_vars of shape "
                             f"({layout.num_groups},), got {None if log_vars is None else tuple(log_vars.shape)}")
        if group_weights is None:
            weights = torch.ones(layout.num_groups, dtype=e.dtype, device=e.device)
        else:
            layout.check_group_weights(group_weights)
            weights = torch.stack([_as_float32(group_weights[g], e).reshape(())
                                   for g in layout.group_names]).to(e.dtype)
        s = torch.clamp(_as_float32(log_vars), min=min_log_var)
        precision = weights.detach() * torch.exp(-s)
        return torch.sum(precision * _group_means(e_scaled, layout, live), dim=-1) + torch.sum(s)
    w = static_dim_weights(strategy, layout, group_weights, dimension_weights, like=e).detach()
    return torch.mean(w.to(e.dtype) * e_scaled, dim=-1)


def masked_mean(x: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    """Mean of `x` `[B, H, ...]` over the entries where `valid` `[B, H]` is True (0 if none)."""
    x = _as_float32(x)
    v = _valid_weights(valid, x)
    return torch.sum(x * v, dim=(0, 1)) / torch.clamp(torch.sum(v, dim=(0, 1)), min=1.0)


def per_group_losses(per_dim_loss: torch.Tensor, layout: ActionLayout,
                     valid: torch.Tensor | None = None, live: Any = None
                     ) -> dict[str, torch.Tensor]:
    """Unweighted mean squared error of each group over the valid (b, h) entries and its live
    dims; mirrors `pi0_armfix.loss.per_group_losses`."""
    means = masked_mean(_group_means(_as_float32(per_dim_loss), layout, live), valid)
    return {g: means[i] for i, g in enumerate(layout.group_names)}


def training_loss(per_dim_loss: torch.Tensor, actions: torch.Tensor, action_is_pad: torch.Tensor, *,
                  layout: ActionLayout, strategy: str, group_weights=None, dimension_weights=None,
                  delta_weighting: bool = False, log_vars=None, min_log_var: float = -5.0,
                  switch_threshold=None, switch_weight: float = 1.0, switch_window: int = 0,
                  live: Any = None):
    """`(loss scalar, {"group_loss": {group: scalar}})`; mirrors `pi0_armfix.loss.training_loss`."""
    valid = torch.logical_not(action_is_pad)
    timestep_weights = None
    if switch_weight != 1.0:
        timestep_weights = switch_emphasis(actions, valid, layout, threshold=switch_threshold,
                                           weight=switch_weight, window=switch_window)
    weighted = compute_weighted_loss(
        per_dim_loss, actions, strategy=strategy, layout=layout, group_weights=group_weights,
        dimension_weights=dimension_weights, delta_weighting=delta_weighting, log_vars=log_vars,
        min_log_var=min_log_var, valid=valid, timestep_weights=timestep_weights, live=live)
    return masked_mean(weighted, valid), {
        "group_loss": per_group_losses(per_dim_loss.detach(), layout, valid, live)}


def warmup_fraction(step: Any, warmup_steps: int) -> torch.Tensor:
    """Linear ramp 0 -> 1 over `warmup_steps` (1 from the start when warmup_steps == 0)."""
    if warmup_steps <= 0:
        return torch.tensor(1.0)
    return torch.clamp(_as_float32(step) / warmup_steps, 0.0, 1.0)


def warmup_group_weights(target: Mapping[str, Any], step: Any, warmup_steps: int) -> dict:
    """Group weights ramped linearly from 1.0 to `target` over `warmup_steps`."""
    frac = warmup_fraction(step, warmup_steps)
    return {g: 1.0 + (_as_float32(w) - 1.0) * frac for g, w in target.items()}


def warmup_dimension_weights(target: Any, step: Any, warmup_steps: int,
                             layout: ActionLayout) -> torch.Tensor:
    """Dimension weights `[D]` ramped from 1.0 on real dims (0 on padding) to `target`."""
    start = torch.as_tensor(np.asarray(layout.real_mask(), np.float32))
    return start + (_as_float32(target) - start) * warmup_fraction(step, warmup_steps)


def update_group_loss_ema(ema: torch.Tensor, count: torch.Tensor, group_losses: torch.Tensor,
                          decay: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One EMA update of the group losses `[G]`; the first update takes the losses as they are."""
    group_losses = _as_float32(group_losses).detach()
    updated = torch.where(torch.as_tensor(count) > 0, decay * ema + (1.0 - decay) * group_losses,
                          group_losses)
    return updated, count + 1


def loss_balanced_weights(ema: torch.Tensor, static: torch.Tensor, w_min: float, w_max: float,
                          eps: float = 1e-8) -> torch.Tensor:
    """Effective group weights `[G]` of `loss_balanced`: static x clamp(inverse EMA loss)."""
    inverse = 1.0 / torch.clamp(_as_float32(ema).detach(), min=eps)
    return _as_float32(static) * torch.clamp(inverse / torch.mean(inverse), w_min, w_max)
