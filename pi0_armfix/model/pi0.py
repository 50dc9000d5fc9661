"""The pi0 forward computation over a plain params dict (see the package docstring for the spec).

Parameter tree (openpi's names):
  PaliGemma/llm   the two-expert Gemma transformer (`gemma.Transformer`; pi0.5: the action
                  expert's norms adaptive, `pre_attention_norm_1/Dense_0`, ...)
  PaliGemma/img   the SigLIP tower (`siglip.SigLIP`)
  state_proj, action_in_proj, action_time_mlp_in, action_time_mlp_out, action_out_proj
                  dense layers {kernel [in, out], bias [out]}; pi0.5: action_in_proj,
                  time_mlp_in, time_mlp_out, action_out_proj

All functions take an observation already through `inputs.preprocess_observation`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp

from pi0_armfix.model.config import Pi0Config
from pi0_armfix.model.gemma import Transformer
from pi0_armfix.model.siglip import SigLIP

Params = Mapping[str, Any]

# Time embedding periods: sensitivity over t in [0, 1].
TIME_MIN_PERIOD = 4e-3
TIME_MAX_PERIOD = 4.0


def transformer(config: Pi0Config) -> Transformer:
    return Transformer(configs=(config.paligemma, config.action_expert), vocab_size=config.vocab_size,
                       dtype=config.dtype, remat=_remat(config), unroll=config.unroll_layers,
                       adaptive=(False, config.pi05), attention=config.attention)


def vision_tower(config: Pi0Config) -> SigLIP:
    return SigLIP(config=config.siglip, num_patches=config.num_image_tokens,
                  out_width=config.paligemma.width, dtype=config.dtype, remat=_remat(config),
                  unroll=config.unroll_layers)


def _remat(config: Pi0Config) -> str:
    return config.remat_policy if config.remat else ""


def dense(params: Params, x: jax.Array) -> jax.Array:
    """x [..., in] @ kernel [in, out] + bias, in the promoted dtype of x and the params."""
    return jnp.dot(x, params["kernel"]) + params["bias"]


def posemb_sincos(t: jax.Array, dim: int, min_period: float = TIME_MIN_PERIOD,
                  max_period: float = TIME_MAX_PERIOD) -> jax.Array:
    """Sin-cos embedding of scalars t [B] -> [B, dim]: sin half, then cos half."""
    fraction = jnp.linspace(0.0, 1.0, dim // 2)
    period = min_period * (max_period / min_period) ** fraction
    arg = jnp.einsum("i,j->ij", t, 1.0 / period * 2 * jnp.pi, precision=jax.lax.Precision.HIGHEST)
    return jnp.concatenate([jnp.sin(arg), jnp.cos(arg)], axis=-1)


def make_attn_mask(input_mask: jax.Array, ar_mask: jax.Array) -> jax.Array:
    """Block-causal mask: token i sees token j iff cumsum(ar)[j] <= cumsum(ar)[i], both valid.

    Args:
      input_mask: [B, N] bool, False for padding.
      ar_mask: [N] (or [B, N]) bool, True where a new block starts that earlier tokens cannot see.
    Returns:
      [B, N, N] bool, [query, key].
    """
    ar_mask = jnp.broadcast_to(ar_mask, input_mask.shape)
    cumsum = jnp.cumsum(ar_mask, axis=1)
    causal = cumsum[:, None, :] <= cumsum[:, :, None]
    valid = input_mask[:, None, :] & input_mask[:, :, None]
    return causal & valid


def embed_prefix(params: Params, observation: Mapping[str, Any], *, config: Pi0Config
                 ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Camera tokens then prompt tokens, one bidirectional block.

    Returns:
      tokens [B, P, W] in `config.dtype`, input mask [B, P] bool, ar mask [P] bool (all False).
    """
    images = [observation["image"][key] for key in config.image_keys]
    # One tower call for all cameras (weights are shared): [num_cameras * B, n, W].
    image_tokens = vision_tower(config).apply(
        {"params": params["PaliGemma"]["img"]}, jnp.concatenate(images, axis=0))
    image_tokens = jnp.split(image_tokens, len(images), axis=0)
    text_tokens = transformer(config).apply(
        {"params": params["PaliGemma"]["llm"]}, observation["tokenized_prompt"], method="embed")
    n = config.num_image_tokens
    masks = [jnp.repeat(observation["image_mask"][key][:, None], n, axis=1) for key in config.image_keys]
    tokens = jnp.concatenate([t.astype(config.dtype) for t in image_tokens] + [text_tokens], axis=1)
    text_mask = jnp.asarray(observation["tokenized_prompt_mask"], bool)
    input_mask = jnp.concatenate(masks + [text_mask], axis=1)
    return tokens, input_mask, jnp.zeros((tokens.shape[1],), bool)


