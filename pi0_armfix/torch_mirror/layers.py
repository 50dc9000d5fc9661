"""The towers of pi0 as pure torch functions over nested dicts of tensors (openpi names).

A line-for-line mirror of `pi0_armfix/model/{gemma,siglip}.py`; the computation is specified in
the docstring of `pi0_armfix/model/__init__.py`. Weights keep their flax layouts (see
`params.py`), so every matmul is the same einsum as on the JAX side. Parameters are float32 and are
cast to the activation dtype at each matmul; norm statistics and Gemma's attention logits and
softmax run in float32.

Einsum axis names: B batch, T query length, S key length, N query heads, K kv heads,
G query heads per kv head, H head dim, D width.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F

from pi0_armfix.model.config import GemmaConfig, SiglipConfig

Params = Mapping[str, Any]
KVCache = tuple[torch.Tensor, torch.Tensor]

# Gemma's masked-logit value (finite, so fully masked rows stay NaN-free).
_BIG_NEG = -2.3819763e38
_ROPE_MAX_WAVELENGTH = 10_000
_RMS_EPS = 1e-6
_LAYER_NORM_EPS = 1e-6


def _f32(value: float) -> torch.Tensor:
    return torch.tensor(value, dtype=torch.float32)


def dense(params: Params, x: torch.Tensor) -> torch.Tensor:
    """x [..., in] @ kernel [in, out] + bias, in x's dtype (flax `nn.Dense(dtype=x.dtype)`)."""
    return x @ params["kernel"].to(x.dtype) + params["bias"].to(x.dtype)


def gelu_tanh(x: torch.Tensor) -> torch.Tensor:
    """flax `nn.gelu(approximate=True)`."""
    return F.gelu(x, approximate="tanh")


def layer_norm(params: Params, x: torch.Tensor) -> torch.Tensor:
    """flax `nn.LayerNorm` (eps 1e-6, fast variance E[x^2] - E[x]^2 in float32), output in x.dtype."""
    x32 = x.to(torch.float32)
    mean = x32.mean(-1, keepdim=True)
    var = torch.clamp(torch.square(x32).mean(-1, keepdim=True) - torch.square(mean), min=0.0)
    mul = torch.rsqrt(var + _LAYER_NORM_EPS) * params["scale"]
    return ((x32 - mean) * mul + params["bias"]).to(x.dtype)


