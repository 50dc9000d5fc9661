"""SigLIP vision tower (big_vision ViT, no pooling) as used by PaliGemma / openpi's pi0 (linen).

Parameter names follow big_vision: `embedding` (patch conv), `pos_embedding`,
`Transformer/encoderblock/...` (scanned over depth, stacked on a leading axis),
`Transformer/encoder_norm`, `head` (linear map to the language model's width).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from pi0_armfix.model.config import SiglipConfig


class MlpBlock(nn.Module):
    """Dense -> gelu (tanh approximation) -> Dense."""

    mlp_dim: int
    dtype: str

    @nn.compact
    def __call__(self, x):
        inits = dict(kernel_init=nn.initializers.xavier_uniform(),
                     bias_init=nn.initializers.normal(stddev=1e-6))
        width = x.shape[-1]
        x = nn.Dense(self.mlp_dim, dtype=self.dtype, **inits)(x)
        x = nn.gelu(x, approximate=True)
        return nn.Dense(width, dtype=self.dtype, **inits)(x)


class Encoder1DBlock(nn.Module):
    """Pre-LayerNorm residual block: self-attention, then MLP. A scan body: returns (x, None)."""

    mlp_dim: int
    num_heads: int
    dtype: str

    @nn.compact
    def __call__(self, x, _):
        y = nn.LayerNorm(dtype=self.dtype)(x)
        y = nn.MultiHeadDotProductAttention(
            num_heads=self.num_heads, kernel_init=nn.initializers.xavier_uniform(),
            deterministic=True, dtype=self.dtype)(y, y)
        x = x + y
        y = nn.LayerNorm(dtype=self.dtype)(x)
        x = x + MlpBlock(self.mlp_dim, self.dtype)(y)
        return x, None


class Encoder(nn.Module):
    """`depth` blocks in one scan, then `encoder_norm`."""

    config: SiglipConfig
    dtype: str
    remat: str
    unroll: bool = False

    @nn.compact
    def __call__(self, x):
        block = Encoder1DBlock
        if self.remat:
            block = nn.remat(block, prevent_cse=False,
                             policy=getattr(jax.checkpoint_policies, self.remat))
        x, _ = nn.scan(
            block, variable_axes={"params": 0}, split_rngs={"params": True},
            in_axes=nn.broadcast, length=self.config.depth,
            unroll=self.config.depth if self.unroll else 1,
        )(self.config.mlp_dim, self.config.num_heads, self.dtype, name="encoderblock")(x, None)
        return nn.LayerNorm(name="encoder_norm", dtype=self.dtype)(x)


class SigLIP(nn.Module):
    """Image [B, h, w, 3] in [-1, 1] -> tokens [B, (h/p) * (w/p), out_width] in `dtype`.

    Attributes:
      config: tower sizes.
      num_patches: (h/p) * (w/p), the length of the learned position embedding.
      out_width: width of the `head` projection (the language model's width).
      dtype: matmul / activation dtype of the encoder; the patch stem stays float32.
      remat: rematerialize each block in the backward pass, keeping what this
        `jax.checkpoint_policies` policy names ("" = no rematerialization).
      unroll: unroll the block scan (for XLA's cost analysis, which counts a loop body once).
    """

    config: SiglipConfig
    num_patches: int
    out_width: int
    dtype: str
    remat: str
    unroll: bool = False

    @nn.compact
    def __call__(self, image):
        x = jnp.asarray(image, jnp.float32)
        stem = self.config.conv_stem
        for i in range(stem):  # channels doubling up to the width: width / 2**(stem-1), ...
            x = nn.relu(nn.Conv(self.config.width // 2 ** (stem - 1 - i), (3, 3), strides=2,
                                name=f"stem_{i}", dtype=jnp.float32)(x))
        patch = self.config.patch_size // 2 ** stem
        x = nn.Conv(self.config.width, (patch, patch), strides=(patch, patch), padding="VALID",
                    name="embedding", dtype=jnp.float32)(x)
        batch, h, w, width = x.shape
        x = x.reshape(batch, h * w, width)
        x = x + self.param("pos_embedding", nn.initializers.normal(stddev=1 / np.sqrt(width)),
                           (1, self.num_patches, width), jnp.float32)
        x = Encoder(self.config, self.dtype, self.remat, self.unroll, name="Transformer")(
            x.astype(self.dtype))
        # DEVIATION from openpi (zero init): a zero head would make a from-scratch model blind.
        return nn.Dense(self.out_width, dtype=self.dtype, name="head")(x)
