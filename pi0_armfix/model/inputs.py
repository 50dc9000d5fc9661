"""Observation preprocessing inside jit: image conversion, resize-with-pad, train-time augmentation.

An observation is the batch dict of docs/design.md §4 without the actions:
  image: {camera: uint8 [B, h, w, 3]} (or float [B, h, w, 3] already in [-1, 1]),
  image_mask: {camera: bool [B]}, state: float32 [B, A],
  tokenized_prompt: int32 [B, L], tokenized_prompt_mask: bool [B, L].

`preprocess_observation` returns the same dict with every camera of `config.image_keys` as float32
[B, *image_resolution, 3] in [-1, 1] (augmented when train=True) and an image_mask for each.
Augmentation has the semantics of openpi's (augmax) chain, `AugmentConfig`: non-wrist cameras get
a random crop (`crop_scale` of each side) resized back and a small rotation, composed into one
coordinate map and resampled once; every camera gets augmax's HSV colour jitter with probability
`jitter_p`. Each image draws its own parameters from `fold_in(rng, camera)` split over the
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


def model_image(images: jax.Array, resolution: tuple[int, int]) -> jax.Array:
    """Camera images `[B, h, w, 3]` (uint8, or float in [-1, 1]) -> the model's float32
    `[B, *resolution, 3]` in [-1, 1]: what `preprocess_observation` does before augmenting."""
    image = image_to_float(jnp.asarray(images))
    if image.shape[1:3] != tuple(resolution):
        image = resize_with_pad(image, *resolution)
    return image


def crop_rotate_map(rng: jax.Array, height: int, width: int, cfg: AugmentConfig) -> jax.Array:
    """The source coordinates [2, h, w] (y, x) each output pixel samples: a random crop of
    `crop_scale` of each side, resized back to (h, w), then rotated about the centre by an angle
    uniform in +-rotate_degrees; crop, resize and rotation composed into one map."""
    rng_y, rng_x, rng_angle = jax.random.split(rng, 3)
    crop_h, crop_w = int(height * cfg.crop_scale), int(width * cfg.crop_scale)
    top = jax.random.randint(rng_y, (), 0, height - crop_h + 1).astype(jnp.float32)
    left = jax.random.randint(rng_x, (), 0, width - crop_w + 1).astype(jnp.float32)
    angle = jnp.deg2rad(jax.random.uniform(rng_angle, (), minval=-cfg.rotate_degrees,
                                           maxval=cfg.rotate_degrees))
    # Pixel centres at i + 0.5: rotate the output point about the centre (inverse map), scale it
    # into the crop, shift by the crop's corner.
    ys, xs = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32) + 0.5,
                          jnp.arange(width, dtype=jnp.float32) + 0.5, indexing="ij")
    cy, cx = height / 2.0, width / 2.0
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    rot_y = cos * (ys - cy) - sin * (xs - cx) + cy
    rot_x = sin * (ys - cy) + cos * (xs - cx) + cx
    src_y = top + rot_y * (crop_h / height) - 0.5
    src_x = left + rot_x * (crop_w / width) - 0.5
    return jnp.stack([src_y, src_x])


def resample(image: jax.Array, coords: jax.Array) -> jax.Array:
    """Bilinear sample of [h, w, C] at coords [2, h', w'] (y, x); black (0) outside."""
    return jnp.stack([jax.scipy.ndimage.map_coordinates(image[..., c], [coords[0], coords[1]],
                                                        order=1, mode="constant", cval=0.0)
                      for c in range(image.shape[2])], axis=-1)


def rgb_to_hsv(rgb: jax.Array) -> jax.Array:
    """[..., 3] RGB in [0, 1] -> [..., 3] (hue in [0, 1), saturation, value)."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    value = jnp.max(rgb, axis=-1)
    delta = value - jnp.min(rgb, axis=-1)
    saturation = jnp.where(value > 0, delta / jnp.where(value > 0, value, 1.0), 0.0)
    safe = jnp.where(delta > 0, delta, 1.0)
    hue = jnp.where(value == r, (g - b) / safe,
                    jnp.where(value == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0))
    hue = jnp.where(delta > 0, (hue / 6.0) % 1.0, 0.0)
    return jnp.stack([hue, saturation, value], axis=-1)


