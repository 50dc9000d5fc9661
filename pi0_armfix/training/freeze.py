"""Which parameters train: all of them, or under LoRA openpi's split (its `get_freeze_filter`).

An expert with LoRA adapters (`Pi0Config.lora_experts`) keeps its own weights in the language
model frozen and trains only its adapters; everything else trains: the vision tower, the
projections, and an expert without adapters. The frozen weights are stored in bfloat16, as openpi
stores them, so a LoRA run holds them at half the bytes and keeps neither gradients nor AdamW
moments (nor an EMA) for them.

A parameter belongs to the action expert when a key of its path ends in `_1` (openpi's names:
`q_einsum_1`, `mlp_1`, `final_norm_1`), to the prefix expert otherwise (the embedder included).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
from flax import traverse_util

from pi0_armfix.model import gemma
from pi0_armfix.model.config import Pi0Config

FROZEN_DTYPE = jnp.bfloat16
_LANGUAGE_MODEL = ("PaliGemma", "llm")


def is_frozen(path: tuple[str, ...], config: Pi0Config) -> bool:
    """Whether the parameter at `path` (a tuple of keys) stays fixed in training under `config`."""
    if path[:2] != _LANGUAGE_MODEL or gemma.is_adapter(path[-1]):
        return False
    expert = "action_expert" if any(key.endswith("_1") for key in path) else "paligemma"
    return expert in config.lora_experts


def split(params: Any, config: Pi0Config) -> tuple[dict[str, Any], dict[str, Any]]:
    """`params` -> (the trainable params, the frozen ones): two nested dicts that `merge` joins
    back (the second is empty without LoRA)."""
    flat = traverse_util.flatten_dict(params)
    frozen = {path: leaf for path, leaf in flat.items() if is_frozen(path, config)}
    trainable = {path: leaf for path, leaf in flat.items() if path not in frozen}
    return traverse_util.unflatten_dict(trainable), traverse_util.unflatten_dict(frozen)


def merge(trainable: Any, frozen: Any) -> dict[str, Any]:
    """Inverse of `split`."""
    return traverse_util.unflatten_dict({**traverse_util.flatten_dict(trainable),
                                         **traverse_util.flatten_dict(frozen)})


def store_frozen(params: Any, config: Pi0Config) -> dict[str, Any]:
    """`params` with the frozen leaves cast to `FROZEN_DTYPE` (what a train state holds)."""
    trainable, frozen = split(params, config)
    cast = traverse_util.unflatten_dict({path: jnp.asarray(leaf, FROZEN_DTYPE) for path, leaf in
                                         traverse_util.flatten_dict(frozen).items()})
    return merge(trainable, cast)