def embed_suffix(params: Params, state: jax.Array, x_t: jax.Array, t: jax.Array, *, config: Pi0Config
                 ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array | None]:
    """pi0: a state token then H action tokens (x_t mixed with the time embedding by a swish
    MLP). pi0.5: H action tokens of x_t alone; the time embedding through `time_mlp_in -> swish
    -> time_mlp_out -> swish` is the condition of the action expert's adaptive norms.

    Args:
      state: [B, A] (unused by pi0.5, whose prompt carries it); x_t: [B, H, A] noisy actions;
        t: [B] flow time.
    Returns:
      tokens [B, S, E] float32 (S = 1 + H, pi0.5: H), input mask [B, S] (all True), ar mask [S]
      (True for the state token and the first action token), and the condition [B, E] (pi0.5)
      or None.
    """
    action_tokens = dense(params["action_in_proj"], x_t)
    time_emb = posemb_sincos(t, config.action_expert.width)
    horizon = x_t.shape[1]
    if config.pi05:
        cond = jax.nn.swish(dense(params["time_mlp_in"], time_emb))
        cond = jax.nn.swish(dense(params["time_mlp_out"], cond))
        ar_mask = jnp.asarray([True] + [False] * (horizon - 1))
        return action_tokens, jnp.ones(action_tokens.shape[:2], bool), ar_mask, cond
    state_token = dense(params["state_proj"], state)[:, None, :]
    time_tokens = jnp.broadcast_to(time_emb[:, None, :], action_tokens.shape)
    hidden = dense(params["action_time_mlp_in"], jnp.concatenate([action_tokens, time_tokens], axis=-1))
    action_tokens = dense(params["action_time_mlp_out"], jax.nn.swish(hidden))
    tokens = jnp.concatenate([state_token, action_tokens], axis=1)
    ar_mask = jnp.asarray([True, True] + [False] * (horizon - 1))
    return tokens, jnp.ones(tokens.shape[:2], bool), ar_mask, None


def velocity_out(params: Params, suffix_out: jax.Array, horizon: int) -> jax.Array:
    """The action tokens' outputs (the last `horizon` of the suffix) -> v [B, H, A] float32."""
    return dense(params["action_out_proj"], suffix_out[:, -horizon:]).astype(jnp.float32)


def forward_velocity(params: Params, observation: Mapping[str, Any], x_t: jax.Array, t: jax.Array, *,
                     config: Pi0Config, samples: int = 1) -> jax.Array:
    """One joint pass of the prefix and `samples` suffixes.

    With K = `samples` > 1 the prefix (images + prompt, most of the compute) runs once and K
    suffixes of K flow-matching draws of the same observation attend to it in one sequence: each
    suffix sees the prefix and itself under the usual mask, never another suffix, at the positions
    a lone suffix has. K = 1 is the plain pi0 forward.

    Args:
      x_t: [K * B, H, A] noisy actions, draw k of sample b at row k * B + b; t: [K * B].
    Returns:
      v [K * B, H, A] float32.
    """
    prefix, prefix_mask, prefix_ar = embed_prefix(params, observation, config=config)
    state = jnp.tile(observation["state"], (samples, 1))
    suffix, suffix_mask, suffix_ar, cond = embed_suffix(params, state, x_t, t, config=config)
    batch, prefix_len = prefix_mask.shape
    suffix_len = suffix.shape[1]
    input_mask = jnp.concatenate([prefix_mask, suffix_mask[:batch]], axis=1)
    attn_mask = make_attn_mask(input_mask, jnp.concatenate([prefix_ar, suffix_ar]))
    positions = jnp.cumsum(input_mask, axis=1) - 1
    if samples > 1:
        suffix = _samples_into_sequence(suffix, samples)
        attn_mask, positions = _samples_mask(attn_mask, positions, prefix_len, samples)
        if cond is not None:  # each suffix token carries its own draw's condition
            cond = _samples_into_sequence(
                jnp.broadcast_to(cond[:, None, :], (cond.shape[0], suffix_len, cond.shape[1])),
                samples)
    (_, suffix_out), _ = transformer(config).apply(
        {"params": params["PaliGemma"]["llm"]}, [prefix, suffix], positions, attn_mask, cond=cond)
    if samples > 1:  # [B, K * S, E] -> [K * B, S, E]
        suffix_out = suffix_out.reshape(batch, samples, suffix_len, -1).swapaxes(0, 1).reshape(
            samples * batch, suffix_len, -1)
    return velocity_out(params, suffix_out, x_t.shape[1])


