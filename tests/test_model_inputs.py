"""Model inputs: image conversion, resize-with-pad, augmentation, and the prompt tokenizer."""

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from pi0_armfix.model import config as model_config
from pi0_armfix.model import inputs
from pi0_armfix.model.inputs import (fake_observation, image_to_float, preprocess_observation,
                                     resize_with_pad)
from pi0_armfix.model.tokenizer import Tokenizer, make_tokenizer, train_sentencepiece

TINY = model_config.get_preset("tiny")
PROMPTS = ["pick up the red cup", "navigate_to the kitchen", "open the fridge door\n",
           "put the cup in the fridge"]


def _preprocess(config, obs, seed):
    return jax.jit(lambda o, r: preprocess_observation(r, o, config=config, train=True))(
        obs, jax.random.key(seed))


# ------------------------------------------------------------------------------ images


def test_uint8_images_map_to_minus_one_one():
    image = np.asarray([[[0, 255, 51]]], np.uint8)
    np.testing.assert_allclose(image_to_float(image), [[[-1.0, 1.0, -0.6]]], atol=1e-6)


def test_resize_with_pad_keeps_aspect_ratio_and_pads_black():
    images = np.ones((1, 20, 40, 3), np.float32) * 0.5
    out = np.asarray(resize_with_pad(images, 16, 16))
    assert out.shape == (1, 16, 16, 3)
    np.testing.assert_allclose(out[0, 4:12], 0.5, atol=1e-6)  # 20x40 -> 8x16, centred
    np.testing.assert_array_equal(out[0, :4], -1.0)
    np.testing.assert_array_equal(out[0, 12:], -1.0)


def test_missing_camera_is_an_error_naming_it():
    obs = fake_observation(TINY, 2)
    del obs["image"]["left_wrist_0_rgb"]
    with pytest.raises(ValueError, match="left_wrist_0_rgb"):
        preprocess_observation(None, obs, config=TINY, train=False)


def test_augmentation_is_deterministic_given_the_rng():
    obs = fake_observation(TINY, 4, image_size=(24, 24))
    first, again, other = (_preprocess(TINY, obs, s)["image"] for s in (0, 0, 1))
    for key in TINY.image_keys:
        np.testing.assert_array_equal(first[key], again[key])
        assert not np.allclose(first[key], other[key])
        assert first[key].shape == (4, *TINY.image_resolution, 3)
        assert -1.0 <= float(first[key].min()) and float(first[key].max()) <= 1.0


def test_wrist_cameras_get_no_crop_or_rotation():
    """With colour jitter off, wrist images pass unchanged while the base camera moves."""
    no_color = TINY.replace(augment=model_config.AugmentConfig(jitter_p=0.0))
    obs = fake_observation(no_color, 2)
    plain = preprocess_observation(None, obs, config=no_color, train=False)["image"]
    augmented = _preprocess(no_color, obs, 0)["image"]
    np.testing.assert_allclose(augmented["left_wrist_0_rgb"], plain["left_wrist_0_rgb"], atol=1e-6)
    np.testing.assert_allclose(augmented["right_wrist_0_rgb"], plain["right_wrist_0_rgb"], atol=1e-6)
    assert not np.allclose(augmented["base_0_rgb"], plain["base_0_rgb"], atol=1e-2)


def test_color_jitter_changes_wrist_cameras():
    always = TINY.replace(augment=model_config.AugmentConfig(jitter_p=1.0))
    obs = fake_observation(always, 2)
    plain = preprocess_observation(None, obs, config=always, train=False)["image"]
    augmented = _preprocess(always, obs, 0)["image"]
    assert not np.allclose(augmented["left_wrist_0_rgb"], plain["left_wrist_0_rgb"], atol=1e-2)


def test_hsv_round_trip_is_the_identity():
    rgb = np.random.default_rng(0).uniform(0, 1, (500, 3)).astype(np.float32)
    rgb[:5] = [[0, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5], [1, 0, 0], [0, 0, 1]]
    np.testing.assert_allclose(inputs.hsv_to_rgb(inputs.rgb_to_hsv(jnp.asarray(rgb))), rgb,
                               atol=1e-6)


def _jittered(cfg, images, seed=0):
    keys = jax.random.split(jax.random.key(seed), len(images))
    return np.asarray(jax.jit(jax.vmap(lambda k, x: inputs.color_jitter(k, x, cfg)))(keys, images))


def test_color_jitter_leaves_images_unchanged_with_probability_one_minus_p():
    images = jnp.asarray(np.random.default_rng(0).uniform(0.1, 0.9, (2000, 4, 4, 3)), jnp.float32)
    out = _jittered(model_config.AugmentConfig(), images)
    unchanged = np.all(np.isclose(out, images, atol=1e-6), axis=(1, 2, 3)).mean()
    assert 0.46 <= unchanged <= 0.54  # openpi's ColorJitter p=0.5


