"""Model configuration: frozen dataclasses and the pi0 / pi0.5 presets.

The config is the only knob of the model. The `pi0` preset reproduces openpi's pi0 (PaliGemma =
SigLIP So400m/14 + Gemma 2B, action expert = Gemma 300M) so that its parameter tree equals
`tests/reference/openpi_param_tree.json["pi0"]`; `demo` trains on a laptop CPU; `tiny` is for unit
tests. `pi05`, `pi05_demo` and `pi05_tiny` are the same sizes as pi0.5 (`Pi0Config.pi05`; tree
`openpi_param_tree.json["pi05"]`). Every preset of a model uses the same parameter names, only
the sizes differ.

`Pi0Config.to_dict()` / `Pi0Config.from_dict()` round-trip through JSON (the PyTorch mirror's
`config.json`); `from_model_config(config.model)` builds one from the training config section.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

# The three camera slots of pi0 (openpi's IMAGE_KEYS); a key containing "wrist" is a wrist camera.
IMAGE_KEYS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
# PaliGemma's sentencepiece vocabulary (openpi's PALIGEMMA_VOCAB_SIZE).
PALIGEMMA_VOCAB_SIZE = 257_152
DTYPES = ("float32", "bfloat16")
# What a rematerialized layer keeps for the backward pass (`jax.checkpoint_policies` by name):
# nothing (the least memory), or the outputs of its matrix products (less recompute).
REMAT_POLICIES = ("nothing_saveable", "dots_with_no_batch_dims_saveable", "dots_saveable")
# The attention's inner product: XLA's einsums and softmax, or `jax.nn.dot_product_attention`
# without `implementation=`, which JAX 0.10.2 always runs as its XLA implementation (its cuDNN
# kernel must be asked for, and takes padding and causal masks natively, pi0's prefix-LM mask
# only as a bias; not wired, unmeasured: docs/gpu.md).
ATTENTION = ("einsum", "fused")
# openpi's LoRA variants by expert: gemma_2b_lora (rank 16) for the prefix, gemma_300m_lora (rank 32)
# for the action expert; both with alpha = rank, on every attention and MLP weight.
LORA_RANKS = {"paligemma": 16, "action_expert": 32}


@dataclasses.dataclass(frozen=True)
class GemmaConfig:
    """One expert of the Gemma transformer (attention is shared across experts, MLPs are not).

    `lora_rank` > 0 gives every attention and MLP weight of the expert LoRA adapters of that rank
    (`gemma.py`); 0 = none."""

    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    num_kv_heads: int
    head_dim: int
    lora_rank: int = 0


@dataclasses.dataclass(frozen=True)
class SiglipConfig:
    """The SigLIP ViT image encoder (no pooling; a linear head maps to the prefix width).

    `conv_stem` = n > 0 puts n stride-2 3x3 convolutions (ReLU) before the patch embedding, which
    then covers `patch_size / 2**n` of their pixels, so the tokens stay one per patch: a ViT with
    early convolutions, the demo's learning-efficiency variant (RESULTS.md). 0 is SigLIP's own
    stem (every pi0 / pi0.5 preset: openpi's parameter tree)."""

    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    patch_size: int
    conv_stem: int = 0


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
    """Train-time image augmentation, openpi's `preprocess_observation` (augmax) semantics.

    Non-wrist cameras: a random crop resized back and a rotation, fused into one bilinear
    resample (black outside). Every camera: augmax's `ColorJitter` in HSV, applied to an image
    with probability `jitter_p` (else the image is left as it is).

    Attributes:
      crop_scale: side of the random crop as a fraction of the image side; 1.0 disables cropping.
      rotate_degrees: rotation angle drawn uniformly from [-rotate_degrees, rotate_degrees].
      brightness: value shift, uniform in [-b, b].
      contrast: c uniform in [-c, c]; value -> (value - 0.5) * tan((c + 1) pi / 4) + 0.5.
      saturation: saturation shift, uniform in [-s, s], clipped to [0, 1].
      hue: hue shift (a fraction of the colour circle), uniform in [-h, h].
      jitter_p: probability that an image is colour-jittered at all.
    """

    crop_scale: float = 0.95
    rotate_degrees: float = 5.0
    brightness: float = 0.3
    contrast: float = 0.4
    saturation: float = 0.5
    hue: float = 0.1
    jitter_p: float = 0.5


@dataclasses.dataclass(frozen=True)
class Pi0Config:
    """Sizes and numerics of a pi0 model.

    Attributes:
      paligemma: the prefix expert (image + language tokens); its width is the token width of the
        vision head and of the text embedding.
      action_expert: the suffix expert (state token + action tokens). Shares depth, num_heads,
        num_kv_heads and head_dim with `paligemma` (attention is joint).
      siglip: the vision tower.
      vocab_size: rows of the token embedding table.
      action_dim: padded action / state width.
      action_horizon: H, action tokens per chunk.
      max_token_len: L, prompt tokens (padded / truncated).
      image_resolution: (height, width) the cameras are resized (with padding) to.
      image_keys: camera slots, in token order.
      dtype: activation dtype, "float32" or "bfloat16". Parameters are always float32.
      remat: rematerialize each scanned layer in the backward pass (saves activation memory).
      remat_policy: what a rematerialized layer keeps (`REMAT_POLICIES`).
      attention: how the Gemma layers compute attention (`ATTENTION`); the same function.
      pi05: pi0.5 instead of pi0: no state token (the state is written into the prompt, see
        `tokenizer`), the flow time conditions every action-expert norm through adaptive RMSNorm
        (`time_mlp_in -> swish -> time_mlp_out -> swish`), and the data default is quantile
        normalization.
      unroll_layers: unroll the layer scans in the compiled program (same params and results).
        XLA's cost analysis counts a loop body once, so FLOP counts need the unrolled program.
      augment: train-time augmentation.
      use_state: False feeds the model a zero state, in training and sampling (the no-state
        ablation: the policy must read everything from the cameras and the prompt).
      state_dropout: probability, per training sample, that the state is replaced by zeros (the
        normalized mean state), so the policy cannot rely on copying it.
      state_noise: std of Gaussian noise added to the normalized state in training, targets
        unchanged (DART-style: the policy learns to act from states a little off the
        demonstrations, as its own mistakes put it in closed loop).
    """

    paligemma: GemmaConfig
    action_expert: GemmaConfig
    siglip: SiglipConfig
    vocab_size: int = PALIGEMMA_VOCAB_SIZE
    action_dim: int = 32
    action_horizon: int = 50
    max_token_len: int = 48
    image_resolution: tuple[int, int] = (224, 224)
    image_keys: tuple[str, ...] = IMAGE_KEYS
    dtype: str = "bfloat16"
    remat: bool = True
    remat_policy: str = "nothing_saveable"
    attention: str = "einsum"
    pi05: bool = False
    unroll_layers: bool = False
    augment: AugmentConfig = AugmentConfig()
    use_state: bool = True
    state_dropout: float = 0.0
    state_noise: float = 0.0

    @property
    def perturbs_state(self) -> bool:
        """Whether the state the model sees differs from the batch's."""
        return not self.use_state or self.state_dropout > 0.0 or self.state_noise > 0.0

    def __post_init__(self):
        object.__setattr__(self, "image_resolution", tuple(int(s) for s in self.image_resolution))
        object.__setattr__(self, "image_keys", tuple(self.image_keys))
        p, a, s = self.paligemma, self.action_expert, self.siglip
        for field in ("depth", "num_heads", "num_kv_heads", "head_dim"):
            if getattr(p, field) != getattr(a, field):
                raise ValueError(
                    f"paligemma.{field}={getattr(p, field)} != action_expert.{field}="
                    f"{getattr(a, field)}: the two experts share every attention layer")
        if p.num_heads % p.num_kv_heads or p.num_kv_heads == p.num_heads:
            # openpi names full multi-head attention differently ("qkv_einsum"); pi0 uses GQA/MQA.
            raise ValueError(f"num_heads={p.num_heads} must be a multiple of num_kv_heads="
                             f"{p.num_kv_heads}, and larger (grouped-query attention)")
        if p.head_dim % 2:
            raise ValueError(f"head_dim={p.head_dim} must be even (RoPE rotates pairs)")
        if a.width % 2:
            raise ValueError(f"action_expert.width={a.width} must be even (sin-cos time embedding)")
        if p.lora_rank < 0 or a.lora_rank < 0:
            raise ValueError(f"lora_rank ({p.lora_rank}, {a.lora_rank}) must be >= 0 (0 = no "
                             "adapters)")
        if s.conv_stem < 0 or s.patch_size % 2 ** s.conv_stem:
            raise ValueError(f"siglip.conv_stem={s.conv_stem} must be >= 0 with 2**conv_stem "
                             f"dividing siglip.patch_size={s.patch_size} (each convolution halves "
                             "the image); conv_stem=0 is SigLIP's own stem, the one the pi0 / "
                             "pi0.5 presets and their checkpoints have: "
                             "--config.model.sizes.siglip.conv_stem=0")
        if s.width % s.num_heads:
            raise ValueError(
                f"siglip.width={s.width} must be a multiple of siglip.num_heads={s.num_heads}")
        if len(self.image_resolution) != 2 or any(r % s.patch_size for r in self.image_resolution):
            raise ValueError(
                f"image_resolution={self.image_resolution} must be (height, width), each a multiple "
                f"of siglip.patch_size={s.patch_size}")
        if not self.image_keys:
            raise ValueError("image_keys must name at least one camera")
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype={self.dtype!r} must be one of {DTYPES}")
        if self.remat_policy not in REMAT_POLICIES:
            raise ValueError(f"model.remat_policy = {self.remat_policy!r} must be one of "
                             f"{REMAT_POLICIES}")
        if self.attention not in ATTENTION:
            raise ValueError(f"model.attention = {self.attention!r} must be one of {ATTENTION}")
        for field in ("vocab_size", "action_dim", "action_horizon", "max_token_len"):
            if getattr(self, field) <= 0:
                raise ValueError(f"{field}={getattr(self, field)} must be positive")
        if not 0.0 <= self.state_dropout <= 1.0:
            raise ValueError(f"state_dropout={self.state_dropout} must be a probability in [0, 1]")
        if self.state_noise < 0.0:
            raise ValueError(f"state_noise={self.state_noise} must be >= 0")
        if self.pi05 and self.perturbs_state:
            raise ValueError("use_state / state_dropout / state_noise act on pi0's state token; "
                             "pi0.5 writes the state into the prompt instead: leave them at "
                             "their defaults (True, 0, 0) with a pi05 preset")
        aug = self.augment
        if not 0.0 < aug.crop_scale <= 1.0:
            raise ValueError(f"augment.crop_scale={aug.crop_scale} must be in (0, 1]")
        if aug.rotate_degrees < 0.0:
            raise ValueError(f"augment.rotate_degrees={aug.rotate_degrees} must be >= 0")
        for field in ("brightness", "contrast", "saturation"):
            if not 0.0 <= getattr(aug, field) < 1.0:
                raise ValueError(f"augment.{field}={getattr(aug, field)} must be in [0, 1)")
        if not 0.0 <= aug.hue <= 0.5:
            raise ValueError(f"augment.hue={aug.hue} must be in [0, 0.5] (a fraction of the circle)")
        if not 0.0 <= aug.jitter_p <= 1.0:
            raise ValueError(f"augment.jitter_p={aug.jitter_p} must be a probability in [0, 1]")

    @property
    def lora_experts(self) -> tuple[str, ...]:
        """The experts with LoRA adapters ("paligemma", "action_expert"), in that order."""
        return tuple(name for name in LORA_RANKS if getattr(self, name).lora_rank)

    @property
    def num_image_tokens(self) -> int:
        """Tokens per camera: (height / patch) * (width / patch)."""
        h, w = self.image_resolution
        return (h // self.siglip.patch_size) * (w // self.siglip.patch_size)

    @property
    def prefix_len(self) -> int:
        return len(self.image_keys) * self.num_image_tokens + self.max_token_len

    @property
    def suffix_len(self) -> int:
        """Action tokens, after pi0's state token."""
        return self.action_horizon + (0 if self.pi05 else 1)

    @property
    def default_norm(self) -> str:
        """openpi's normalization for the model: quantile for pi0.5, z-score for pi0."""
        return "quantile" if self.pi05 else "zscore"

    def replace(self, **changes) -> Pi0Config:
        return dataclasses.replace(self, **changes)

    def without_lora(self) -> Pi0Config:
        """The same model with its adapters folded into the weights (`gemma.merge_lora`)."""
        return self.replace(**{name: dataclasses.replace(getattr(self, name), lora_rank=0)
                               for name in LORA_RANKS})

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready nested dict (tuples become lists)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Pi0Config:
        """Inverse of `to_dict`; an unknown key is a ValueError naming it."""
        nested = {"paligemma": GemmaConfig, "action_expert": GemmaConfig,
                  "siglip": SiglipConfig, "augment": AugmentConfig}
        kwargs = {}
        for key, value in d.items():
            sub = nested.get(key)
            target = sub if sub is not None else cls
            known = {f.name for f in dataclasses.fields(target)}
            if sub is not None:
                unknown = set(value) - known
                if unknown:
                    raise ValueError(f"unknown key(s) {sorted(unknown)} in model config field {key!r}")
                value = sub(**value)
            elif key not in {f.name for f in dataclasses.fields(cls)}:
                raise ValueError(f"unknown model config key {key!r}")
            kwargs[key] = value
        return cls(**kwargs)


GEMMA_2B = GemmaConfig(width=2048, depth=18, mlp_dim=16_384, num_heads=8, num_kv_heads=1, head_dim=256)
GEMMA_300M = GemmaConfig(width=1024, depth=18, mlp_dim=4096, num_heads=8, num_kv_heads=1, head_dim=256)
SIGLIP_SO400M_14 = SiglipConfig(width=1152, depth=27, mlp_dim=4304, num_heads=16, patch_size=14)

_PRESETS = {
    # openpi's pi0: 3 cameras x 256 tokens + 48 prompt tokens; 1 state + 50 action tokens.
    "pi0": Pi0Config(
        paligemma=GEMMA_2B, action_expert=GEMMA_300M, siglip=SIGLIP_SO400M_14,
        vocab_size=PALIGEMMA_VOCAB_SIZE, action_horizon=50, max_token_len=48,
        image_resolution=(224, 224), dtype="bfloat16", remat=True),
    # Laptop CPU: 3 cameras x 16 tokens + 16 prompt tokens; 1 + 32 suffix tokens.
    "demo": Pi0Config(
        paligemma=GemmaConfig(width=128, depth=2, mlp_dim=256, num_heads=4, num_kv_heads=1, head_dim=32),
        action_expert=GemmaConfig(width=64, depth=2, mlp_dim=128, num_heads=4, num_kv_heads=1,
                                  head_dim=32),
        siglip=SiglipConfig(width=64, depth=2, mlp_dim=128, num_heads=4, patch_size=8),
        vocab_size=512, action_horizon=32, max_token_len=16,
        image_resolution=(32, 32), dtype="float32", remat=False),
    # Unit tests: grouped-query attention with 2 query heads per kv head.
    "tiny": Pi0Config(
        paligemma=GemmaConfig(width=32, depth=2, mlp_dim=64, num_heads=4, num_kv_heads=2, head_dim=8),
        action_expert=GemmaConfig(width=16, depth=2, mlp_dim=32, num_heads=4, num_kv_heads=2,
                                  head_dim=8),
        siglip=SiglipConfig(width=16, depth=2, mlp_dim=32, num_heads=2, patch_size=8),
        vocab_size=64, action_horizon=4, max_token_len=8,
        image_resolution=(16, 16), dtype="float32", remat=False),
}
# pi0.5 at each size: the prompt carries the state, so it is longer (openpi: 200 tokens).
_PI05_PROMPT_LEN = {"pi0": 200, "demo": 64, "tiny": 48}
_PRESETS.update({f"pi05{'' if name == 'pi0' else '_' + name}": _PRESETS[name].replace(
    pi05=True, max_token_len=length) for name, length in _PI05_PROMPT_LEN.items()})
PRESETS = tuple(_PRESETS)


def dense_shapes(config: Pi0Config) -> dict[str, tuple[int, int]]:
    """(in, out) features of each dense layer outside the two towers."""
    width, action_dim = config.action_expert.width, config.action_dim
    if config.pi05:
        return {
            "action_in_proj": (action_dim, width),
            "time_mlp_in": (width, width),
            "time_mlp_out": (width, width),
            "action_out_proj": (width, action_dim),
        }
    return {
        "state_proj": (action_dim, width),
        "action_in_proj": (action_dim, width),
        "action_time_mlp_in": (2 * width, width),
        "action_time_mlp_out": (width, width),
        "action_out_proj": (width, action_dim),
    }


def get_preset(name: str, **changes) -> Pi0Config:
    """The named preset (`PRESETS`), with top-level fields replaced by `changes`."""
    if name not in _PRESETS:
        raise ValueError(f"unknown model preset {name!r}; choose one of {PRESETS}")
    return _PRESETS[name].replace(**changes)


def from_model_config(model_cfg: Mapping[str, Any]) -> Pi0Config:
    """Builds the model config from the training config's `model` section.

    Reads `preset`; `dtype`, `action_horizon` and `action_dim` override the preset when set
    (non-empty / > 0); `augment` (its fields), `use_state`, `state_dropout`, `state_noise`,
    `remat_policy` and `attention` when present; `sizes` changes the towers (`_resized`); `lora`
    names the experts that get openpi's adapters (`LORA_RANKS`).
    """
    changes = {}
    if model_cfg.get("augment"):
        changes["augment"] = AugmentConfig(**dict(model_cfg["augment"]))
    for field in ("use_state", "state_dropout", "state_noise", "remat_policy", "attention"):
        if model_cfg.get(field) is not None:
            changes[field] = model_cfg[field]
    if model_cfg.get("action_dim"):
        changes["action_dim"] = int(model_cfg["action_dim"])
    if model_cfg.get("dtype"):
        changes["dtype"] = model_cfg["dtype"]
    if model_cfg.get("action_horizon"):
        changes["action_horizon"] = int(model_cfg["action_horizon"])
    preset = get_preset(model_cfg["preset"])
    changes.update(_resized(preset, model_cfg.get("sizes") or {}))
    lora = model_cfg.get("lora") or ()
    if isinstance(lora, str) or not set(lora) <= set(LORA_RANKS):
        raise ValueError(f"model.lora = {lora!r} must be a tuple of experts among "
                         f"{tuple(LORA_RANKS)}, e.g. --config.model.lora=\"{tuple(LORA_RANKS)}\" "
                         "(openpi's LoRA fine-tuning); () = every weight trains")
    for name in lora:
        changes[name] = dataclasses.replace(changes.get(name, getattr(preset, name)),
                                            lora_rank=LORA_RANKS[name])
    return preset.replace(**changes)


def _resized(preset: Pi0Config, sizes: Mapping[str, Mapping[str, int]]
             ) -> dict[str, GemmaConfig | SiglipConfig]:
    """The towers of `preset` with the non-zero fields of the config's `model.sizes` in place of
    the preset's: `siglip.*`, `paligemma.*` / `action_expert.*` (width, mlp_dim) and
    `attention.*` (depth, num_heads, num_kv_heads, head_dim: both experts, which share every
    attention layer)."""
    changed = {}
    for section, fields in dict(sizes).items():
        for field, value in dict(fields).items():
            if value < 0:
                raise ValueError(f"model.sizes.{section}.{field} = {value} must be >= 0 (0 = "
                                 "the preset's)")
            if value:
                changed.setdefault(section, {})[field] = int(value)
    shared = changed.pop("attention", {})
    towers = {}
    for name in ("paligemma", "action_expert"):
        if name in changed or shared:
            towers[name] = dataclasses.replace(getattr(preset, name),
                                               **changed.pop(name, {}), **shared)
    if "siglip" in changed:
        towers["siglip"] = dataclasses.replace(preset.siglip, **changed.pop("siglip"))
    return towers


def norm_mode(config: Any) -> str:
    """The run's normalization: `data.norm` when set, else the model's (`Pi0Config.default_norm`)."""
    return config.data.get("norm") or from_model_config(config.model).default_norm