def _samples_into_sequence(suffix: jax.Array, samples: int) -> jax.Array:
    """[K * B, S, E] (row k * B + b) -> [B, K * S, E] (the K suffixes of sample b in a row)."""
    _, length, width = suffix.shape
    return suffix.reshape(samples, -1, length, width).swapaxes(0, 1).reshape(-1, samples * length,
                                                                             width)


def _samples_mask(attn_mask: jax.Array, positions: jax.Array, prefix_len: int, samples: int
                  ) -> tuple[jax.Array, jax.Array]:
    """The mask [B, P + S, P + S] and positions [B, P + S] of one suffix, widened to K suffixes:
    [B, P + K S, P + K S] (suffix k sees the prefix and suffix k only) and [B, P + K S]."""
    prefix_rows = attn_mask[:, :prefix_len]  # the prefix never sees a suffix
    to_prefix, to_suffix = attn_mask[:, prefix_len:, :prefix_len], attn_mask[:, prefix_len:,
                                                                              prefix_len:]
    own = jnp.eye(samples, dtype=bool)
    suffix_rows = jnp.concatenate([
        jnp.tile(to_prefix, (1, samples, 1)),
        (own[None, :, None, :, None] & to_suffix[:, None, :, None, :]).reshape(
            attn_mask.shape[0], samples * to_suffix.shape[1], samples * to_suffix.shape[2]),
    ], axis=2)
    width = prefix_len + samples * to_suffix.shape[2]
    prefix_rows = jnp.pad(prefix_rows, ((0, 0), (0, 0), (0, width - prefix_rows.shape[2])))
    positions = jnp.concatenate([positions[:, :prefix_len],
                                 jnp.tile(positions[:, prefix_len:], (1, samples))], axis=1)
    return jnp.concatenate([prefix_rows, suffix_rows], axis=1), positions


def prefix_kv_cache(params: Params, observation: Mapping[str, Any], *, config: Pi0Config
                    ) -> tuple[tuple[jax.Array, jax.Array], jax.Array]:
    """Runs the prefix alone. Returns its (k, v), each [depth, B, P, K, Dh], and its mask [B, P]."""
    prefix, prefix_mask, prefix_ar = embed_prefix(params, observation, config=config)
    positions = jnp.cumsum(prefix_mask, axis=1) - 1
    _, kv_cache = transformer(config).apply(
        {"params": params["PaliGemma"]["llm"]}, [prefix, None], positions,
        make_attn_mask(prefix_mask, prefix_ar))
    return kv_cache, prefix_mask


def cached_velocity(params: Params, state: jax.Array, kv_cache: tuple[jax.Array, jax.Array],
                    prefix_mask: jax.Array, x_t: jax.Array, t: jax.Array, *, config: Pi0Config
                    ) -> jax.Array:
    """The suffix pass against a prefix KV cache; equals `forward_velocity`. -> v [B, H, A]."""
    suffix, suffix_mask, suffix_ar, cond = embed_suffix(params, state, x_t, t, config=config)
    suffix_len = suffix.shape[1]
    # Suffix queries see every valid prefix key, and the suffix under its own block-causal mask.
    to_prefix = jnp.broadcast_to(prefix_mask[:, None, :], (prefix_mask.shape[0], suffix_len,
                                                           prefix_mask.shape[1]))
    attn_mask = jnp.concatenate([to_prefix, make_attn_mask(suffix_mask, suffix_ar)], axis=-1)
    positions = jnp.sum(prefix_mask, axis=-1)[:, None] + jnp.cumsum(suffix_mask, axis=-1) - 1
    (_, suffix_out), _ = transformer(config).apply(
        {"params": params["PaliGemma"]["llm"]}, [None, suffix], positions, attn_mask, kv_cache,
        cond=cond)
    return velocity_out(params, suffix_out, x_t.shape[1])
