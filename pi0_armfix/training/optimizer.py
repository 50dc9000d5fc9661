"""AdamW with global-norm clipping on a warmup-cosine schedule, from `config.optim`.

The optimizer acts on the trainable tree `{"params": model params, "loss_params": loss params}`
(the learned log-variances of the `uncertainty` strategy live in `loss_params`). Weight decay
applies to the model params only: decaying a log-variance would pull the loss weights to 1.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import jax
import optax


def effective_warmup(optim: Mapping[str, Any], total_steps: int) -> tuple[int, str | None]:
    """`optim.warmup_steps`, or a tenth of a run too short for it (a smoke run such as
    `train.total_steps=20` under a 1000-step warmup), with the line that says so (None if kept)."""
    warmup = int(optim["warmup_steps"])
    if warmup < 0:
        raise ValueError(f"optim.warmup_steps = {warmup} must be >= 0")
    if warmup < total_steps:
        return warmup, None
    clamped = total_steps // 10
    return clamped, (f"optim.warmup_steps = {warmup} is not shorter than train.total_steps = "
                     f"{total_steps}: warming up over {clamped} steps instead")


def check_optim_config(optim: Mapping[str, Any]) -> None:
    """Every `optim` value in its range, each failure naming the key and the range."""
    ranges = (("lr", optim["lr"] > 0 and math.isfinite(optim["lr"]), "a positive number"),
              ("end_lr_factor", 0.0 <= optim["end_lr_factor"] <= 1.0, "in [0, 1]"),
              ("b1", 0.0 <= optim["b1"] < 1.0, "in [0, 1)"),
              ("b2", 0.0 <= optim["b2"] < 1.0, "in [0, 1)"),
              ("eps", optim["eps"] > 0, "positive"),
              ("weight_decay", optim["weight_decay"] >= 0, ">= 0"),
              ("clip_norm", optim["clip_norm"] > 0, "positive"),
              ("ema_decay", 0.0 <= optim["ema_decay"] < 1.0, "in [0, 1) (0 = no EMA)"))
    bad = [f"optim.{key} = {optim[key]} must be {rule}" for key, ok, rule in ranges if not ok]
    if bad:
        raise ValueError("; ".join(bad))


def learning_rate_schedule(optim: Mapping[str, Any], total_steps: int) -> optax.Schedule:
    """Linear warmup 0 -> `optim.lr` over `effective_warmup` steps, then cosine decay to
    `optim.lr * optim.end_lr_factor` at `total_steps`."""
    check_optim_config(optim)
    warmup, _ = effective_warmup(optim, total_steps)
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=optim["lr"], warmup_steps=warmup, decay_steps=total_steps,
        end_value=optim["lr"] * optim["end_lr_factor"])


def _decay_mask(trainable: Mapping[str, Any]) -> dict[str, Any]:
    return {name: jax.tree.map(lambda _: name == "params", subtree)
            for name, subtree in trainable.items()}


def make_optimizer(optim: Mapping[str, Any], total_steps: int
                   ) -> tuple[optax.GradientTransformation, optax.Schedule]:
    """The gradient transformation and its learning-rate schedule (for logging)."""
    schedule = learning_rate_schedule(optim, total_steps)
    tx = optax.chain(
        optax.clip_by_global_norm(optim["clip_norm"]),
        optax.adamw(schedule, b1=optim["b1"], b2=optim["b2"], eps=optim["eps"],
                    weight_decay=optim["weight_decay"], mask=_decay_mask),
    )
    return tx, schedule
