"""The train step: effective loss weights for this step, gradient, AdamW update, EMAs, metrics.

The effective loss weights are a function of the step number and the train state, computed inside
the step and passed to the model's `compute_loss` as loss kwargs:

  per_group, uncertainty   group weights ramped 1.0 -> target over `loss.weight_warmup_steps`.
  loss_balanced            the ramped weights x the clamped inverse EMA of the group losses (the
                           EMA before this step's update, so a step never weighs by its own loss).
  per_dimension            dimension weights ramped 1.0 -> target (0 on padding throughout).
  uniform, original        no weights to ramp.

The step's randomness (noise, flow time, augmentation) is `fold_in(key(seed), step)`: a function
of the step alone, so a resumed run draws exactly what an uninterrupted run draws.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import optax

from pi0_armfix import loss as loss_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import flow_model
from pi0_armfix.model.config import Pi0Config
from pi0_armfix.training import freeze
from pi0_armfix.training.state import TrainState


def check_loss_config(loss_cfg: Mapping[str, Any], layout: ActionLayout) -> None:
    """Raises ValueError (naming the `loss.*` key) for a loss section the step cannot run."""
    strategy = loss_lib.loss_strategy(loss_cfg["strategy"], loss_cfg["delta_weighting"])
    if strategy.config_weights == "dimension":
        layout.check_dimension_weights(loss_cfg["dimension_weights"],
                                       field="loss.dimension_weights")
    elif strategy.config_weights == "group":
        layout.check_group_weights(dict(loss_cfg["group_weights"]), field="loss.group_weights")
    if loss_cfg["weight_warmup_steps"] < 0:
        raise ValueError(f"loss.weight_warmup_steps = {loss_cfg['weight_warmup_steps']} must "
                         "be >= 0")
    if loss_cfg["flow_samples"] < 1:
        raise ValueError(f"loss.flow_samples = {loss_cfg['flow_samples']} must be >= 1 (flow "
                         "matching draws per prefix pass; 1 = pi0)")
    if not 0.0 < loss_cfg["noise_beta"] <= 1.0:
        raise ValueError(f"loss.noise_beta = {loss_cfg['noise_beta']} must be in (0, 1] (the share "
                         "of independent noise; 1 = pi0's N(0, I))")
    if loss_cfg["switch_weight"] <= 0 or loss_cfg["switch_window"] < 0:
        raise ValueError(f"loss.switch_weight = {loss_cfg['switch_weight']} must be > 0 and "
                         f"loss.switch_window = {loss_cfg['switch_window']} >= 0")
    if loss_cfg["switch_weight"] != 1.0 and not layout.groups_with_role("gripper"):
        raise ValueError("loss.switch_weight emphasizes gripper switches, but the layout has no "
                         "group of role gripper: set layout.roles, or loss.switch_weight=1")
    if strategy.balances:
        if not 0.0 <= loss_cfg["ema_decay"] < 1.0:
            raise ValueError(f"loss.ema_decay = {loss_cfg['ema_decay']} must be in [0, 1)")
        if not 0.0 < loss_cfg["w_min"] <= loss_cfg["w_max"]:
            raise ValueError(f"loss.w_min = {loss_cfg['w_min']} and loss.w_max = "
                             f"{loss_cfg['w_max']} must satisfy 0 < w_min <= w_max")


def loss_kwargs(loss_cfg: Mapping[str, Any], layout: ActionLayout, step: jax.Array,
                loss_params: Mapping[str, jax.Array], balancer: Mapping[str, jax.Array],
                switch_threshold: Any = None) -> dict[str, Any]:
    """The keyword arguments of `loss.training_loss` for this step (weights as traced arrays).

    `switch_threshold`: `[D]` or `[H, D]` the grippers' open/close boundary in normalized units,
    for gripper-switch emphasis (`loss.switch_weight != 1`)."""
    strategy = loss_lib.loss_strategy(loss_cfg["strategy"])
    warmup = loss_cfg["weight_warmup_steps"]
    kwargs: dict[str, Any] = dict(strategy=strategy.name,
                                  delta_weighting=loss_cfg["delta_weighting"])
    if loss_cfg["switch_weight"] != 1.0:
        kwargs.update(switch_threshold=switch_threshold, switch_weight=loss_cfg["switch_weight"],
                      switch_window=loss_cfg["switch_window"])
    if strategy.config_weights == "dimension":
        kwargs["dimension_weights"] = loss_lib.warmup_dimension_weights(
            jnp.asarray(loss_cfg["dimension_weights"], jnp.float32), step, warmup, layout)
    elif strategy.config_weights == "group":
        weights = loss_lib.warmup_group_weights(dict(loss_cfg["group_weights"]), step, warmup)
        if strategy.balances:
            static = jnp.stack([weights[g] for g in layout.group_names])
            balanced = loss_lib.loss_balanced_weights(balancer["ema"], static, loss_cfg["w_min"],
                                                      loss_cfg["w_max"])
            weights = {g: balanced[i] for i, g in enumerate(layout.group_names)}
        kwargs["group_weights"] = weights
    if strategy.learns_log_vars:
        kwargs["log_vars"] = loss_params["log_vars"]
        kwargs["min_log_var"] = loss_cfg["min_log_var"]
    return kwargs


def effective_group_weights(kwargs: Mapping[str, Any], layout: ActionLayout) -> jax.Array:
    """What each group's error is multiplied by this step, `[G]`, for the metrics.

    per_group / loss_balanced / per_dimension: the normalized static weight (mean over the group's
    dims; the static weights have mean 1 over all action dims). uncertainty: w_g exp(-s_g), the
    precision on the group's mean error. uniform / original: 1.
    """
    weighting = loss_lib.loss_strategy(kwargs["strategy"]).weighting
    if weighting == "precision":
        precision = jnp.exp(-jnp.maximum(kwargs["log_vars"], kwargs["min_log_var"]))
        return jnp.stack([kwargs["group_weights"][g] for g in layout.group_names]) * precision
    if weighting != "static":
        return jnp.ones((layout.num_groups,), jnp.float32)
    dim_weights = loss_lib.static_dim_weights(kwargs["strategy"], layout, kwargs.get("group_weights"),
                                              kwargs.get("dimension_weights"))
    membership = jnp.asarray(layout.membership())
    return dim_weights @ membership / membership.sum(0)


def microbatch(batch: Mapping[str, Any], n: int) -> Any:
    """`batch` (leaves `[B, ...]`) -> `[n, B / n, ...]`, part i the rows i, i + n, i + 2n, ...:
    strided, so that every device's rows of a batch sharded over devices hold some of each
    part (a device's block of B / devices rows, a multiple of n, splits evenly)."""
    return jax.tree.map(
        lambda x: jnp.swapaxes(x.reshape(x.shape[0] // n, n, *x.shape[1:]), 0, 1), batch)


def microbatched(value_and_grad: Any, params: Any, rng: jax.Array, batch: Mapping[str, Any],
                 n: int) -> Any:
    """`value_and_grad(params, rng, batch) -> ((loss, aux), grads)` of a mean over the batch's
    valid steps (`action_is_pad` `[B, H]` False), computed over `n` strided parts one after
    another (`microbatch`; part i with `fold_in(rng, i)`): each part's outputs weigh by its
    share of the batch's valid steps, so that a part's masked mean counts as its numerator and
    the loss, aux and gradients are the full batch's, however unevenly the parts are padded."""
    parts = microbatch(batch, n)
    counts = jnp.sum(~jnp.asarray(parts["action_is_pad"], bool), axis=(1, 2)).astype(jnp.float32)
    shares = counts / jnp.maximum(counts.sum(), 1.0)  # [n]

    def accumulate(total, part):
        i, share, micro = part
        out = value_and_grad(params, jax.random.fold_in(rng, i), micro)
        return jax.tree.map(lambda t, x: t + share * x, total, out), None

    zeros = jax.tree.map(jnp.zeros_like, jax.eval_shape(
        lambda: value_and_grad(params, rng, jax.tree.map(lambda x: x[0], parts))))
    out, _ = jax.lax.scan(accumulate, zeros, (jnp.arange(n), shares, parts))
    return out


def train_step(state: TrainState, batch: Mapping[str, Any], *, base_rng: jax.Array,
               model_config: Pi0Config, loss_cfg: Mapping[str, Any], layout: ActionLayout,
               tx: optax.GradientTransformation, schedule: optax.Schedule, ema_decay: float,
               noise_factor: jax.Array | None = None, switch_threshold: Any = None,
               loss_mask: Any = None, microbatches: int = 1
               ) -> tuple[TrainState, dict[str, jax.Array]]:
    """One optimizer step on the global `batch`.

    `noise_factor`: the correlated noise's Cholesky factor (`loss.noise_beta < 1`), else None;
    `switch_threshold`: see `loss_kwargs`; `loss_mask`: see `flow_model.compute_loss`.
    `loss.flow_samples` draws per sample share one prefix pass. Under LoRA only the adapters and
    the weights outside the adapted experts get gradients (`training/freeze.py`).
    `microbatches` n > 1 (`train.microbatches`) computes the loss and gradients of the batch
    over n strided parts (`microbatched`), one after another, each with its own noise
    (`fold_in(rng, i)`), weighed by their valid steps: the batch's loss with the activations of
    B / n samples at a time, one optimizer step (`original`'s temporal weights, normalized over
    the batch, normalize over each part).

    Returns:
      the new state and scalar metrics: `loss`, `grad_norm` (of the trained params), `lr`,
      `loss/<group>` (unweighted group error over the valid timesteps), `weight/<group>` (see
      `effective_group_weights`).
    """
    rng = jax.random.fold_in(base_rng, state.step)
    frozen = freeze.split(state.params, model_config)[1]

    def loss_fn(trainable, rng, batch):
        kwargs = loss_kwargs(loss_cfg, layout, state.step, trainable["loss_params"],
                             state.balancer, switch_threshold)
        params = freeze.merge(trainable["params"], frozen)
        loss, aux = flow_model.compute_loss(params, rng, batch, config=model_config,
                                            layout=layout, train=True,
                                            flow_samples=loss_cfg["flow_samples"],
                                            noise_factor=noise_factor, loss_mask=loss_mask,
                                            **kwargs)
        return loss, (aux, effective_group_weights(kwargs, layout))

    before = state.trainable(model_config)
    if microbatches == 1:
        (loss, (aux, weights)), grads = jax.value_and_grad(loss_fn, has_aux=True)(before, rng,
                                                                                   batch)
    else:
        (loss, (aux, weights)), grads = microbatched(
            jax.value_and_grad(loss_fn, has_aux=True), before, rng, batch, microbatches)
    updates, opt_state = tx.update(grads, state.opt_state, before)
    trainable = optax.apply_updates(before, updates)

    group_loss = jnp.stack([aux["group_loss"][g] for g in layout.group_names])
    ema_params = state.ema_params
    if ema_params is not None:
        ema_trained = jax.tree.map(lambda e, p: ema_decay * e + (1.0 - ema_decay) * p,
                                   freeze.split(ema_params, model_config)[0], trainable["params"])
        ema_params = freeze.merge(ema_trained, frozen)
    balancer = state.balancer
    if balancer:
        ema, count = loss_lib.update_group_loss_ema(balancer["ema"], balancer["count"], group_loss,
                                                    loss_cfg["ema_decay"])
        balancer = {"ema": ema, "count": count}

    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads), "lr": schedule(state.step)}
    for i, g in enumerate(layout.group_names):
        metrics[f"loss/{g}"] = group_loss[i]
        metrics[f"weight/{g}"] = weights[i]
    new_state = state.replace(step=state.step + 1,
                              params=freeze.merge(trainable["params"], frozen),
                              loss_params=trainable["loss_params"], opt_state=opt_state,
                              ema_params=ema_params, balancer=balancer)
    return new_state, metrics