def rms_norm(params: Params, x: torch.Tensor, cond: torch.Tensor | None = None
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """`n = x * rsqrt(mean(x^2) + 1e-6)` (statistics in float32) -> (out in x.dtype, gate).

    Plain (cond None): `n * (1 + scale)`, gate None. Adaptive (pi0.5, cond [B, C] or [B, T, C]):
    `scale, shift, gate` = thirds of `Dense_0(cond)` in x's dtype, `n * (1 + scale) + shift`.
    """
    var = torch.square(x.to(torch.float32)).mean(-1, keepdim=True)
    normed = x * torch.reciprocal(torch.sqrt(var + _RMS_EPS))
    if cond is None:
        return (normed * (1 + params["scale"])).to(x.dtype), None
    modulation = dense(params["Dense_0"], cond.to(x.dtype))
    if modulation.ndim < x.ndim:  # one condition per sample, for every token
        modulation = modulation[:, None, :]
    scale, shift, gate = torch.chunk(modulation, 3, dim=-1)
    return (normed * (1 + scale) + shift).to(x.dtype), gate


def gated_residual(x: torch.Tensor | None, y: torch.Tensor | None, gate: torch.Tensor | None
                   ) -> torch.Tensor | None:
    """`x + y`, or `x + y * gate` after an adaptive norm; None for an absent expert."""
    if x is None:
        return None
    return x + y if gate is None else x + y * gate


# ------------------------------------------------------------------------------------------ SigLIP


def _siglip_attention(params: Params, x: torch.Tensor) -> torch.Tensor:
    """flax `MultiHeadDotProductAttention` self-attention: x [B, T, D] -> [B, T, D]."""
    dtype = x.dtype
    q, k, v = (torch.einsum("btd,dnh->btnh", x, params[name]["kernel"].to(dtype))
               + params[name]["bias"].to(dtype) for name in ("query", "key", "value"))
    q = q / torch.sqrt(_f32(q.shape[-1])).to(dtype)
    # flax's softmax runs in the activation dtype here (unlike Gemma's float32 logits).
    probs = torch.softmax(torch.einsum("bqnh,bknh->bnqk", q, k), dim=-1)
    encoded = torch.einsum("bnqk,bknh->bqnh", probs, v)
    out = params["out"]
    return torch.einsum("btnh,nhd->btd", encoded, out["kernel"].to(dtype)) + out["bias"].to(dtype)


def siglip(params: Params, image: torch.Tensor, *, config: SiglipConfig, dtype: torch.dtype
           ) -> torch.Tensor:
    """The `PaliGemma/img` tower: image [B, h, w, 3] in [-1, 1] -> tokens [B, n, out_width] in dtype.

    The stem (`conv_stem` stride-2 3x3 convolutions with ReLU, then a conv with kernel = stride =
    the remaining patch, VALID) and the position embedding run in float32; tokens are row-major
    over the (h / p, w / p) patch grid.
    """
    x = image.to(torch.float32)
    for i in range(config.conv_stem):
        conv = params[f"stem_{i}"]
        # flax's SAME at stride 2 on an even side pads one pixel after, none before.
        y = F.pad(x.permute(0, 3, 1, 2), (0, 1, 0, 1))
        y = F.conv2d(y, conv["kernel"].permute(3, 2, 0, 1), conv["bias"], stride=2)
        x = torch.relu(y).permute(0, 2, 3, 1)
    patch = config.patch_size >> config.conv_stem
    batch, height, width, channels = x.shape
    grid_h, grid_w = height // patch, width // patch
    patches = x.reshape(batch, grid_h, patch, grid_w, patch, channels)
    stem = params["embedding"]
    x = torch.einsum("biyjxc,yxcd->bijd", patches, stem["kernel"]) + stem["bias"]
    x = x.reshape(batch, grid_h * grid_w, -1) + params["pos_embedding"]
    x = x.to(dtype)
    blocks = params["Transformer"]["encoderblock"]
    for layer in range(config.depth):
        block = _layer(blocks, layer)
        x = x + _siglip_attention(block["MultiHeadDotProductAttention_0"],
                                  layer_norm(block["LayerNorm_0"], x))
        mlp = block["MlpBlock_0"]
        y = layer_norm(block["LayerNorm_1"], x)
        x = x + dense(mlp["Dense_1"], gelu_tanh(dense(mlp["Dense_0"], y)))
    x = layer_norm(params["Transformer"]["encoder_norm"], x)
    return dense(params["head"], x)


def _layer(tree: Params, index: int) -> dict[str, Any]:
    """The `index`-th slice of a depth-stacked parameter subtree."""
    return {k: _layer(v, index) if isinstance(v, Mapping) else v[index] for k, v in tree.items()}


# ------------------------------------------------------------------------------------------- Gemma


def _name(name: str, expert: int) -> str:
    return name if expert == 0 else f"{name}_{expert}"


def embed_tokens(params: Params, tokens: torch.Tensor, *, dtype: torch.dtype) -> torch.Tensor:
    """The `PaliGemma/llm` embedder: tokens [B, L] int -> [B, L, D_0] (scaled by sqrt(D_0)) in dtype."""
    table = params["embedder"]["input_embedding"]
    scale = torch.sqrt(_f32(table.shape[1]))
    return (table[tokens.long()] * scale).to(dtype)


def apply_rope(x: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Half-split rotary embedding, base 10_000. x [B, T, N, H], positions [B, T] -> like x."""
    head_dim = x.shape[-1]
    freq_exponents = _f32(2.0 / head_dim) * torch.arange(head_dim // 2, dtype=torch.float32)
    timescale = _f32(_ROPE_MAX_WAVELENGTH) ** freq_exponents
    radians = positions.to(torch.float32)[..., None] / timescale[None, None, :]
    radians = radians[..., None, :]  # [B, T, 1, H/2], broadcast over heads
    sin, cos = torch.sin(radians), torch.cos(radians)
    x1, x2 = torch.chunk(x, 2, dim=-1)
    return torch.cat([x1 * cos - x2 * sin, x2 * cos + x1 * sin], dim=-1).to(x.dtype)


def _attention(params: Params, xs: Sequence[torch.Tensor | None], positions: torch.Tensor,
               attn_mask: torch.Tensor, kv_cache: KVCache | None, configs: Sequence[GemmaConfig]
               ) -> tuple[list[torch.Tensor | None], KVCache]:
    """Joint grouped-query attention of one layer over all present experts' tokens.

    Args:
      params: the layer's `attn` subtree (one layer, not stacked).
      xs: per expert [B, T_i, D_i] or None. positions: [B, T]. attn_mask: [B, T, S] bool.
      kv_cache: None, or this layer's cached (k, v), each [B, S - T, K, H] (after RoPE).
    Returns:
      per expert [B, T_i, D_i] or None, and the layer's (k, v) [B, S, K, H].
    """
    cfg = configs[0]
    dtype = next(x.dtype for x in xs if x is not None)
    qs, ks, vs = [], [], []
    for i, x in enumerate(xs):
        if x is None:
            continue
        qs.append(torch.einsum("btd,ndh->btnh", x, params[_name("q_einsum", i)]["w"].to(dtype)))
        k, v = torch.einsum("bsd,ckdh->cbskh", x, params[_name("kv_einsum", i)]["w"].to(dtype))
        ks.append(k), vs.append(v)
    q, k, v = (torch.cat(y, dim=1) for y in (qs, ks, vs))

    q = apply_rope(q, positions) * _f32(cfg.head_dim**-0.5).to(dtype)
    k = apply_rope(k, positions)
    if kv_cache is not None:
        k = torch.cat([kv_cache[0], k], dim=1)
        v = torch.cat([kv_cache[1], v], dim=1)

    batch, length = q.shape[:2]
    q = q.reshape(batch, length, cfg.num_kv_heads, cfg.num_heads // cfg.num_kv_heads, cfg.head_dim)
    logits = torch.einsum("btkgh,bskh->bkgts", q.to(torch.float32), k.to(torch.float32))
    logits = torch.where(attn_mask[:, None, None, :, :], logits, _f32(_BIG_NEG))
    probs = torch.softmax(logits, dim=-1).to(dtype)
    encoded = torch.einsum("bkgts,bskh->btkgh", probs, v)
    encoded = encoded.reshape(batch, length, cfg.num_heads, cfg.head_dim)

    out, start = [], 0
    for i, x in enumerate(xs):
        if x is None:
            out.append(None)
            continue
        end = start + x.shape[1]
        w = params[_name("attn_vec_einsum", i)]["w"].to(dtype)
        out.append(torch.einsum("btnh,nhd->btd", encoded[:, start:end], w))
        start = end
    return out, (k, v)


def _feed_forward(params: Params, x: torch.Tensor) -> torch.Tensor:
    """Gated GELU: `(gelu_tanh(x @ gating[0]) * (x @ gating[1])) @ linear`."""
    gating = params["gating_einsum"].to(x.dtype)
    hidden = gelu_tanh(x @ gating[0]) * (x @ gating[1])
    return hidden @ params["linear"].to(x.dtype)


def transformer(params: Params, xs: Sequence[torch.Tensor | None], positions: torch.Tensor,
                attn_mask: torch.Tensor, kv_cache: KVCache | None = None, *,
                configs: Sequence[GemmaConfig], dtype: torch.dtype,
                cond: torch.Tensor | None = None, adaptive: Sequence[bool] = (False, False)
                ) -> tuple[list[torch.Tensor | None], KVCache]:
    """The `PaliGemma/llm` layers and final norms (experts share every attention layer).

    Args:
      params: the `PaliGemma/llm` subtree (layer weights stacked on a leading depth axis).
      xs: per expert [B, T_i, D_i] or None (expert absent in this call).
      positions: [B, T] int, T = sum of present T_i.
      attn_mask: [B, T, S] bool, S = T + cached length.
      kv_cache: None, or (k, v) each [depth, B, S - T, K, H] from a previous call.
      cond: the condition of the adaptive experts present (pi0.5's time embedding), or None.
      adaptive: per expert, whether its norms are adaptive.
    Returns:
      per expert final-normed outputs [B, T_i, D_i] (or None), and this call's (k, v), each
      [depth, B, S, K, H].
    """
    xs = [None if x is None else x.to(dtype) for x in xs]
    conds = [cond if a and x is not None else None for x, a in zip(xs, adaptive)]
    keys, values = [], []
    for layer in range(configs[0].depth):
        p = _layer(params["layers"], layer)
        normed, gates = [], []
        for i, (x, c) in enumerate(zip(xs, conds)):
            y, gate = (None, None) if x is None else rms_norm(p[_name("pre_attention_norm", i)], x, c)
            normed.append(y), gates.append(gate)
        cache = None if kv_cache is None else (kv_cache[0][layer], kv_cache[1][layer])
        attended, (k, v) = _attention(p["attn"], normed, positions, attn_mask, cache, configs)
        keys.append(k), values.append(v)
        xs = [gated_residual(x, y, gate) for x, y, gate in zip(xs, attended, gates)]
        for i, (x, c) in enumerate(zip(xs, conds)):
            if x is not None:
                y, gate = rms_norm(p[_name("pre_ffw_norm", i)], x, c)
                xs[i] = gated_residual(x, _feed_forward(p[_name("mlp", i)], y), gate)
    outs = [None if x is None else rms_norm(params[_name("final_norm", i)], x, c)[0]
            for i, (x, c) in enumerate(zip(xs, conds))]
    return outs, (torch.stack(keys), torch.stack(values))
