"""The PyTorch mirror of pi0 and pi0.5 (docs/design.md §5) against the Flax model, on the tiny
presets after conversion.

Every comparison feeds both sides the same parameters, observation, noise and time. float32 on
CPU: the mirror agrees to ~1e-6; the tolerances (1e-5, sampling 1e-4) leave room for the time
embedding, whose float32 sines at periods down to 4e-3 move by ~1e-6 between any two compilers
(JAX jitted vs op-by-op differ by as much).
"""

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import inputs as flax_inputs
from pi0_armfix.model import flow_model
from pi0_armfix.model.config import get_preset
from pi0_armfix.torch_mirror import checkpoint, inputs
from pi0_armfix.torch_mirror.model import Pi0
from pi0_armfix.model.tree import flatten_tree
from pi0_armfix.torch_mirror.params import openpi_name, param_shapes, torch_name

CONFIG = get_preset("tiny")
LAYOUT = ActionLayout.preset("b1k_r1pro")
BATCH = 3
REFERENCE_TREE = Path(__file__).resolve().parent / "reference" / "openpi_param_tree.json"


def _preset(name):
    """A preset, or `tiny_conv_stem`: `tiny` with a ViT of early convolutions (siglip.conv_stem)."""
    if name == "tiny_conv_stem":
        tiny = get_preset("tiny")
        return tiny.replace(siglip=dataclasses.replace(tiny.siglip, conv_stem=2))
    return get_preset(name)


@pytest.fixture(scope="module", params=[  # the conv stem differs only before the first layer
    "tiny", "pi05_tiny", pytest.param("tiny_conv_stem", marks=pytest.mark.slow)])
def config(request):
    return _preset(request.param)


@pytest.fixture(scope="module")
def flax_params(config):
    """Initial params; pi0.5's adaptive-norm kernels (zero at init) made random, so that the
    time condition reaches the actions on both sides."""
    params = flow_model.init_params(config, jax.random.key(0))
    llm = params["PaliGemma"]["llm"]
    norms = [llm["layers"][n]["Dense_0"] for n in ("pre_attention_norm_1", "pre_ffw_norm_1")
             if "Dense_0" in llm["layers"].get(n, {})]
    norms += [llm["final_norm_1"]["Dense_0"]] if "Dense_0" in llm["final_norm_1"] else []
    for i, dense in enumerate(norms):
        dense["kernel"] = 0.3 * jax.random.normal(jax.random.key(10 + i), dense["kernel"].shape)
    return params


@pytest.fixture(scope="module")
def torch_model(config, flax_params, tmp_path_factory):
    """The Flax params through conversion and back: what a user of the mirror loads."""
    out = tmp_path_factory.mktemp("converted")
    arrays = {k: np.asarray(v) for k, v in flatten_tree(flax_params).items()}
    checkpoint.write_converted(str(out), arrays, config, None, source="test")
    model, _ = checkpoint.load_converted(str(out))
    return model


@pytest.fixture(scope="module")
def observation(config):
    """Cameras stored at 20x24 (resized with padding to 16x16), one camera missing, padded prompts."""
    obs = flax_inputs.fake_observation(config, BATCH, image_size=(20, 24), seed=1)
    obs["image_mask"]["left_wrist_0_rgb"][1] = False
    obs["image"]["left_wrist_0_rgb"][1] = 0
    return obs


def _noise_and_time(seed):
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((BATCH, CONFIG.action_horizon, CONFIG.action_dim)).astype(np.float32)
    return noise, rng.uniform(0.001, 1.0, BATCH).astype(np.float32)


def test_param_shapes_equal_the_flax_tree_for_every_small_preset():
    for name in ("tiny", "demo", "pi05_tiny", "pi05_demo", "tiny_conv_stem"):
        config = _preset(name)
        flax_shapes = {k: v.shape for k, v in flatten_tree(flow_model.param_shapes(config)).items()}
        assert param_shapes(config) == flax_shapes, name


@pytest.mark.parametrize("preset", ["pi0", "pi05"])
def test_param_shapes_equal_openpi_published_tree(preset):
    with open(REFERENCE_TREE) as f:
        reference = {name: tuple(shape) for name, (shape, _) in json.load(f)[preset].items()}
    assert param_shapes(get_preset(preset)) == reference


def test_torch_state_dict_names_are_openpi_names_with_dots():
    names = set(Pi0(CONFIG).state_dict())
    assert names == {torch_name(name) for name in param_shapes(CONFIG)}
    assert "PaliGemma.llm.layers.attn.q_einsum_1.w" in names
    assert openpi_name("PaliGemma.img.head.kernel") == "PaliGemma/img/head/kernel"


def test_resize_with_pad_matches_jax_image_resize():
    rng = np.random.default_rng(0)
    for shape in ((2, 20, 24, 3), (2, 7, 30, 3), (1, 48, 40, 3)):
        image = rng.uniform(-1, 1, shape).astype(np.float32)
        expected = np.asarray(flax_inputs.resize_with_pad(jnp.asarray(image), 16, 16))
        got = inputs.resize_with_pad(torch.from_numpy(image), 16, 16).numpy()
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)


def test_velocity_matches_flax(config, flax_params, torch_model, observation):
    x_t, t = _noise_and_time(0)
    expected = np.asarray(jax.jit(lambda p, o, x, t: flow_model.velocity(p, o, x, t, config=config))(
        flax_params, observation, x_t, t))
    with torch.no_grad():
        got = torch_model.velocity(observation, x_t, t).numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)


