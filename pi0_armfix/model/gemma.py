"""Gemma transformer with several experts that share every attention layer (linen).

Expert i has its own norms, projections and MLP; names of expert i > 0 carry the suffix `_i`
(openpi's naming: `q_einsum` / `q_einsum_1`). All experts' tokens are concatenated for one joint
attention per layer. Layers are one `nn.scan` over depth, so parameters are stacked on a leading
depth axis and compile time does not grow with depth.

Linen rather than NNX because `nn.scan` over a parameter-stacked block yields openpi's parameter
tree (`layers/attn/q_einsum/w` with shape [depth, ...]) directly as a plain nested dict.

Einsum axis names: B batch, T query length, S key length, N query heads, K kv heads,
G query heads per kv head, H head dim, D width.

LoRA (openpi's `gemma_2b_lora` / `gemma_300m_lora`, an expert's `lora_rank` > 0): every attention
and MLP weight of the expert gets two low-rank factors beside it, `lora_a` / `lora_b` (`<name>_lora_a`
/ `_lora_b` in the MLP), with openpi's shapes, equations and N(0, 0.01^2) init, and alpha = rank so
that the product is added unscaled. `training/freeze.py` decides which weights train.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from pi0_armfix.model.config import GemmaConfig

# Gemma's masked-logit value (finite, so fully masked rows stay NaN-free).
_BIG_NEG = -2.3819763e38
_ROPE_MAX_WAVELENGTH = 10_000
_LORA_INIT = nn.initializers.normal(stddev=0.01)  # openpi's LoRAConfig.init_fn, for both factors
_LORA_LABEL = "L"  # the rank's axis in the adapters' einsum equations
# Each weight's einsum, by parameter name (the MLP's as the einsums its dots are).
EQUATIONS = {"q_einsum": "BTD,NDH->BTNH", "kv_einsum": "BSD,2KDH->2BSKH",
             "attn_vec_einsum": "BTNH,NHD->BTD", "gating_einsum": "BTD,2DF->2BTF",
             "linear": "BTF,FD->BTD"}


def _name(name: str, expert: int) -> str:
    return name if expert == 0 else f"{name}_{expert}"


class RMSNorm(nn.Module):
    """`n = x * rsqrt(mean(x^2) + 1e-6)`, statistics in float32, output in x.dtype.

    Plain (cond None): `n * (1 + scale)`, a learned `scale` [D]; returns (out, None).
    Adaptive (pi0.5's adaRMS, cond [B, C] or per token [B, T, C]): `scale, shift, gate` are the
    three thirds of `Dense_0(cond)` ([C, 3D], zero-initialized kernel, so it starts as identity
    with gate 0); `n * (1 + scale) + shift`; returns (out, gate), the gate scaling the residual
    branch this norm feeds (`gated_residual`).
    """

    @nn.compact
    def __call__(self, x, cond=None):
        var = jnp.mean(jnp.square(x.astype(jnp.float32)), axis=-1, keepdims=True)
        normed = x * jnp.reciprocal(jnp.sqrt(var + 1e-6))
        if cond is None:
            scale = self.param("scale", nn.initializers.zeros_init(), (x.shape[-1],))
            return (normed * (1 + scale)).astype(x.dtype), None
        modulation = nn.Dense(3 * x.shape[-1], kernel_init=nn.initializers.zeros,
                              dtype=x.dtype)(cond)
        if modulation.ndim < x.ndim:  # one condition per sample, for every token
            modulation = modulation[:, None, :]
        scale, shift, gate = jnp.split(modulation, 3, axis=-1)
        return (normed * (1 + scale) + shift).astype(x.dtype), gate


def gated_residual(x, y, gate):
    """`x + y`, or `x + y * gate` after an adaptive norm; None for an absent expert."""
    if x is None:
        return None
    return x + y if gate is None else x + y * gate


class Embedder(nn.Module):
    """Token embedding table `input_embedding` [vocab, width]; lookups are scaled by sqrt(width)."""

    vocab_size: int
    width: int

    def setup(self):
        self.input_embedding = self.param(
            "input_embedding", nn.initializers.normal(), (self.vocab_size, self.width))

    def encode(self, tokens):
        """[B, L] int -> [B, L, width] float32."""
        return self.input_embedding[(tokens,)] * jnp.sqrt(self.width).astype(jnp.float32)


def is_adapter(name: str) -> bool:
    """Whether the parameter named `name` (the last key of its path) is a LoRA factor: `lora_a`,
    `lora_b` of an Einsum, `<name>_lora_a` / `_lora_b` of the MLP."""
    return "lora" in name


def lora_equations(eqn: str) -> tuple[str, str]:
    """An einsum `"x,w->y"` of a weight whose last two axes are (in, out) -> the equations of its
    adapters: `x, lora_a -> z` (the out axis replaced by the rank) and `z, lora_b -> y` (the in axis
    replaced by the rank), as openpi writes them."""
    match = re.fullmatch(r"(.*),(.*)->(.*)", eqn)
    if match is None or _LORA_LABEL in eqn:
        raise ValueError(f"einsum {eqn!r} has no 'x,w->y' form free of {_LORA_LABEL!r}")
    lhs, rhs, out = match.groups()
    in_label, out_label = rhs[-2], rhs[-1]
    low = out.replace(out_label, _LORA_LABEL)
    return (f"{lhs},{rhs.replace(out_label, _LORA_LABEL)}->{low}",
            f"{low},{rhs.replace(in_label, _LORA_LABEL)}->{out}")


def lora_delta(eqn: str, a: jax.Array, b: jax.Array) -> jax.Array:
    """The change of the weight that the adapters `a`, `b` of an einsum `eqn` make: `einsum(eqn,
    x, w + delta)` equals `x`'s path through `w` plus its path through the adapters. An axis of
    `b` that the first product drops (the heads of `attn_vec_einsum`) is summed over `b` alone,
    as the adapters' equations sum it. A leading axis beyond the equation's (the layers') is
    shared."""
    eqn_a, eqn_b = lora_equations(eqn)
    a_rhs, low = eqn_a.split(",")[1].split("->")
    b_rhs = eqn_b.split(",")[1].split("->")[0]
    rhs, out = eqn.split(",")[1].split("->")
    alone = iter(c for c in "MPQRUVWXY" if c not in eqn)
    b_rhs = "".join(c if c in low or c in out else next(alone) for c in b_rhs)
    lead = "Z" * (a.ndim - len(a_rhs))
    return jnp.einsum(f"{lead}{a_rhs},{lead}{b_rhs}->{lead}{rhs}", a, b)


def merge_lora(params: Mapping[str, Any]) -> dict[str, Any]:
    """`{"a/b/name": array}` with LoRA adapters -> the same function without them: every adapted
    weight plus its `lora_delta` (float32), the adapters dropped."""
    merged = {k: v for k, v in params.items() if not is_adapter(k.rpartition("/")[2])}
    for key in params:
        folder, _, leaf = key.rpartition("/")
        if not leaf.endswith("lora_a"):
            continue
        if leaf == "lora_a":  # an Einsum's: <name>/lora_a beside <name>/w
            weight, name = f"{folder}/w", folder.rpartition("/")[2]
        else:  # the MLP's: <name>_lora_a beside <name>
            weight = key.removesuffix("_lora_a")
            name = weight.rpartition("/")[2]
        eqn = EQUATIONS[re.sub(r"_\d+$", "", name)]
        delta = lora_delta(eqn, jnp.asarray(params[key], jnp.float32),
                           jnp.asarray(params[key[:-1] + "b"], jnp.float32))
        merged[weight] = jnp.asarray(params[weight], jnp.float32) + delta
    return merged


class Einsum(nn.Module):
    """One weight `w` of a fixed shape, applied with an einsum in the input's dtype; with
    `lora_rank` > 0 its adapters `lora_a` ([..., in, rank]) and `lora_b` ([..., rank, out]) add
    their product's einsum."""

    shape: tuple[int, ...]
    init_fn: nn.initializers.Initializer
    lora_rank: int = 0

    @nn.compact
    def __call__(self, eqn: str, x):
        w = self.param("w", self.init_fn, self.shape)
        y = jnp.einsum(eqn, x, w.astype(x.dtype))
        if self.lora_rank:
            a = self.param("lora_a", _LORA_INIT, (*self.shape[:-1], self.lora_rank))
            b = self.param("lora_b", _LORA_INIT, (*self.shape[:-2], self.lora_rank, self.shape[-1]))
            eqn_a, eqn_b = lora_equations(eqn)
            y = y + jnp.einsum(eqn_b, jnp.einsum(eqn_a, x, a.astype(x.dtype)), b.astype(x.dtype))
        return y


def apply_rope(x, positions):
    """Half-split rotary embedding, base 10_000. x [B, T, N, H], positions [B, T] -> like x."""
    head_dim = x.shape[-1]
    freq_exponents = (2.0 / head_dim) * jnp.arange(head_dim // 2, dtype=jnp.float32)
    timescale = _ROPE_MAX_WAVELENGTH**freq_exponents
    radians = positions[..., None] / timescale[None, None, :]
    radians = radians[..., None, :]  # [B, T, 1, H/2], broadcast over heads
    sin, cos = jnp.sin(radians), jnp.cos(radians)
    x1, x2 = jnp.split(x, 2, axis=-1)
    return jnp.concatenate([x1 * cos - x2 * sin, x2 * cos + x1 * sin], axis=-1).astype(x.dtype)


class Attention(nn.Module):
    """Joint grouped-query attention over the concatenated tokens of all present experts."""

    configs: Sequence[GemmaConfig]
    attention: str = "einsum"

    @nn.compact
    def __call__(self, xs, positions, attn_mask, kv_cache):
        """Args:
          xs: per expert [B, T_i, D_i] or None (expert absent in this call).
          positions: [B, T] int, T = sum of present T_i.
          attn_mask: [B, 1, T, S] bool, S = T + cached length.
          kv_cache: None or (k, v), each [B, S - T, K, H] (after RoPE).

        Returns:
          per expert [B, T_i, D_i] or None, and this call's (k, v) [B, S, K, H].
        """
        cfg = self.configs[0]
        dtype = next(x.dtype for x in xs if x is not None)
        qs, ks, vs = [], [], []
        for i, (x, config) in enumerate(zip(xs, self.configs)):
            if x is None:
                continue
            q = Einsum(
                shape=(config.num_heads, config.width, config.head_dim), name=_name("q_einsum", i),
                init_fn=nn.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=(0,)),
                lora_rank=config.lora_rank,
            )(EQUATIONS["q_einsum"], x)
            k, v = Einsum(
                shape=(2, config.num_kv_heads, config.width, config.head_dim),
                name=_name("kv_einsum", i),
                init_fn=nn.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=(0, 1)),
                lora_rank=config.lora_rank,
            )(EQUATIONS["kv_einsum"], x)
            qs.append(q), ks.append(k), vs.append(v)
        q, k, v = (jnp.concatenate(y, axis=1) for y in (qs, ks, vs))

        q = apply_rope(q, positions) * jnp.asarray(cfg.head_dim**-0.5, dtype)
        k = apply_rope(k, positions)
        if kv_cache is not None:
            k = jnp.concatenate([kv_cache[0], k], axis=1)
            v = jnp.concatenate([kv_cache[1], v], axis=1)

        batch, length = q.shape[:2]
        if self.attention == "fused":  # q is already scaled
            encoded = jax.nn.dot_product_attention(q, k, v, mask=attn_mask, scale=1.0)
        else:
            q = q.reshape(batch, length, cfg.num_kv_heads, cfg.num_heads // cfg.num_kv_heads,
                          cfg.head_dim)
            logits = jnp.einsum("BTKGH,BSKH->BKGTS", q, k, preferred_element_type=jnp.float32)
            logits = jnp.where(attn_mask[:, :, None, :, :], logits, _BIG_NEG)
            probs = jax.nn.softmax(logits, axis=-1).astype(dtype)
            encoded = jnp.einsum("BKGTS,BSKH->BTKGH", probs, v)
            encoded = encoded.reshape(batch, length, cfg.num_heads, cfg.head_dim)

        out, start = [], 0
        for i, (x, config) in enumerate(zip(xs, self.configs)):
            if x is None:
                out.append(None)
                continue
            end = start + x.shape[1]
            out.append(Einsum(
                shape=(config.num_heads, config.head_dim, config.width),
                name=_name("attn_vec_einsum", i),
                init_fn=nn.initializers.lecun_normal(in_axis=(-3, -2), out_axis=-1),
                lora_rank=config.lora_rank,
            )(EQUATIONS["attn_vec_einsum"], encoded[:, start:end]))
            start = end
        return out, (k, v)


class FeedForward(nn.Module):
    """Gated GELU: `(gelu_tanh(x @ gating[0]) * (x @ gating[1])) @ linear`; with `lora_rank` > 0
    each product adds its adapters' (`gating_einsum_lora_a` [2, D, r] / `_b` [2, r, F],
    `linear_lora_a` [F, r] / `_b` [r, D])."""

    width: int
    mlp_dim: int
    lora_rank: int = 0

    @nn.compact
    def __call__(self, x):
        gating = self.param(
            "gating_einsum", nn.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=(0,)),
            (2, self.width, self.mlp_dim))
        linear = self.param(
            "linear", nn.initializers.lecun_normal(in_axis=-2, out_axis=-1),
            (self.mlp_dim, self.width))
        adapters = [(None, None)] * 3
        if self.lora_rank:
            rank = self.lora_rank
            gate_a = self.param("gating_einsum_lora_a", _LORA_INIT, (2, self.width, rank))
            gate_b = self.param("gating_einsum_lora_b", _LORA_INIT, (2, rank, self.mlp_dim))
            adapters = [(gate_a[0], gate_b[0]), (gate_a[1], gate_b[1]),
                        (self.param("linear_lora_a", _LORA_INIT, (self.mlp_dim, rank)),
                         self.param("linear_lora_b", _LORA_INIT, (rank, self.width)))]

        def dot(y, w, adapter):
            out = jnp.dot(y, w.astype(y.dtype))
            a, b = adapter
            if a is not None:
                out = out + jnp.dot(jnp.dot(y, a.astype(y.dtype)), b.astype(y.dtype))
            return out

        hidden = (nn.gelu(dot(x, gating[0], adapters[0]), approximate=True)
                  * dot(x, gating[1], adapters[1]))
        return dot(hidden, linear, adapters[2])


