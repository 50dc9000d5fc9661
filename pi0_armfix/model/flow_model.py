"""The flow-matching model as functions over a plain nested-dict params pytree (openpi names);
openpi calls this the model, `inference.RunPolicy` is the policy that wraps it.

  init_params(config, rng) -> params
  param_shapes(config) -> params of jax.ShapeDtypeStruct (no allocation)
  velocity(params, observation, x_t, t, *, config) -> v [B, H, A]
  compute_loss(params, rng, batch, *, config, layout, train, **loss_kwargs) -> (loss, aux)
  sample_actions(params, rng, observation, *, config, num_steps=10, noise=None,
                 use_kv_cache=True, inpaint=None, inpaint_weights=None, temperature=1.0,
                 average_draws=1, num_draws=None) -> actions [B, H, A] (or [M, B, H, A])

`observation` / `batch` are the dicts of docs/design.md §4 (raw uint8 cameras at any resolution; the
model converts, resizes and, for training, augments them). Parameters are float32; activations
run in `config.dtype`. init_params, velocity and sample_actions are jit-compiled (config and the
other non-array arguments static); compute_loss is traced by the caller's train step.
Flow-matching convention (docs/design.md §3): t = 1 is noise, t = 0 the data.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_armfix import loss as loss_lib
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model import pi0
from pi0_armfix.model.config import Pi0Config, dense_shapes
from pi0_armfix.model.tree import flatten_tree
from pi0_armfix.model.inputs import preprocess_observation

Params = dict[str, Any]


@functools.partial(jax.jit, static_argnums=0)
def init_params(config: Pi0Config, rng: jax.Array) -> Params:
    """Random float32 parameters with openpi's tree structure and names."""
    rng_llm, rng_img, rng_dense = jax.random.split(rng, 3)
    llm = pi0.transformer(config).init(rng_llm, method="initialize")["params"]
    image = jnp.zeros((1, *config.image_resolution, 3), jnp.float32)
    img = pi0.vision_tower(config).init(rng_img, image)["params"]
    params: Params = {"PaliGemma": {"llm": llm, "img": img}}
    shapes = dense_shapes(config)
    for key, name in zip(jax.random.split(rng_dense, len(shapes)), shapes):
        fan_in, fan_out = shapes[name]
        kernel = jax.nn.initializers.lecun_normal()(key, (fan_in, fan_out), jnp.float32)
        params[name] = {"kernel": kernel, "bias": jnp.zeros((fan_out,), jnp.float32)}
    return params


def param_shapes(config: Pi0Config) -> Params:
    """The parameter tree as jax.ShapeDtypeStruct leaves, without allocating it."""
    return jax.eval_shape(lambda: init_params(config, jax.random.key(0)))


def param_tree(config: Pi0Config) -> dict[str, list]:
    """`{"path/with/slashes": [shape, dtype]}`, sorted: the format of openpi's reference tree file."""
    flat = flatten_tree(param_shapes(config))
    return {path: [list(leaf.shape), str(leaf.dtype)] for path, leaf in sorted(flat.items())}


@functools.partial(jax.jit, static_argnames="config")
def velocity(params: Params, observation: Mapping[str, Any], x_t: jax.Array, t: jax.Array, *,
             config: Pi0Config) -> jax.Array:
    """The predicted flow v(x_t, t) [B, H, A] float32 (eval preprocessing, one full forward).

    Args:
      observation: batch dict without actions. x_t: [B, H, A]. t: [B] in [0, 1].
    """
    observation = preprocess_observation(None, observation, config=config, train=False)
    return pi0.forward_velocity(params, observation, x_t, t, config=config)