def test_color_jitter_shifts_hue_by_at_most_the_configured_fraction():
    cfg = model_config.AugmentConfig(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.1,
                                     jitter_p=1.0)
    pixel = jnp.asarray([[[0.9, 0.3, 0.2]]], jnp.float32)  # saturated, hue ~0.02
    out = _jittered(cfg, jnp.broadcast_to(pixel, (500, 1, 1, 3)))
    before = float(inputs.rgb_to_hsv(pixel)[0, 0, 0])
    shift = (np.asarray(inputs.rgb_to_hsv(jnp.asarray(out)))[:, 0, 0, 0] - before + 0.5) % 1 - 0.5
    assert np.abs(shift).max() <= 0.1 + 1e-5 and np.abs(shift).max() > 0.09
    assert abs(shift.mean()) < 0.01


def test_crop_and_rotation_are_one_map_that_keeps_distances_to_the_centre():
    rotate = model_config.AugmentConfig(crop_scale=1.0, rotate_degrees=30.0)
    coords = np.asarray(inputs.crop_rotate_map(jax.random.key(3), 16, 16, rotate))
    ys, xs = np.meshgrid(np.arange(16) + 0.5, np.arange(16) + 0.5, indexing="ij")
    np.testing.assert_allclose(np.hypot(coords[0] + 0.5 - 8, coords[1] + 0.5 - 8),
                               np.hypot(ys - 8, xs - 8), atol=1e-4)
    crop = model_config.AugmentConfig(crop_scale=0.5, rotate_degrees=0.0)
    coords = np.asarray(inputs.crop_rotate_map(jax.random.key(3), 16, 16, crop))
    assert np.ptp(coords[0]) == pytest.approx(7.5 * 0.5 * 2) and np.ptp(coords[1]) == pytest.approx(7.5)
    identity = np.asarray(inputs.crop_rotate_map(
        jax.random.key(3), 16, 16, model_config.AugmentConfig(crop_scale=1.0, rotate_degrees=0.0)))
    np.testing.assert_allclose(identity, [ys - 0.5, xs - 0.5], atol=1e-6)


def test_base_camera_is_resampled_once_through_the_composed_map():
    cfg = model_config.AugmentConfig(jitter_p=0.0)
    image = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (16, 16, 3)), jnp.float32)
    rng = jax.random.key(5)
    out = inputs.augment_image(rng, image, cfg, wrist=False)
    rng_geometry, _ = jax.random.split(rng)
    expected = inputs.resample(image / 2 + 0.5, inputs.crop_rotate_map(rng_geometry, 16, 16, cfg))
    np.testing.assert_allclose(out, expected * 2 - 1, atol=1e-6)


# ------------------------------------------------------------------------------ tokenizer


def _model_cfg(**changes):
    return ml_collections.ConfigDict(dict(dict(preset="demo", dtype="", action_horizon=0,
                                               pretrained="", tokenizer=""), **changes))


def test_offline_tokenizer_is_deterministic_and_cached(tmp_path):
    assert train_sentencepiece(PROMPTS, 512) == train_sentencepiece(reversed(PROMPTS), 512)
    make_tokenizer(_model_cfg(), prompts=PROMPTS, cache_dir=tmp_path)
    cached = list((tmp_path / "tokenizers").glob("*.model"))
    make_tokenizer(_model_cfg(), prompts=PROMPTS, cache_dir=tmp_path)
    assert len(cached) == 1 and list((tmp_path / "tokenizers").glob("*.model")) == cached


def test_tokens_are_bos_prompt_newline_then_padding(tmp_path):
    tokenize = make_tokenizer(_model_cfg(), prompts=PROMPTS, cache_dir=tmp_path)
    demo = model_config.get_preset("demo")
    tokens, mask = tokenize("  navigate_to the\nkitchen ")
    assert tokens.dtype == np.int32 and mask.dtype == bool
    assert tokens.shape == mask.shape == (demo.max_token_len,)
    n = int(mask.sum())
    assert tokens[0] == 2  # BOS
    assert tokenize.decode(tokens[1:], mask[1:]) == "navigate to the kitchen\n"
    assert mask[:n].all() and not mask[n:].any() and (tokens[n:] == 0).all()
    assert tokens.max() < demo.vocab_size


def test_long_prompts_are_truncated_to_max_token_len(tmp_path):
    tokenize = make_tokenizer(_model_cfg(), prompts=PROMPTS, cache_dir=tmp_path)
    tokens, mask = tokenize(" ".join(PROMPTS * 4))
    assert tokens.shape == (tokenize.max_len,) and mask.all()


