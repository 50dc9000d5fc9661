"""Parameter names and shapes of the PyTorch mirror, and the one mapping from openpi's names.

The mirror keeps openpi's parameter tree as it is: the same arrays, the same shapes (flax layouts:
Dense kernels `[in, out]`, einsum weights as in `pi0_armfix/model/gemma.py`, the patch conv as
`[ph, pw, 3, width]`), layer weights still stacked on their leading depth axis. Only the separator
changes, because torch joins module paths with "." and flax with "/":

    openpi  "PaliGemma/llm/layers/attn/q_einsum/w"  [depth, N, W, Dh]
    torch   "PaliGemma.llm.layers.attn.q_einsum.w"  [depth, N, W, Dh]

so conversion never transposes or splits an array and the mapping is its own inverse
(`torch_name` / `openpi_name`). `param_shapes(config)` lists every parameter a config implies,
without JAX, and `check_state_dict` is the strict key check used by conversion and loading.
"""

from __future__ import annotations

from collections.abc import Mapping

from pi0_armfix.model.config import GemmaConfig, Pi0Config, dense_shapes

def torch_name(openpi_path: str) -> str:
    """"PaliGemma/llm/final_norm/scale" -> "PaliGemma.llm.final_norm.scale"."""
    if "." in openpi_path:
        raise ValueError(f"parameter name {openpi_path!r} contains '.', which torch reserves "
                         "for module paths")
    return openpi_path.replace("/", ".")


def openpi_name(torch_key: str) -> str:
    """Inverse of `torch_name`."""
    return torch_key.replace(".", "/")


def _suffix(name: str, expert: int) -> str:
    return name if expert == 0 else f"{name}_{expert}"


def _norm_shapes(name: str, width: int, adaptive: bool) -> dict[str, tuple[int, ...]]:
    """A plain RMSNorm's `scale`, or an adaptive one's `Dense_0` (condition of the same width)."""
    if adaptive:
        return {f"{name}/Dense_0/kernel": (width, 3 * width), f"{name}/Dense_0/bias": (3 * width,)}
    return {f"{name}/scale": (width,)}


def _gemma_shapes(config: Pi0Config) -> dict[str, tuple[int, ...]]:
    experts: tuple[GemmaConfig, ...] = (config.paligemma, config.action_expert)
    depth = config.paligemma.depth
    shapes = {"embedder/input_embedding": (config.vocab_size, config.paligemma.width)}
    for i, c in enumerate(experts):
        adaptive = config.pi05 and i == 1  # pi0.5's action expert
        layer = {
            f"attn/{_suffix('q_einsum', i)}/w": (c.num_heads, c.width, c.head_dim),
            f"attn/{_suffix('kv_einsum', i)}/w": (2, c.num_kv_heads, c.width, c.head_dim),
            f"attn/{_suffix('attn_vec_einsum', i)}/w": (c.num_heads, c.head_dim, c.width),
            f"{_suffix('mlp', i)}/gating_einsum": (2, c.width, c.mlp_dim),
            f"{_suffix('mlp', i)}/linear": (c.mlp_dim, c.width),
            **_norm_shapes(_suffix("pre_attention_norm", i), c.width, adaptive),
            **_norm_shapes(_suffix("pre_ffw_norm", i), c.width, adaptive),
        }
        shapes.update({f"layers/{name}": (depth, *shape) for name, shape in layer.items()})
        shapes.update(_norm_shapes(_suffix("final_norm", i), c.width, adaptive))
    return {f"PaliGemma/llm/{name}": shape for name, shape in shapes.items()}


def _siglip_shapes(config: Pi0Config) -> dict[str, tuple[int, ...]]:
    s = config.siglip
    heads, head_dim = s.num_heads, s.width // s.num_heads
    block = {
        "LayerNorm_0/scale": (s.width,), "LayerNorm_0/bias": (s.width,),
        "LayerNorm_1/scale": (s.width,), "LayerNorm_1/bias": (s.width,),
        "MlpBlock_0/Dense_0/kernel": (s.width, s.mlp_dim), "MlpBlock_0/Dense_0/bias": (s.mlp_dim,),
        "MlpBlock_0/Dense_1/kernel": (s.mlp_dim, s.width), "MlpBlock_0/Dense_1/bias": (s.width,),
        "MultiHeadDotProductAttention_0/out/kernel": (heads, head_dim, s.width),
        "MultiHeadDotProductAttention_0/out/bias": (s.width,),
    }
    for proj in ("query", "key", "value"):
        block[f"MultiHeadDotProductAttention_0/{proj}/kernel"] = (s.width, heads, head_dim)
        block[f"MultiHeadDotProductAttention_0/{proj}/bias"] = (heads, head_dim)
    shapes = {f"Transformer/encoderblock/{name}": (s.depth, *shape) for name, shape in block.items()}
    shapes.update({
        "Transformer/encoder_norm/scale": (s.width,),
        "Transformer/encoder_norm/bias": (s.width,),
        "embedding/kernel": (s.patch_size >> s.conv_stem, s.patch_size >> s.conv_stem,
                             s.width if s.conv_stem else 3, s.width),
        "embedding/bias": (s.width,),
        "pos_embedding": (1, config.num_image_tokens, s.width),
        "head/kernel": (s.width, config.paligemma.width),
        "head/bias": (config.paligemma.width,),
    })
    channels = 3
    for i in range(s.conv_stem):
        out = s.width // 2 ** (s.conv_stem - 1 - i)
        shapes.update({f"stem_{i}/kernel": (3, 3, channels, out), f"stem_{i}/bias": (out,)})
        channels = out
    return {f"PaliGemma/img/{name}": shape for name, shape in shapes.items()}


def param_shapes(config: Pi0Config) -> dict[str, tuple[int, ...]]:
    """Every parameter of a model built from `config`: {openpi flattened name: shape}, sorted."""
    shapes = {**_gemma_shapes(config), **_siglip_shapes(config)}
    for name, (fan_in, fan_out) in dense_shapes(config).items():
        shapes[f"{name}/kernel"] = (fan_in, fan_out)
        shapes[f"{name}/bias"] = (fan_out,)
    return dict(sorted(shapes.items()))


class ParameterMismatchError(ValueError):
    """A parameter set does not fit the model: names missing, unexpected or of the wrong shape."""


def check_state_dict(shapes: Mapping[str, tuple[int, ...]], expected: Mapping[str, tuple[int, ...]],
                     *, source: str) -> None:
    """Strict key check of torch-named `shapes` against `expected` (both {torch name: shape}).

    Raises:
      ParameterMismatchError listing every missing, unexpected and mis-shaped name, with `source`
      (the file or folder the parameters came from).
    """
    missing = sorted(set(expected) - set(shapes))
    unexpected = sorted(set(shapes) - set(expected))
    mis_shaped = sorted(f"{name}: {tuple(shapes[name])} != expected {tuple(expected[name])}"
                        for name in set(shapes) & set(expected)
                        if tuple(shapes[name]) != tuple(expected[name]))
    if missing or unexpected or mis_shaped:
        lines = [f"parameters from {source} do not match the model config:"]
        for title, names in (("missing", missing), ("unexpected", unexpected),
                             ("mis-shaped", mis_shaped)):
            if names:
                lines.append(f"  {title} ({len(names)}): " + ", ".join(names))
        raise ParameterMismatchError("\n".join(lines))