def compute_loss(params: Params, rng: jax.Array, batch: Mapping[str, Any], *, config: Pi0Config,
                 layout: ActionLayout, train: bool, flow_samples: int = 1,
                 noise_factor: jax.Array | None = None, loss_mask: jax.Array | None = None,
                 **loss_kwargs) -> tuple[jax.Array, dict[str, Any]]:
    """Flow-matching loss on a batch.

    t ~ Beta(1.5, 1) * 0.999 + 0.001 per draw, x_t = t * noise + (1 - t) * a, u = noise - a,
    e = (v - u)^2, reduced by `loss.training_loss(e, actions, action_is_pad, layout=layout,
    **loss_kwargs)` over all K * B draws (the mean over the K draws of each sample's loss).

    Args:
      rng: splits into augmentation, noise and time keys.
      batch: docs/design.md §4 batch with `actions` [B, H, A] and `action_is_pad` [B, H].
      train: apply image augmentation.
      flow_samples: K noise / time draws per sample, all against one prefix pass
        (`pi0.forward_velocity`); K = 1 is the plain pi0 loss.
      noise_factor: `[H * A, H * A]` Cholesky factor of correlated noise (`noise.flow_noise`),
        or None.
      loss_mask: `[A]` or `[H, A]`, 0 on the dims that carry no loss (the constant dims,
        `data.batching.loss_mask`), or None.
      **loss_kwargs: `strategy`, `group_weights`, ... of `loss.training_loss`.
    Returns:
      (scalar loss over valid timesteps, aux) with aux = {"group_loss": {group: scalar}}.
    """
    actions = jnp.asarray(batch["actions"], jnp.float32)
    if actions.shape[1:] != (config.action_horizon, config.action_dim):
        raise ValueError(f"batch['actions'] has shape {actions.shape}; the model expects "
                         f"[B, action_horizon={config.action_horizon}, action_dim={config.action_dim}]")
    rng_augment, rng_noise, rng_time = jax.random.split(rng, 3)
    observation = preprocess_observation(rng_augment, batch, config=config, train=train)
    draws = flow_samples * actions.shape[0]
    actions = jnp.tile(actions, (flow_samples, 1, 1))  # row k * B + b: draw k of sample b
    is_pad = jnp.tile(jnp.asarray(batch["action_is_pad"], bool), (flow_samples, 1))
    noise = noise_lib.flow_noise(rng_noise, (draws, *actions.shape[1:]), noise_factor)
    t = jax.random.beta(rng_time, 1.5, 1.0, (draws,)) * 0.999 + 0.001
    x_t = t[:, None, None] * noise + (1.0 - t[:, None, None]) * actions
    v = pi0.forward_velocity(params, observation, x_t, t, config=config, samples=flow_samples)
    per_dim_loss = jnp.square(v - (noise - actions))
    if loss_mask is not None:
        per_dim_loss = per_dim_loss * jnp.asarray(loss_mask, per_dim_loss.dtype)
    return loss_lib.training_loss(per_dim_loss, actions, is_pad, layout=layout, live=loss_mask,
                                  **loss_kwargs)


@functools.partial(jax.jit, static_argnames=("config", "num_steps", "use_kv_cache", "num_draws",
                                             "average_draws", "draw_counts"))