def hsv_to_rgb(hsv: jax.Array) -> jax.Array:
    """Inverse of `rgb_to_hsv` (hue taken modulo 1)."""
    hue, saturation, value = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    h6 = (hue % 1.0) * 6.0
    sector = jnp.floor(h6)
    f = h6 - sector
    p = value * (1 - saturation)
    q = value * (1 - saturation * f)
    t = value * (1 - saturation * (1 - f))
    sector = sector.astype(jnp.int32) % 6
    choices = [jnp.stack(c, axis=-1) for c in
               ((value, t, p), (q, value, p), (p, value, t), (p, q, value), (t, p, value),
                (value, p, q))]
    return jnp.select([(sector == i)[..., None] for i in range(6)], choices)


def color_jitter(rng: jax.Array, image: jax.Array, cfg: AugmentConfig) -> jax.Array:
    """augmax's ColorJitter on [h, w, 3] in [0, 1], one draw per image: hue + U(-h, h),
    saturation + U(-s, s) clipped, value + U(-b, b), then the contrast slant, value clipped;
    applied with probability `jitter_p`."""
    rng_h, rng_s, rng_b, rng_c, rng_apply = jax.random.split(rng, 5)

    def shift(key, strength):
        return jax.random.uniform(key, (), minval=-strength, maxval=strength)

    hue, saturation, value = jnp.moveaxis(rgb_to_hsv(image), -1, 0)
    hue = hue + shift(rng_h, cfg.hue)
    saturation = jnp.clip(saturation + shift(rng_s, cfg.saturation), 0.0, 1.0)
    value = value + shift(rng_b, cfg.brightness)
    slant = jnp.tan((shift(rng_c, cfg.contrast) + 1.0) * (jnp.pi / 4))
    value = jnp.clip(value * slant + 0.5 * (1 - slant), 0.0, 1.0)
    jittered = hsv_to_rgb(jnp.stack([hue, saturation, value], axis=-1))
    return jnp.where(jax.random.bernoulli(rng_apply, cfg.jitter_p), jittered, image)


def augment_image(rng: jax.Array, image: jax.Array, cfg: AugmentConfig, *, wrist: bool) -> jax.Array:
    """One image [h, w, 3] in [-1, 1] -> augmented [h, w, 3] in [-1, 1]. Wrist cameras: colour only."""
    image = image / 2.0 + 0.5
    rng_geometry, rng_color = jax.random.split(rng)
    if not wrist and (cfg.crop_scale < 1.0 or cfg.rotate_degrees > 0.0):
        image = resample(image, crop_rotate_map(rng_geometry, *image.shape[:2], cfg))
    image = color_jitter(rng_color, image, cfg)
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
        image = model_image(observation["image"][key], config.image_resolution)
        if train:
            keys = jax.random.split(jax.random.fold_in(rng, index), image.shape[0])
            augment = functools.partial(augment_image, cfg=config.augment, wrist="wrist" in key)
            image = jax.vmap(augment)(keys, image)
        images[key] = image
        mask = observation.get("image_mask", {}).get(key)
        masks[key] = jnp.ones((batch_size,), bool) if mask is None else jnp.asarray(mask, bool)
    state = observation["state"]
    if config.perturbs_state:
        rng_state = jax.random.fold_in(rng, len(config.image_keys)) if train else None
        state = perturb_state(rng_state, jnp.asarray(state, jnp.float32), config=config,
                              train=train)
    return {**observation, "state": state, "image": images, "image_mask": masks}


def perturb_state(rng: jax.Array | None, state: jax.Array, *, config: Pi0Config, train: bool
                  ) -> jax.Array:
    """The state levers against copying the state (`Pi0Config.use_state`, `state_dropout`,
    `state_noise`) on a normalized state `[B, S]`: zeros without the state; in training, each
    sample's state dropped to zeros with probability `state_dropout`, else `state_noise` std of
    Gaussian noise added to its nonzero dims: the padding dims and the constant dims (normalized
    to exactly 0) stay 0, as they are at inference."""
    if not config.use_state:
        return jnp.zeros_like(state)
    if not train:
        return state
    rng_drop, rng_noise = jax.random.split(rng)
    if config.state_noise > 0.0:
        noise = config.state_noise * jax.random.normal(rng_noise, state.shape, state.dtype)
        state = state + jnp.where(state != 0, noise, 0.0)
    if config.state_dropout > 0.0:
        keep = jax.random.bernoulli(rng_drop, 1.0 - config.state_dropout, state.shape[:1])
        state = jnp.where(keep[:, None], state, 0.0)
    return state


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
