"""Observation preprocessing inside jit: image conversion, resize-with-pad, train-time augmentation.

An observation is the batch dict of CONTRACT.md without the actions:
  image: {camera: uint8 [B, h, w, 3]} (or float [B, h, w, 3] already in [-1, 1]),
  image_mask: {camera: bool [B]}, state: float32 [B, A],
  tokenized_prompt: int32 [B, L], tokenized_prompt_mask: bool [B, L].

`preprocess_observation` returns the same dict with every camera of `config.image_keys` as float32
[B, *image_resolution, 3] in [-1, 1] (augmented when train=True) and an image_mask for each.
Augmentation follows openpi's pi0 recipe: non-wrist cameras get a random crop (`crop_scale` of
each side) resized back and a small rotation; every camera gets brightness / contrast /
saturation jitter. Each image draws its own parameters from `fold_in(rng, camera)` split over the
batch, so the result is a deterministic function of the rng.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_armfix.model.config import AugmentConfig, Pi0Config

# ITU-R 601 luma weights (grayscale for the saturation and contrast jitter).
_LUMA = (0.299, 0.587, 0.114)


def image_to_float(image: jax.Array) -> jax.Array:
    """uint8 [..., 3] in [0, 255] -> float32 in [-1, 1]; float images are taken as in [-1, 1]."""
    if image.dtype == jnp.uint8:
        return image.astype(jnp.float32) / 255.0 * 2.0 - 1.0
    return image.astype(jnp.float32)


def resize_with_pad(images: jax.Array, height: int, width: int) -> jax.Array:
    """Resizes [B, h, w, C] in [-1, 1] to fit (height, width) keeping the aspect ratio; pads with -1.

    The image is scaled by 1 / max(h / height, w / width) (bilinear, antialiased when shrinking)
    and centred; the odd pixel of padding goes to the bottom / right (openpi's resize_with_pad).
    """
    cur_height, cur_width = images.shape[1:3]
    ratio = max(cur_width / width, cur_height / height)
    resized_height, resized_width = int(cur_height / ratio), int(cur_width / ratio)
    resized = jax.image.resize(
        images, (images.shape[0], resized_height, resized_width, images.shape[3]), method="linear")
    pad_top, extra_h = divmod(height - resized_height, 2)
    pad_left, extra_w = divmod(width - resized_width, 2)
    padding = ((0, 0), (pad_top, pad_top + extra_h), (pad_left, pad_left + extra_w), (0, 0))
    return jnp.pad(resized, padding, constant_values=-1.0)


def _random_crop_resize(rng: jax.Array, image: jax.Array, scale: float) -> jax.Array:
    """Crops a random window of `scale` x each side from [h, w, C] and resizes it back to [h, w, C]."""
    height, width = image.shape[:2]
    crop_h, crop_w = int(height * scale), int(width * scale)
    rng_y, rng_x = jax.random.split(rng)
    top = jax.random.randint(rng_y, (), 0, height - crop_h + 1)
    left = jax.random.randint(rng_x, (), 0, width - crop_w + 1)
    crop = jax.lax.dynamic_slice(image, (top, left, 0), (crop_h, crop_w, image.shape[2]))
    return jax.image.resize(crop, image.shape, method="linear")


def _rotate(rng: jax.Array, image: jax.Array, max_degrees: float) -> jax.Array:
    """Rotates [h, w, C] about its centre by a uniform angle in +-max_degrees; outside is black (0)."""
    height, width = image.shape[:2]
    angle = jnp.deg2rad(jax.random.uniform(rng, (), minval=-max_degrees, maxval=max_degrees))
    ys, xs = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32), jnp.arange(width, dtype=jnp.float32),
                          indexing="ij")
    cy, cx = (height - 1) / 2.0, (width - 1) / 2.0
    # Inverse map: each output pixel samples the input at the point rotated by -angle.
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    src_y = cos * (ys - cy) - sin * (xs - cx) + cy
    src_x = sin * (ys - cy) + cos * (xs - cx) + cx
    channels = [jax.scipy.ndimage.map_coordinates(image[..., c], [src_y, src_x], order=1,
                                                  mode="constant", cval=0.0)
                for c in range(image.shape[2])]
    return jnp.stack(channels, axis=-1)


def _color_jitter(rng: jax.Array, image: jax.Array, cfg: AugmentConfig) -> jax.Array:
    """Brightness, contrast, saturation factors each uniform in [1 - s, 1 + s]; [h, w, 3] in [0, 1]."""
    rng_b, rng_c, rng_s = jax.random.split(rng, 3)

    def factor(key, strength):
        return jax.random.uniform(key, (), minval=1.0 - strength, maxval=1.0 + strength)

    luma = jnp.asarray(_LUMA, image.dtype)
    image = jnp.clip(image * factor(rng_b, cfg.brightness), 0.0, 1.0)
    mean_gray = jnp.mean(image @ luma)
    image = jnp.clip((image - mean_gray) * factor(rng_c, cfg.contrast) + mean_gray, 0.0, 1.0)
    gray = (image @ luma)[..., None]
    return jnp.clip((image - gray) * factor(rng_s, cfg.saturation) + gray, 0.0, 1.0)


def augment_image(rng: jax.Array, image: jax.Array, cfg: AugmentConfig, *, wrist: bool) -> jax.Array:
    """One image [h, w, 3] in [-1, 1] -> augmented [h, w, 3] in [-1, 1]. Wrist cameras: colour only."""
    image = image / 2.0 + 0.5
    rng_crop, rng_rotate, rng_color = jax.random.split(rng, 3)
    if not wrist:
        if cfg.crop_scale < 1.0:
            image = _random_crop_resize(rng_crop, image, cfg.crop_scale)
        if cfg.rotate_degrees > 0.0:
            image = _rotate(rng_rotate, image, cfg.rotate_degrees)
    image = _color_jitter(rng_color, image, cfg)
    return image * 2.0 - 1.0


def preprocess_observation(rng: jax.Array | None, observation: Mapping[str, Any], *,
                           config: Pi0Config, train: bool) -> dict[str, Any]:
    """Model-ready observation: cameras float32 [B, *image_resolution, 3] in [-1, 1], masks bool [B].

    A camera of `config.image_keys` missing from `observation["image"]` is a ValueError; a camera
    without an `image_mask` entry counts as present (openpi's default). `rng` is only used when
    `train` is True.
    """
    missing = [key for key in config.image_keys if key not in observation["image"]]
    if missing:
        raise ValueError(f"observation['image'] lacks camera(s) {missing}; expected {config.image_keys} "
                         "(a missing camera is an all-zero image with image_mask False)")
    batch_size = observation["state"].shape[0]
    images, masks = {}, {}
    for index, key in enumerate(config.image_keys):
        image = image_to_float(jnp.asarray(observation["image"][key]))
        if image.shape[1:3] != config.image_resolution:
            image = resize_with_pad(image, *config.image_resolution)
        if train:
            keys = jax.random.split(jax.random.fold_in(rng, index), image.shape[0])
            augment = functools.partial(augment_image, cfg=config.augment, wrist="wrist" in key)
            image = jax.vmap(augment)(keys, image)
        images[key] = image
        mask = observation.get("image_mask", {}).get(key)
        masks[key] = jnp.ones((batch_size,), bool) if mask is None else jnp.asarray(mask, bool)
    return {**observation, "image": images, "image_mask": masks}


def fake_observation(config: Pi0Config, batch_size: int, *, image_size: tuple[int, int] | None = None,
                     seed: int = 0) -> dict[str, np.ndarray]:
    """A random observation in the batch format (uint8 cameras), for tests and benchmarks."""
    rng = np.random.default_rng(seed)
    height, width = image_size or config.image_resolution
    return {
        "image": {key: rng.integers(0, 256, (batch_size, height, width, 3), dtype=np.uint8)
                  for key in config.image_keys},
        "image_mask": {key: np.ones((batch_size,), bool) for key in config.image_keys},
        "state": rng.standard_normal((batch_size, config.action_dim)).astype(np.float32),
        "tokenized_prompt": rng.integers(0, config.vocab_size, (batch_size, config.max_token_len),
                                         dtype=np.int32),
        "tokenized_prompt_mask": np.arange(config.max_token_len)[None].repeat(batch_size, 0)
        < rng.integers(1, config.max_token_len + 1, (batch_size, 1)),
    }