def sample_actions(params: Params, rng: jax.Array, observation: Mapping[str, Any], *,
                   config: Pi0Config, num_steps: int = 10, noise: jax.Array | None = None,
                   use_kv_cache: bool = True, noise_factor: jax.Array | None = None,
                   inpaint: jax.Array | None = None, inpaint_weights: jax.Array | None = None,
                   temperature: float = 1.0, average_draws: int = 1, num_draws: int | None = None,
                   draw_counts: Sequence[int] | None = None) -> jax.Array:
    """Integrates the flow from t = 1 (noise) to t = 0 with `num_steps` Euler steps.

    The policy's inference levers: `temperature` τ scales the initial noise (τ < 1 samples
    nearer the mode), and `average_draws` k > 1 returns each chunk as the mean of k draws from
    independent noise (the spread of a single draw averaged away). The k draws share one prefix
    pass (its KV cache is repeated), so k costs k suffix passes, not k prefix passes.

    Args:
      rng: draws the initial noise (unused when `noise` is given).
      observation: batch dict without actions.
      noise: optional [B, H, A] starting point (k = 1), or [k * B, H, A] (row j * B + b: draw j
        of sample b); not scaled by the temperature.
      use_kv_cache: run the prefix once and reuse its keys / values at every step; False
        recomputes the full prefix + suffix forward each step (same result, for checking).
      noise_factor: the correlated noise's Cholesky factor the policy was trained with, or None.
      inpaint, inpaint_weights: soft inpainting (the real-time-chunking family): after every
        Euler step to time t, x_t <- w * (t * noise + (1 - t) * inpaint) + (1 - w) * x_t, so the
        chunk follows the actions `inpaint` [B, H, A] (normalized) with weight w [B, H] in [0, 1]
        (1: exactly, 0: free), e.g. the unexecuted tail of the previous chunk.
      temperature: τ in (0, 1], the initial noise's scale.
      average_draws: k, draws averaged into each returned chunk.
      num_draws: M: return every one of M draws, `[M, B, H, A]` (draw j from rows j * B + b of
        the noise), instead of their mean; None returns the mean of `average_draws`.
      draw_counts: `[A]` draws averaged into each action dim (`mean_of_draws`), in place of
        `average_draws` (per-group draws, `policies.sampling.Sampling.group_draws`).
    Returns:
      actions [B, H, A] float32 (normalized, padded like the training targets), or [M, B, H, A].
    """
    observation = preprocess_observation(None, observation, config=config, train=False)
    batch_size = observation["state"].shape[0]
    draws = num_draws or (max(draw_counts) if draw_counts else average_draws)
    if noise is None:
        noise = temperature * noise_lib.flow_noise(
            rng, (draws * batch_size, config.action_horizon, config.action_dim), noise_factor)
    elif noise.shape[0] != draws * batch_size:
        raise ValueError(f"noise has {noise.shape[0]} rows; {draws} draw(s) of a batch of "
                         f"{batch_size} need {draws * batch_size}")

    def repeat(x):  # [B, ...] -> [draws * B, ...], row j * B + b
        return jnp.tile(x, (draws,) + (1,) * (x.ndim - 1))

    dt = -1.0 / num_steps
    if use_kv_cache:
        kv_cache, prefix_mask = pi0.prefix_kv_cache(params, observation, config=config)
        state = observation["state"]
        if draws > 1:  # the cache is [depth, B, P, K, Dh]
            kv_cache = tuple(jnp.tile(c, (1, draws, 1, 1, 1)) for c in kv_cache)
            prefix_mask, state = repeat(prefix_mask), repeat(state)

        def flow(x_t, t):
            return pi0.cached_velocity(params, state, kv_cache, prefix_mask, x_t, t, config=config)
    else:
        repeated = jax.tree.map(repeat, observation) if draws > 1 else observation

        def flow(x_t, t):
            return pi0.forward_velocity(params, repeated, x_t, t, config=config)
    if inpaint is not None and draws > 1:
        inpaint, inpaint_weights = repeat(inpaint), repeat(inpaint_weights)
    rows = noise.shape[0]

    def step(_, carry):
        x_t, t = carry
        v = flow(x_t, jnp.broadcast_to(t, (rows,)))
        x_next, t_next = x_t + dt * v, t + dt
        if inpaint is not None:
            t_next = jnp.maximum(t_next, 0.0)
            known = t_next * noise + (1.0 - t_next) * inpaint
            w = inpaint_weights[..., None]
            x_next = w * known + (1.0 - w) * x_next
        return x_next, t_next

    actions, _ = jax.lax.fori_loop(0, num_steps, step, (noise.astype(jnp.float32), jnp.float32(1.0)))
    actions = actions.reshape(draws, batch_size, *actions.shape[1:])
    return actions if num_draws else mean_of_draws(actions, draw_counts)


def mean_of_draws(draws: jax.Array, counts: Sequence[int] | None = None) -> jax.Array:
    """Draws `[k, ..., A]` -> `[..., A]`: each dim d the mean of its first `counts[d]` draws
    (`counts` `[A]`, each in [1, k]), or of all k for None. Every mean includes draw 0, so a dim
    of one draw is the single draw."""
    if counts is None:
        return draws.mean(axis=0)
    counts = np.asarray(counts)
    weights = (np.arange(draws.shape[0])[:, None] < counts) / counts  # [k, A]
    return (draws * weights.reshape(len(weights), *(1,) * (draws.ndim - 2), -1)).sum(axis=0)
