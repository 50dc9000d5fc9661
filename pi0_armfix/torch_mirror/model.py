"""pi0 and pi0.5 in PyTorch: the mirror of `pi0_armfix/model/{pi0,policy}.py`, for converted checkpoints.

`Pi0(config)` is built from the same `Pi0Config` as the Flax model (`config.json` of a converted
checkpoint is `Pi0Config.to_dict()`). Its parameters are openpi's tree under torch names
(`params.py`: "/" -> ".", depth axes stacked, flax layouts), so `state_dict()` is exactly what
`convert.py` writes. The forward computation is the one specified in the docstring of
`pi0_armfix/model/__init__.py`; the towers are in `layers.py`.

  velocity(observation, x_t, t) -> v [B, H, A]
  compute_loss(observation, actions, action_is_pad, noise, time, *, layout, **loss_kwargs)
      -> (loss, {"group_loss": {group: scalar}})
  sample_actions(observation, noise, num_steps=10, use_kv_cache=True) -> actions [B, H, A]

`observation` is the batch dict of docs/design.md §4 (numpy or torch arrays, uint8 cameras at any
resolution). Flow-matching convention (docs/design.md §3): t = 1 is noise, t = 0 the data. Noise and
time are inputs, so a caller (a parity test, a deployment) controls every random draw.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model.config import Pi0Config
from pi0_armfix.torch_mirror import layers
from pi0_armfix.torch_mirror import loss as loss_lib
from pi0_armfix.torch_mirror.inputs import as_tensor, preprocess_observation
from pi0_armfix.torch_mirror.params import param_shapes

Params = Mapping[str, Any]

# Time embedding periods: sensitivity over t in [0, 1] (openpi's pi0).
TIME_MIN_PERIOD = 4e-3
TIME_MAX_PERIOD = 4.0
_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def posemb_sincos(t: torch.Tensor, dim: int, min_period: float = TIME_MIN_PERIOD,
                  max_period: float = TIME_MAX_PERIOD) -> torch.Tensor:
    """Sin-cos embedding of scalars t [B] -> [B, dim]: sin half, then cos half (float32)."""
    # linspace(0, 1, n) as XLA computes it (iota times the float32 reciprocal of n - 1): periods
    # down to 4e-3 turn a last-bit difference here into a visible one in the sines.
    half = dim // 2
    fraction = torch.arange(half, dtype=torch.float32) * torch.tensor(1.0 / max(half - 1, 1))
    period = min_period * (torch.tensor(max_period / min_period, dtype=torch.float32) ** fraction)
    arg = t.to(torch.float32)[:, None] * (1.0 / period * 2 * torch.pi)[None, :]
    return torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)


def make_attn_mask(input_mask: torch.Tensor, ar_mask: torch.Tensor) -> torch.Tensor:
    """Block-causal mask: token i sees token j iff cumsum(ar)[j] <= cumsum(ar)[i], both valid.

    Args:
      input_mask: [B, N] bool, False for padding.
      ar_mask: [N] (or [B, N]) bool, True where a new block starts that earlier tokens cannot see.
    Returns:
      [B, N, N] bool, [query, key].
    """
    cumsum = torch.cumsum(ar_mask.broadcast_to(input_mask.shape).to(torch.int32), dim=1)
    causal = cumsum[:, None, :] <= cumsum[:, :, None]
    valid = input_mask[:, None, :] & input_mask[:, :, None]
    return causal & valid


def _unflatten(named: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """{"a.b.c": tensor} -> {"a": {"b": {"c": tensor}}}."""
    tree: dict[str, Any] = {}
    for name, value in named.items():
        *parents, leaf = name.split(".")
        node = tree
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    return tree


class Pi0(nn.Module):
    """pi0 with openpi's parameter tree (torch names), built from a `Pi0Config`.

    Parameters start at zero: the mirror receives its weights from a converted checkpoint
    (`convert.load_converted`) or `load_state_dict`; it is not trained from scratch.
    """

    def __init__(self, config: Pi0Config):
        super().__init__()
        self.config = config
        self.dtype = _DTYPES[config.dtype]
        for path, shape in param_shapes(config).items():
            *parents, leaf = path.split("/")
            module: nn.Module = self
            for name in parents:
                if not hasattr(module, name):
                    module.add_module(name, nn.Module())
                module = getattr(module, name)
            module.register_parameter(leaf, nn.Parameter(torch.zeros(shape, dtype=torch.float32)))

    def params(self) -> dict[str, Any]:
        """The parameters as a nested dict with openpi's names (views, not copies)."""
        return _unflatten(dict(self.named_parameters()))

    # ------------------------------------------------------------------------- token embedding

    def embed_prefix(self, params: Params, observation: Mapping[str, Any]
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Camera tokens then prompt tokens, one bidirectional block.

        Returns:
          tokens [B, P, W] in the activation dtype, input mask [B, P] bool, ar mask [P] (all False).
        """
        config = self.config
        images = [observation["image"][key] for key in config.image_keys]
        # One tower call for all cameras (weights are shared): [num_cameras * B, n, W].
        image_tokens = layers.siglip(params["PaliGemma"]["img"], torch.cat(images, dim=0),
                                     config=config.siglip, dtype=self.dtype)
        image_tokens = torch.chunk(image_tokens, len(images), dim=0)
        text_tokens = layers.embed_tokens(params["PaliGemma"]["llm"], observation["tokenized_prompt"],
                                          dtype=self.dtype)
        n = config.num_image_tokens
        masks = [observation["image_mask"][key][:, None].repeat(1, n) for key in config.image_keys]
        tokens = torch.cat([t.to(self.dtype) for t in image_tokens] + [text_tokens], dim=1)
        input_mask = torch.cat(masks + [observation["tokenized_prompt_mask"]], dim=1)
        return tokens, input_mask, torch.zeros(tokens.shape[1], dtype=torch.bool)

    def embed_suffix(self, params: Params, state: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """pi0: a state token then H action tokens (x_t mixed with the time embedding by a swish
        MLP). pi0.5: H action tokens of x_t alone, and the time embedding through `time_mlp_in
        -> swish -> time_mlp_out -> swish` as the adaptive norms' condition.

        Args:
          state: [B, A] (unused by pi0.5); x_t: [B, H, A] noisy actions; t: [B] flow time.
        Returns:
          tokens [B, S, E] float32 (S = 1 + H, pi0.5: H), input mask [B, S] (all True), ar mask
          [S], and the condition [B, E] (pi0.5) or None.
        """
        if not self.config.use_state:  # the no-state ablation: a zero state, as in the Flax model
            state = torch.zeros_like(state)
        action_tokens = layers.dense(params["action_in_proj"], x_t)
        time_emb = posemb_sincos(t, self.config.action_expert.width)
        horizon = x_t.shape[1]
        if self.config.pi05:
            cond = nn.functional.silu(layers.dense(params["time_mlp_in"], time_emb))
            cond = nn.functional.silu(layers.dense(params["time_mlp_out"], cond))
            ar_mask = torch.tensor([True] + [False] * (horizon - 1))
            return action_tokens, torch.ones(action_tokens.shape[:2], dtype=torch.bool), ar_mask, cond
        state_token = layers.dense(params["state_proj"], state)[:, None, :]
        time_tokens = time_emb[:, None, :].broadcast_to(action_tokens.shape)
        hidden = layers.dense(params["action_time_mlp_in"], torch.cat([action_tokens, time_tokens], -1))
        action_tokens = layers.dense(params["action_time_mlp_out"], nn.functional.silu(hidden))
        tokens = torch.cat([state_token, action_tokens], dim=1)
        ar_mask = torch.tensor([True, True] + [False] * (horizon - 1))
        return tokens, torch.ones(tokens.shape[:2], dtype=torch.bool), ar_mask, None

    # ---------------------------------------------------------------------------- forward passes

    def _llm(self, params: Params, xs, positions, attn_mask, kv_cache=None, cond=None):
        config = self.config
        return layers.transformer(params["PaliGemma"]["llm"], xs, positions, attn_mask, kv_cache,
                                  configs=(config.paligemma, config.action_expert), dtype=self.dtype,
                                  cond=cond, adaptive=(False, config.pi05))

    def _action_out(self, params: Params, suffix_out: torch.Tensor) -> torch.Tensor:
        """The action tokens' outputs (the last H of the suffix) -> v [B, H, A] float32."""
        horizon = self.config.action_horizon
        return layers.dense(params["action_out_proj"], suffix_out[:, -horizon:]).to(torch.float32)

    def forward_velocity(self, params: Params, observation: Mapping[str, Any], x_t: torch.Tensor,
                         t: torch.Tensor) -> torch.Tensor:
        """One joint prefix + suffix pass on a preprocessed observation -> v [B, H, A] float32."""
        prefix, prefix_mask, prefix_ar = self.embed_prefix(params, observation)
        suffix, suffix_mask, suffix_ar, cond = self.embed_suffix(params, observation["state"], x_t, t)
        input_mask = torch.cat([prefix_mask, suffix_mask], dim=1)
        attn_mask = make_attn_mask(input_mask, torch.cat([prefix_ar, suffix_ar]))
        positions = torch.cumsum(input_mask.to(torch.int32), dim=1) - 1
        (_, suffix_out), _ = self._llm(params, [prefix, suffix], positions, attn_mask, cond=cond)
        return self._action_out(params, suffix_out)

    def prefix_kv_cache(self, params: Params, observation: Mapping[str, Any]
                        ) -> tuple[layers.KVCache, torch.Tensor]:
        """Runs the prefix alone. Returns its (k, v), each [depth, B, P, K, Dh], and its mask [B, P]."""
        prefix, prefix_mask, prefix_ar = self.embed_prefix(params, observation)
        positions = torch.cumsum(prefix_mask.to(torch.int32), dim=1) - 1
        _, kv_cache = self._llm(params, [prefix, None], positions, make_attn_mask(prefix_mask, prefix_ar))
        return kv_cache, prefix_mask

    def cached_velocity(self, params: Params, state: torch.Tensor, kv_cache: layers.KVCache,
                        prefix_mask: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The suffix pass against a prefix KV cache; equals `forward_velocity`. -> v [B, H, A]."""
        suffix, suffix_mask, suffix_ar, cond = self.embed_suffix(params, state, x_t, t)
        batch, prefix_len = prefix_mask.shape
        # Suffix queries see every valid prefix key, and the suffix under its own block-causal mask.
        to_prefix = prefix_mask[:, None, :].broadcast_to(batch, suffix.shape[1], prefix_len)
        attn_mask = torch.cat([to_prefix, make_attn_mask(suffix_mask, suffix_ar)], dim=-1)
        positions = (prefix_mask.to(torch.int32).sum(-1)[:, None]
                     + torch.cumsum(suffix_mask.to(torch.int32), dim=-1) - 1)
        (_, suffix_out), _ = self._llm(params, [None, suffix], positions, attn_mask, kv_cache,
                                       cond=cond)
        return self._action_out(params, suffix_out)

    # ------------------------------------------------------------------------------- public API

    def velocity(self, observation: Mapping[str, Any], x_t: Any, t: Any) -> torch.Tensor:
        """The predicted flow v(x_t, t) [B, H, A] float32.

        Args:
          observation: batch dict without actions. x_t: [B, H, A]. t: [B] in [0, 1].
        """
        observation = preprocess_observation(observation, config=self.config)
        return self.forward_velocity(self.params(), observation, as_tensor(x_t).to(torch.float32),
                                     as_tensor(t).to(torch.float32))

    def compute_loss(self, observation: Mapping[str, Any], actions: Any, action_is_pad: Any,
                     noise: Any, time: Any, *, layout: ActionLayout, loss_mask: Any = None,
                     **loss_kwargs) -> tuple[torch.Tensor, dict[str, Any]]:
        """Flow-matching loss with given noise and time (the JAX side draws them from its rng).

        x_t = t * noise + (1 - t) * a, u = noise - a, e = (v - u)^2 [B, H, A], reduced by
        `torch_mirror.loss.training_loss(e, actions, action_is_pad, layout=layout, **loss_kwargs)`.

        Args:
          observation: batch dict (its actions, if any, are ignored).
          actions: [B, H, A] normalized targets. action_is_pad: [B, H] bool.
          noise: [B, H, A]. time: [B] in (0, 1].
          loss_mask: [A] or [H, A], 0 on the dims that carry no loss (the constant dims), or None.
          **loss_kwargs: `strategy`, `group_weights`, ... of `training_loss`.
        Returns:
          (scalar loss over valid timesteps, {"group_loss": {group: scalar}}).
        """
        actions = as_tensor(actions).to(torch.float32)
        expected = (self.config.action_horizon, self.config.action_dim)
        if tuple(actions.shape[1:]) != expected:
            raise ValueError(f"actions have shape {tuple(actions.shape)}; the model expects "
                             f"[B, action_horizon={expected[0]}, action_dim={expected[1]}]")
        noise = as_tensor(noise).to(torch.float32)
        t = as_tensor(time).to(torch.float32)[:, None, None]
        x_t = t * noise + (1.0 - t) * actions
        v = self.velocity(observation, x_t, t[:, 0, 0])
        per_dim_loss = torch.square(v - (noise - actions))
        if loss_mask is not None:
            per_dim_loss = per_dim_loss * as_tensor(loss_mask).to(torch.float32)
        return loss_lib.training_loss(per_dim_loss, actions, as_tensor(action_is_pad).to(torch.bool),
                                      layout=layout, live=loss_mask, **loss_kwargs)

    @torch.no_grad()
    def sample_actions(self, observation: Mapping[str, Any], noise: Any, num_steps: int = 10, *,
                       use_kv_cache: bool = True) -> torch.Tensor:
        """Integrates the flow from t = 1 (x = noise [B, H, A]) to t = 0 with `num_steps` Euler steps.

        With `use_kv_cache` the prefix runs once and its keys / values are reused at every step;
        False recomputes the full forward each step (same result, for checking).
        Returns actions [B, H, A] float32 (normalized, padded like the training targets).
        """
        params = self.params()
        observation = preprocess_observation(observation, config=self.config)
        x_t = as_tensor(noise).to(torch.float32)
        batch_size = x_t.shape[0]
        if use_kv_cache:
            kv_cache, prefix_mask = self.prefix_kv_cache(params, observation)

            def flow(x, t):
                return self.cached_velocity(params, observation["state"], kv_cache, prefix_mask, x, t)
        else:
            def flow(x, t):
                return self.forward_velocity(params, observation, x, t)

        dt = torch.tensor(-1.0 / num_steps, dtype=torch.float32)
        t = torch.tensor(1.0, dtype=torch.float32)
        for _ in range(num_steps):
            x_t = x_t + dt * flow(x_t, t.broadcast_to(batch_size))
            t = t + dt
        return x_t
