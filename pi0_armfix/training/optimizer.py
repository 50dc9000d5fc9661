"""AdamW with global-norm clipping on a warmup-cosine schedule, from `config.optim`.

The optimizer acts on the trainable tree `{"params": model params, "loss_params": loss params}`
(the learned log-variances of the `uncertainty` strategy live in `loss_params`). Weight decay
applies to the model params only: decaying a log-variance would pull the loss weights to 1.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import optax


def learning_rate_schedule(optim: Mapping[str, Any], total_steps: int) -> optax.Schedule:
    """Linear warmup 0 -> `optim.lr` over `optim.warmup_steps`, then cosine decay to
    `optim.lr * optim.end_lr_factor` at `total_steps`."""
    warmup = int(optim["warmup_steps"])
    if warmup < 0 or warmup >= total_steps:
        raise ValueError(f"optim.warmup_steps = {warmup} must be in [0, train.total_steps = "
                         f"{total_steps})")
    if optim["lr"] <= 0:
        raise ValueError(f"optim.lr = {optim['lr']} must be positive")
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=optim["lr"], warmup_steps=warmup, decay_steps=total_steps,
        end_value=optim["lr"] * optim["end_lr_factor"])


def _decay_mask(trainable: Mapping[str, Any]) -> dict[str, Any]:
    return {name: jax.tree.map(lambda _: name == "params", subtree)
            for name, subtree in trainable.items()}


def make_optimizer(optim: Mapping[str, Any], total_steps: int
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """The gradient transformation and its learning-rate schedule (for logging)."""
    if optim["clip_norm"] <= 0:
        raise ValueError(f"optim.clip_norm = {optim['clip_norm']} must be positive")
    if not 0.0 <= optim["ema_decay"] < 1.0:
        raise ValueError(f"optim.ema_decay = {optim['ema_decay']} must be in [0, 1) (0 = no EMA)")
    schedule = learning_rate_schedule(optim, total_steps)
    tx = optax.chain(
        optax.clip_by_global_norm(optim["clip_norm"]),
        optax.adamw(schedule, b1=optim["b1"], b2=optim["b2"], eps=optim["eps"],
                    weight_decay=optim["weight_decay"], mask=_decay_mask),
    )
    return tx, schedule