class Block(nn.Module):
    """Pre-norm residual layer: joint attention, then each expert's own MLP. An expert with a
    condition (`conds[i]` not None) has adaptive norms and gated residuals."""

    configs: Sequence[GemmaConfig]
    attention: str = "einsum"

    @nn.compact
    def __call__(self, xs, kv_cache, positions, attn_mask, conds):
        normed, gates = [], []
        for i, (x, cond) in enumerate(zip(xs, conds)):
            y, gate = (None, None) if x is None else RMSNorm(name=_name("pre_attention_norm", i))(
                x, cond)
            normed.append(y), gates.append(gate)
        attended, kv_cache = Attention(self.configs, self.attention, name="attn")(
            normed, positions, attn_mask, kv_cache)
        xs = [gated_residual(x, y, gate) for x, y, gate in zip(xs, attended, gates)]
        out = []
        for i, (x, config, cond) in enumerate(zip(xs, self.configs, conds)):
            if x is not None:
                y, gate = RMSNorm(name=_name("pre_ffw_norm", i))(x, cond)
                x = gated_residual(x, FeedForward(config.width, config.mlp_dim, config.lora_rank,
                                                  name=_name("mlp", i))(y), gate)
            out.append(x)
        return out, kv_cache


class Transformer(nn.Module):
    """The `PaliGemma/llm` module: embedder of expert 0, scanned layers, one final norm per expert.

    Attributes:
      configs: one GemmaConfig per expert (equal depth / heads / head_dim).
      vocab_size: rows of the embedding table.
      dtype: activation dtype (params stay float32).
      remat: rematerialize each layer in the backward pass, keeping what this
        `jax.checkpoint_policies` policy names ("" = no rematerialization).
      attention: "einsum" or "fused" (`config.ATTENTION`).
      unroll: unroll the layer scan (for XLA's cost analysis, which counts a loop body once).
      adaptive: per expert, whether its norms are adaptive (pi0.5's action expert): such an
        expert takes a condition in every call.
    """

    configs: Sequence[GemmaConfig]
    vocab_size: int
    dtype: str
    remat: str
    unroll: bool = False
    adaptive: Sequence[bool] = (False, False)
    attention: str = "einsum"

    def setup(self):
        self.embedder = Embedder(self.vocab_size, self.configs[0].width, name="embedder")
        block = Block
        if self.remat:
            block = nn.remat(Block, prevent_cse=False,
                             policy=getattr(jax.checkpoint_policies, self.remat))
        self.layers = nn.scan(
            block, variable_axes={"params": 0}, split_rngs={"params": True},
            in_axes=(0, nn.broadcast, nn.broadcast, nn.broadcast), length=self.configs[0].depth,
            unroll=self.configs[0].depth if self.unroll else 1,
        )(self.configs, self.attention, name="layers")
        self.final_norms = [RMSNorm(name=_name("final_norm", i)) for i in range(len(self.configs))]

    def embed(self, tokens):
        """[B, L] int -> [B, L, D_0] in `dtype`."""
        return self.embedder.encode(tokens).astype(self.dtype)

    def __call__(self, xs, positions, attn_mask, kv_cache=None, cond=None):
        """Runs all layers.

        Args:
          xs: per expert [B, T_i, D_i] or None.
          positions: [B, T] int.
          attn_mask: [B, T, S] bool (S = T + cached length).
          kv_cache: None, or (k, v) each [depth, B, S - T, K, H] from a previous call.
          cond: the condition of the adaptive experts present in this call, [B, C] (or per token
            [B, T_i, C]); None when no adaptive expert is present.

        Returns:
          per expert final-normed outputs [B, T_i, D_i] (or None), and the (k, v) of this call,
          each [depth, B, S, K, H].
        """
        xs = [None if x is None else x.astype(self.dtype) for x in xs]
        conditioned = [adaptive and x is not None for x, adaptive in zip(xs, self.adaptive)]
        if any(conditioned) and cond is None:
            raise ValueError("an adaptive (pi0.5) expert needs its condition: pass cond")
        conds = [cond if c else None for c in conditioned]
        xs, kv_cache = self.layers(xs, kv_cache, positions, attn_mask[:, None], conds)
        return [None if x is None else norm(x, c)[0]
                for norm, x, c in zip(self.final_norms, xs, conds)], kv_cache

    def initialize(self):
        """Touches every parameter (for `init` / `eval_shape`)."""
        self.embed(jnp.zeros((1, 1), jnp.int32))
        xs = [jnp.zeros((1, 1, c.width), self.dtype) for c in self.configs]
        length = len(self.configs)
        # Adaptive experts are conditioned on a vector of their own width (the time embedding).
        widths = [c.width for c, adaptive in zip(self.configs, self.adaptive) if adaptive]
        cond = jnp.zeros((1, widths[0]), self.dtype) if widths else None
        self(xs, jnp.zeros((1, length), jnp.int32), jnp.ones((1, length, length), bool), cond=cond)