@pytest.mark.parametrize("loss_kwargs", [
    dict(strategy="uniform"),
    dict(strategy="per_group", delta_weighting=True,
         group_weights={"base": 1.0, "torso": 0.5, "left_arm": 3.0, "left_gripper": 2.0,
                        "right_arm": 3.0, "right_gripper": 2.0}),
    dict(strategy="per_dimension", dimension_weights=[1.0] * 23 + [0.0] * 9),
], ids=lambda kw: kw["strategy"])
def test_compute_loss_matches_flax(config, flax_params, torch_model, observation, loss_kwargs):
    rng = np.random.default_rng(2)
    actions = np.zeros((BATCH, CONFIG.action_horizon, CONFIG.action_dim), np.float32)
    actions[..., :LAYOUT.real_dim] = np.cumsum(rng.normal(0, 0.3, actions[..., :LAYOUT.real_dim].shape), 1)
    action_is_pad = np.zeros((BATCH, CONFIG.action_horizon), bool)
    action_is_pad[0, -2:] = True
    batch = {**observation, "actions": actions, "action_is_pad": action_is_pad}
    key = jax.random.key(7)
    expected, expected_aux = flow_model.compute_loss(flax_params, key, batch, config=config, layout=LAYOUT,
                                                 train=False, **loss_kwargs)
    # The draws of flow_model.compute_loss: its rng splits into augmentation, noise and time keys.
    _, key_noise, key_time = jax.random.split(key, 3)
    noise = np.asarray(jax.random.normal(key_noise, actions.shape))
    time = np.asarray(jax.random.beta(key_time, 1.5, 1.0, (BATCH,)) * 0.999 + 0.001)

    with torch.no_grad():
        got, aux = torch_model.compute_loss(batch, actions, action_is_pad, noise, time, layout=LAYOUT,
                                            **loss_kwargs)
    np.testing.assert_allclose(got.numpy(), np.asarray(expected), rtol=0, atol=1e-5)
    for group in LAYOUT.group_names:
        np.testing.assert_allclose(aux["group_loss"][group].numpy(),
                                   np.asarray(expected_aux["group_loss"][group]), rtol=0, atol=1e-5)


def test_sample_actions_matches_flax(config, flax_params, torch_model, observation):
    noise, _ = _noise_and_time(3)
    expected = np.asarray(flow_model.sample_actions(flax_params, None, observation, config=config,
                                                num_steps=10, noise=jnp.asarray(noise)))
    got = torch_model.sample_actions(observation, noise, num_steps=10).numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-4)


def test_sampling_with_prefix_kv_cache_equals_full_recomputation(torch_model, observation):
    noise, _ = _noise_and_time(4)
    cached = torch_model.sample_actions(observation, noise, num_steps=3, use_kv_cache=True)
    full = torch_model.sample_actions(observation, noise, num_steps=3, use_kv_cache=False)
    torch.testing.assert_close(cached, full, rtol=0, atol=1e-5)


def test_prefix_never_sees_the_suffix(config, torch_model, observation):
    """Changing the noisy actions leaves the prefix KV cache untouched, but moves v."""
    params = torch_model.params()
    obs = inputs.preprocess_observation(observation, config=config)
    cache, _ = torch_model.prefix_kv_cache(params, obs)
    x_a, t = (torch.from_numpy(a) for a in _noise_and_time(5))
    with torch.no_grad():
        v_a = torch_model.forward_velocity(params, obs, x_a, t)
        v_b = torch_model.forward_velocity(params, obs, x_a + 1.0, t)
        cache_again, _ = torch_model.prefix_kv_cache(params, obs)
    assert not torch.allclose(v_a, v_b)
    torch.testing.assert_close(cache_again, cache, rtol=0, atol=0)


def test_missing_camera_is_a_value_error_naming_it(torch_model, observation):
    obs = {**observation, "image": {k: v for k, v in observation["image"].items()
                                    if k != "right_wrist_0_rgb"}}
    with pytest.raises(ValueError, match="right_wrist_0_rgb"):
        torch_model.velocity(obs, *_noise_and_time(0))


def test_actions_of_the_wrong_shape_are_a_value_error(torch_model, observation):
    noise, time = _noise_and_time(0)
    with pytest.raises(ValueError, match="action_horizon=4"):
        torch_model.compute_loss(observation, noise[:, :2], np.zeros((BATCH, 2), bool), noise[:, :2],
                                 time, layout=LAYOUT, strategy="uniform")


def test_a_no_state_run_samples_like_flax_in_the_mirror(tmp_path):
    config = CONFIG.replace(use_state=False)
    observation = flax_inputs.fake_observation(config, BATCH, seed=1)
    params = flow_model.init_params(config, jax.random.key(0))
    checkpoint.write_converted(str(tmp_path), {k: np.asarray(v) for k, v in
                                               flatten_tree(params).items()}, config, None,
                               source="test")
    model, _ = checkpoint.load_converted(str(tmp_path))
    noise, _ = _noise_and_time(5)
    expected = np.asarray(flow_model.sample_actions(params, None, observation, config=config,
                                                num_steps=4, noise=jnp.asarray(noise)))
    np.testing.assert_allclose(model.sample_actions(observation, noise, num_steps=4).numpy(),
                               expected, rtol=0, atol=1e-4)
