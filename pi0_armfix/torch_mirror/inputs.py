"""Evaluation-time observation preprocessing in torch ops (mirror of `pi0_armfix/model/inputs.py`).

Cameras become float32 [B, *image_resolution, 3] in [-1, 1]: uint8 -> `x / 255 * 2 - 1`, then
openpi's resize_with_pad when the stored resolution differs. The resize reproduces
`jax.image.resize(method="linear")` (a triangle kernel, widened when shrinking, i.e. antialiased)
as one [in, out] weight matrix per spatial axis, built with the same float32 arithmetic, so JAX and
torch see the same pixels. Train-time augmentation is not mirrored: the mirror runs policies.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from pi0_armfix.model.config import Pi0Config

_F32_EPS = float(np.finfo(np.float32).eps)


def as_tensor(x: Any) -> torch.Tensor:
    """numpy / torch / jax array -> torch tensor (a copy only when needed)."""
    return x if torch.is_tensor(x) else torch.from_numpy(np.array(x))


def image_to_float(image: torch.Tensor) -> torch.Tensor:
    """uint8 [..., 3] in [0, 255] -> float32 in [-1, 1]; float images are taken as in [-1, 1]."""
    if image.dtype == torch.uint8:
        return image.to(torch.float32) / 255.0 * 2.0 - 1.0
    return image.to(torch.float32)


def linear_resize_weights(in_size: int, out_size: int) -> torch.Tensor:
    """[in_size, out_size] float32 weights of `jax.image.resize(method="linear", antialias=True)`.

    Output pixel i samples the input at (i + 0.5) / scale - 0.5 with a triangle kernel whose
    support is stretched by 1 / scale when shrinking; columns are normalized to sum to 1.
    """
    inv_scale = torch.tensor(1.0 / (out_size / in_size), dtype=torch.float32)
    kernel_scale = torch.maximum(inv_scale, torch.tensor(1.0))
    sample_f = (torch.arange(out_size, dtype=torch.float32) + 0.5) * inv_scale - 0.5
    x = torch.abs(sample_f[None, :] - torch.arange(in_size, dtype=torch.float32)[:, None]) / kernel_scale
    weights = torch.clamp(1.0 - torch.abs(x), min=0.0)
    total = weights.sum(0, keepdim=True)
    weights = torch.where(torch.abs(total) > 1000.0 * _F32_EPS,
                          weights / torch.where(total != 0, total, torch.ones_like(total)),
                          torch.zeros_like(weights))
    inside = (sample_f >= -0.5) & (sample_f <= in_size - 0.5)
    return torch.where(inside[None, :], weights, torch.zeros_like(weights))


def resize_with_pad(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Resizes [B, h, w, C] in [-1, 1] to fit (height, width) keeping the aspect ratio; pads with -1.

    Scale 1 / max(h / height, w / width), centred, the odd padding row / column at the bottom /
    right (openpi's resize_with_pad).
    """
    cur_height, cur_width = images.shape[1:3]
    ratio = max(cur_width / width, cur_height / height)
    resized_height, resized_width = int(cur_height / ratio), int(cur_width / ratio)
    resized = images
    if resized_height != cur_height:
        resized = torch.einsum("bhwc,hH->bHwc", resized, linear_resize_weights(cur_height, resized_height))
    if resized_width != cur_width:
        resized = torch.einsum("bhwc,wW->bhWc", resized, linear_resize_weights(cur_width, resized_width))
    pad_top, extra_h = divmod(height - resized_height, 2)
    pad_left, extra_w = divmod(width - resized_width, 2)
    return torch.nn.functional.pad(
        resized, (0, 0, pad_left, pad_left + extra_w, pad_top, pad_top + extra_h), value=-1.0)


def preprocess_observation(observation: Mapping[str, Any], *, config: Pi0Config) -> dict[str, Any]:
    """Model-ready observation: cameras float32 [B, *image_resolution, 3] in [-1, 1], masks bool [B].

    Arrays may be numpy or torch. A camera of `config.image_keys` missing from
    `observation["image"]` is a ValueError; a camera without an `image_mask` entry counts as present.
    """
    missing = [key for key in config.image_keys if key not in observation["image"]]
    if missing:
        raise ValueError(f"observation['image'] lacks camera(s) {missing}; expected {config.image_keys} "
                         "(a missing camera is an all-zero image with image_mask False)")
    state = as_tensor(observation["state"]).to(torch.float32)
    images, masks = {}, {}
    for key in config.image_keys:
        image = image_to_float(as_tensor(observation["image"][key]))
        if tuple(image.shape[1:3]) != config.image_resolution:
            image = resize_with_pad(image, *config.image_resolution)
        images[key] = image
        mask = observation.get("image_mask", {}).get(key)
        masks[key] = (torch.ones(state.shape[0], dtype=torch.bool) if mask is None
                      else as_tensor(mask).to(torch.bool))
    return {
        "image": images,
        "image_mask": masks,
        "state": state,
        "tokenized_prompt": as_tensor(observation["tokenized_prompt"]).long(),
        "tokenized_prompt_mask": as_tensor(observation["tokenized_prompt_mask"]).to(torch.bool),
    }