def test_tokenizer_file_is_used_when_configured(tmp_path):
    path = tmp_path / "spm.model"
    path.write_bytes(train_sentencepiece(["a completely different corpus"], 512))
    tokenize = make_tokenizer(_model_cfg(tokenizer=str(path)))
    expected = Tokenizer(path.read_bytes(), tokenize.max_len, vocab_size=512, source="test")
    for got, want in zip(tokenize("different corpus"), expected("different corpus")):
        np.testing.assert_array_equal(got, want)


def test_tokenizer_larger_than_the_embedding_is_rejected(tmp_path):
    path = tmp_path / "spm.model"
    path.write_bytes(train_sentencepiece(PROMPTS * 3, 512))
    with pytest.raises(ValueError, match="vocab_size=16"):
        Tokenizer(path.read_bytes(), 8, vocab_size=16, source=str(path))


def test_pretrained_weights_require_their_tokenizer():
    with pytest.raises(ValueError, match="model.tokenizer"):
        make_tokenizer(_model_cfg(pretrained="/ckpt/params"), prompts=PROMPTS)


def test_missing_tokenizer_file_is_named(tmp_path):
    with pytest.raises(ValueError, match="nope.model"):
        make_tokenizer(_model_cfg(tokenizer=str(tmp_path / "nope.model")))


def test_pi05_prompt_writes_the_state_bins_in_openpi_format():
    from pi0_armfix.model.tokenizer import pi05_prompt

    state = np.array([-1.0, 0.0, 0.999, 1.5, -1.5, -0.5])
    assert pi05_prompt("pick_up the cup\n", state) == (
        "Task: pick up the cup, State: 0 128 255 255 -1 64;\nAction: ")


def test_pi05_tokenizer_encodes_the_state_prompt_with_bos(tmp_path):
    from pi0_armfix.model.tokenizer import pi05_prompt

    model_cfg = ml_collections.ConfigDict({"preset": "pi05_demo", "tokenizer": "",
                                           "pretrained": ""})
    tokenizer = make_tokenizer(model_cfg, prompts=PROMPTS, cache_dir=tmp_path)
    assert tokenizer.state_in_prompt and tokenizer.max_len == 64
    state = np.array([0.25, -0.75, 1.0])
    tokens, mask = tokenizer("open the fridge door", state)
    text = pi05_prompt("open the fridge door", state)
    assert tokens[0] == 2  # BOS
    assert tokenizer.decode(tokens, mask) == text.rstrip()
    assert 3 not in tokens[mask]  # no unknown piece: the numbers are in the vocabulary


# ------------------------------------------------------------------------------ state levers


def _state_after(config, train, batch=4000, seed=0):
    obs = fake_observation(config, batch)
    obs["state"] = np.ones((batch, config.action_dim), np.float32)
    rng = jax.random.key(seed) if train else None
    return np.asarray(preprocess_observation(rng, obs, config=config, train=train)["state"])


def test_without_the_state_the_model_sees_zeros_in_training_and_sampling():
    config = TINY.replace(use_state=False)
    assert not _state_after(config, train=True, batch=8).any()
    assert not _state_after(config, train=False, batch=8).any()


@pytest.mark.slow  # a forward compilation per mode
def test_state_dropout_zeroes_whole_samples_at_its_rate_in_training_only():
    config = TINY.replace(state_dropout=0.3)
    state = _state_after(config, train=True)
    dropped = ~state.any(axis=1)
    assert abs(dropped.mean() - 0.3) < 0.03
    assert (state[~dropped] == 1.0).all()  # a kept sample is untouched
    assert (_state_after(config, train=False, batch=8) == 1.0).all()


def test_state_noise_has_its_std_around_the_unchanged_state_in_training_only():
    config = TINY.replace(state_noise=0.2)
    state = _state_after(config, train=True)
    assert abs(state.mean() - 1.0) < 0.01 and abs(state.std() - 0.2) < 0.01
    assert (_state_after(config, train=False, batch=8) == 1.0).all()


@pytest.mark.slow  # a forward compilation per mode
def test_state_noise_leaves_the_padding_and_constant_dims_at_zero_as_at_inference():
    config = TINY.replace(state_noise=0.2)
    obs = fake_observation(config, 64)
    obs["state"] = np.ones((64, config.action_dim), np.float32)
    obs["state"][:, 5:] = 0.0  # padding (and a constant dim) normalize to exactly 0
    state = np.asarray(preprocess_observation(jax.random.key(0), obs, config=config,
                                              train=True)["state"])
    assert (state[:, 5:] == 0.0).all() and state[:, :5].std() > 0.1


def test_state_levers_are_refused_for_pi05_whose_state_is_in_the_prompt():
    with pytest.raises(ValueError, match="pi0.5 writes the state into the prompt"):
        model_config.get_preset("pi05_tiny", state_dropout=0.5)
