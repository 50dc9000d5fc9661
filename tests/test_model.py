"""pi0 model: parameter tree, flow-matching loss, attention-mask semantics, KV-cached sampling, scan."""

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model, pi0
from pi0_armfix.model import noise as noise_lib
from pi0_armfix.model.inputs import fake_observation, preprocess_observation
from pi0_armfix.model.tree import count_params

REFERENCE = Path(__file__).resolve().parent / "reference" / "openpi_param_tree.json"
TINY = model_config.get_preset("tiny")
LAYOUT = ActionLayout.preset("b1k_r1pro")
BATCH = 3


@pytest.fixture(scope="module")
def params():
    return flow_model.init_params(TINY, jax.random.key(0))


def _observation(seed=0):
    obs = fake_observation(TINY, BATCH, image_size=(20, 24), seed=seed)
    obs["tokenized_prompt_mask"][0, 3:] = False  # a padded prompt
    obs["image_mask"]["right_wrist_0_rgb"][1] = False  # a missing camera
    return obs


def _batch(seed=0):
    rng = np.random.default_rng(seed)
    actions = rng.standard_normal((BATCH, TINY.action_horizon, TINY.action_dim)).astype(np.float32)
    is_pad = np.zeros((BATCH, TINY.action_horizon), bool)
    is_pad[2, -2:] = True
    return dict(_observation(seed), actions=actions, action_is_pad=is_pad)


def _noise_and_time(seed=1):
    rng = jax.random.key(seed)
    noise = jax.random.normal(rng, (BATCH, TINY.action_horizon, TINY.action_dim))
    return noise, jnp.asarray([0.9, 0.5, 0.1])


def _expert_outputs(params, obs, x_t, t):
    """Final prefix and suffix outputs of one joint forward ([B, P, W], [B, S, E]) and the masks."""
    obs = preprocess_observation(None, obs, config=TINY, train=False)
    prefix, prefix_mask, prefix_ar = pi0.embed_prefix(params, obs, config=TINY)
    suffix, suffix_mask, suffix_ar, _ = pi0.embed_suffix(params, obs["state"], x_t, t, config=TINY)
    input_mask = jnp.concatenate([prefix_mask, suffix_mask], axis=1)
    attn_mask = pi0.make_attn_mask(input_mask, jnp.concatenate([prefix_ar, suffix_ar]))
    (prefix_out, suffix_out), _ = pi0.transformer(TINY).apply(
        {"params": params["PaliGemma"]["llm"]}, [prefix, suffix], jnp.cumsum(input_mask, 1) - 1,
        attn_mask)
    return prefix_out, suffix_out, prefix_mask


# ------------------------------------------------------------------------------ parameter tree


def test_pi0_param_tree_equals_openpi_reference():
    expected = json.loads(REFERENCE.read_text())["pi0"]
    tree = flow_model.param_tree(model_config.get_preset("pi0"))
    assert tree == expected
    assert count_params(tree) == 3_238_048_528


@pytest.mark.parametrize("preset", ["demo", "tiny"])
def test_small_presets_use_the_pi0_names(preset):
    pi0_names = set(flow_model.param_tree(model_config.get_preset("pi0")))
    assert set(flow_model.param_tree(model_config.get_preset(preset))) == pi0_names


def test_config_round_trips_through_json():
    for name in model_config.PRESETS:
        config = model_config.get_preset(name)
        assert model_config.Pi0Config.from_dict(json.loads(json.dumps(config.to_dict()))) == config


def test_experts_with_different_head_layout_are_rejected():
    expert = TINY.action_expert
    with pytest.raises(ValueError, match="head_dim"):
        TINY.replace(action_expert=model_config.GemmaConfig(
            width=expert.width, depth=expert.depth, mlp_dim=expert.mlp_dim,
            num_heads=expert.num_heads, num_kv_heads=expert.num_kv_heads, head_dim=16))


def test_unknown_preset_is_named():
    with pytest.raises(ValueError, match="'huge'"):
        model_config.get_preset("huge")


# ------------------------------------------------------------------------------ loss


def test_compute_loss_returns_scalar_and_group_losses_with_finite_gradients(params):
    def loss_fn(p):
        return flow_model.compute_loss(p, jax.random.key(3), _batch(), config=TINY, layout=LAYOUT,
                                   train=True, strategy="uniform")

    (loss, aux), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(params)
    assert loss.shape == () and np.isfinite(loss)
    assert set(aux["group_loss"]) == set(LAYOUT.group_names)
    assert jax.tree.structure(grads) == jax.tree.structure(params)
    assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))


def test_compute_loss_is_flow_matching_on_the_velocity(params):
    """uniform strategy, no augmentation: mean over valid (b, h) of mean_d (v - (noise - a))^2."""
    batch, rng = _batch(), jax.random.key(4)
    loss, _ = jax.jit(lambda p, b: flow_model.compute_loss(
        p, rng, b, config=TINY, layout=LAYOUT, train=False, strategy="uniform"))(params, batch)
    _, rng_noise, rng_time = jax.random.split(rng, 3)
    actions = batch["actions"]
    noise = jax.random.normal(rng_noise, actions.shape)
    t = jax.random.beta(rng_time, 1.5, 1.0, (BATCH,)) * 0.999 + 0.001
    x_t = t[:, None, None] * noise + (1 - t[:, None, None]) * actions
    v = flow_model.velocity(params, batch, x_t, t, config=TINY)
    per_step = np.mean(np.square(v - (noise - actions)), axis=-1)
    expected = per_step[~batch["action_is_pad"]].mean()
    np.testing.assert_allclose(loss, expected, rtol=1e-6)


def test_actions_of_the_wrong_horizon_are_rejected(params):
    batch = _batch()
    batch["actions"] = batch["actions"][:, :2]
    with pytest.raises(ValueError, match="action_horizon"):
        flow_model.compute_loss(params, jax.random.key(0), batch, config=TINY, layout=LAYOUT,
                            train=False, strategy="uniform")


def test_bfloat16_activations_keep_float32_params_and_outputs():
    config = TINY.replace(dtype="bfloat16")
    params = flow_model.init_params(config, jax.random.key(0))
    noise, t = _noise_and_time()
    v16 = flow_model.velocity(params, _observation(), noise, t, config=config)
    v32 = flow_model.velocity(params, _observation(), noise, t, config=TINY)
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(params))
    assert v16.dtype == jnp.float32
    np.testing.assert_allclose(v16, v32, atol=0.1 * float(np.abs(v32).max()))


# ------------------------------------------------------------------------------ attention mask


def test_attention_mask_blocks():
    """Prefix bidirectional and blind to the suffix; state sees prefix + itself; actions see all."""
    prefix_mask = jnp.asarray([[True, True, False]])
    suffix_ar = jnp.asarray([True, True, False])  # state, action 0, action 1
    mask = pi0.make_attn_mask(jnp.concatenate([prefix_mask, jnp.ones((1, 3), bool)], axis=1),
                              jnp.concatenate([jnp.zeros(3, bool), suffix_ar]))
    expected = np.asarray([
        # p0 p1 pad st a0 a1   (keys)
        [1, 1, 0, 0, 0, 0],  # p0
        [1, 1, 0, 0, 0, 0],  # p1
        [0, 0, 0, 0, 0, 0],  # pad
        [1, 1, 0, 1, 0, 0],  # state
        [1, 1, 0, 1, 1, 1],  # a0
        [1, 1, 0, 1, 1, 1],  # a1
    ], bool)
    np.testing.assert_array_equal(mask[0], expected)


@pytest.mark.slow  # a forward compilation per action input
def test_prefix_and_state_outputs_do_not_depend_on_the_actions(params):
    noise, t = _noise_and_time()
    prefix_a, suffix_a, prefix_mask = _expert_outputs(params, _observation(), noise, t)
    prefix_b, suffix_b, _ = _expert_outputs(params, _observation(), noise * 3.0 + 1.0, t[::-1])
    valid = np.asarray(prefix_mask)
    np.testing.assert_array_equal(np.asarray(prefix_a)[valid], np.asarray(prefix_b)[valid])
    np.testing.assert_array_equal(suffix_a[:, 0], suffix_b[:, 0])  # the state token
    assert not np.allclose(suffix_a[:, 1:], suffix_b[:, 1:])  # the action tokens do change


def test_masked_camera_pixels_do_not_reach_the_actions(params):
    noise, t = _noise_and_time()
    obs = _observation()
    base = flow_model.velocity(params, obs, noise, t, config=TINY)
    masked = _observation()
    masked["image"]["right_wrist_0_rgb"][1] = 255 - masked["image"]["right_wrist_0_rgb"][1]
    np.testing.assert_allclose(flow_model.velocity(params, masked, noise, t, config=TINY)[1], base[1],
                               atol=1e-6)
    seen = _observation()
    seen["image"]["base_0_rgb"][1] = 255 - seen["image"]["base_0_rgb"][1]
    assert not np.allclose(flow_model.velocity(params, seen, noise, t, config=TINY)[1], base[1], atol=1e-4)


# ------------------------------------------------------------------------------ sampling


def test_kv_cached_sampling_equals_full_recomputation(params):
    noise, _ = _noise_and_time()
    cached = flow_model.sample_actions(params, None, _observation(), config=TINY, num_steps=10, noise=noise)
    full = flow_model.sample_actions(params, None, _observation(), config=TINY, num_steps=10, noise=noise,
                  use_kv_cache=False)
    assert cached.shape == (BATCH, TINY.action_horizon, TINY.action_dim)
    np.testing.assert_allclose(cached, full, atol=1e-5)


def test_sampling_integrates_the_velocity_with_euler_steps(params):
    noise, _ = _noise_and_time()
    obs = _observation()
    x, t = noise, 1.0
    for _ in range(2):
        x = x - 0.5 * flow_model.velocity(params, obs, x, jnp.full((BATCH,), t), config=TINY)
        t -= 0.5
    sampled = flow_model.sample_actions(params, None, obs, config=TINY, num_steps=2, noise=noise)
    np.testing.assert_allclose(sampled, x, atol=1e-5)


def test_soft_inpainting_pins_full_weight_steps_and_leaves_zero_weight_steps_free(params):
    noise, _ = _noise_and_time()
    obs = _observation()
    target = np.random.default_rng(3).standard_normal(noise.shape).astype(np.float32)
    weights = np.zeros((BATCH, TINY.action_horizon), np.float32)
    weights[:, :2] = 1.0
    free = flow_model.sample_actions(params, None, obs, config=TINY, num_steps=4, noise=noise)
    guided = flow_model.sample_actions(params, None, obs, config=TINY, num_steps=4, noise=noise,
                                   inpaint=target, inpaint_weights=weights)
    np.testing.assert_allclose(guided[:, :2], target[:, :2], atol=1e-5)
    unguided = flow_model.sample_actions(params, None, obs, config=TINY, num_steps=4, noise=noise,
                                     inpaint=target, inpaint_weights=np.zeros_like(weights))
    np.testing.assert_allclose(unguided, free, atol=1e-6)


def test_sampling_is_deterministic_given_the_rng(params):
    a = flow_model.sample_actions(params, jax.random.key(7), _observation(), config=TINY, num_steps=2)
    b = flow_model.sample_actions(params, jax.random.key(7), _observation(), config=TINY, num_steps=2)
    np.testing.assert_array_equal(a, b)


def _noise_of(rng, draws):
    return noise_lib.flow_noise(rng, (draws * BATCH, TINY.action_horizon, TINY.action_dim))


@pytest.mark.slow  # a sampler compilation per draw count
def test_every_draw_of_several_is_the_single_draw_from_its_own_noise(params):
    noise = _noise_of(jax.random.key(5), 3)
    draws = flow_model.sample_actions(params, jax.random.key(5), _observation(), config=TINY,
                                      num_steps=3, num_draws=3)
    assert draws.shape == (3, BATCH, TINY.action_horizon, TINY.action_dim)
    for j in range(3):
        single = flow_model.sample_actions(params, None, _observation(), config=TINY, num_steps=3,
                                           noise=noise[j * BATCH:(j + 1) * BATCH])
        np.testing.assert_allclose(draws[j], single, atol=1e-5)


def test_several_draws_share_the_prefix_and_equal_full_recomputation(params):
    noise = _noise_of(jax.random.key(2), 2)
    cached = flow_model.sample_actions(params, None, _observation(), config=TINY, num_steps=2,
                                       noise=noise, num_draws=2)
    full = flow_model.sample_actions(params, None, _observation(), config=TINY, num_steps=2,
                                     noise=noise, num_draws=2, use_kv_cache=False)
    np.testing.assert_allclose(cached, full, atol=1e-5)


def test_the_mean_of_n_draws_is_reproducible_for_a_seed_and_the_mean_of_the_draws(params):
    kwargs = dict(config=TINY, num_steps=2, average_draws=4)
    a = flow_model.sample_actions(params, jax.random.key(9), _observation(), **kwargs)
    b = flow_model.sample_actions(params, jax.random.key(9), _observation(), **kwargs)
    np.testing.assert_array_equal(a, b)
    draws = flow_model.sample_actions(params, jax.random.key(9), _observation(), config=TINY,
                                      num_steps=2, num_draws=4)
    np.testing.assert_allclose(a, np.mean(draws, axis=0), atol=1e-6)
    other = flow_model.sample_actions(params, jax.random.key(10), _observation(), **kwargs)
    assert not np.allclose(a, other)


def test_the_temperature_scales_the_initial_noise_and_is_reproducible_for_a_seed(params):
    kwargs = dict(config=TINY, num_steps=2, temperature=0.5)
    a = flow_model.sample_actions(params, jax.random.key(4), _observation(), **kwargs)
    b = flow_model.sample_actions(params, jax.random.key(4), _observation(), **kwargs)
    np.testing.assert_array_equal(a, b)
    scaled = flow_model.sample_actions(params, None, _observation(), config=TINY, num_steps=2,
                                       noise=0.5 * _noise_of(jax.random.key(4), 1))
    np.testing.assert_allclose(a, scaled, atol=1e-6)


# ------------------------------------------------------------------------------ scan over depth


def _with_depth(depth):
    def expert(cfg):
        return model_config.GemmaConfig(**{**cfg.__dict__, "depth": depth})

    siglip = model_config.SiglipConfig(**{**TINY.siglip.__dict__, "depth": depth})
    return TINY.replace(paligemma=expert(TINY.paligemma), action_expert=expert(TINY.action_expert),
                        siglip=siglip)


def test_layers_are_stacked_along_depth():
    shapes = flow_model.param_shapes(_with_depth(5))
    assert shapes["PaliGemma"]["llm"]["layers"]["attn"]["q_einsum_1"]["w"].shape[0] == 5
    encoder = shapes["PaliGemma"]["img"]["Transformer"]["encoderblock"]
    assert encoder["LayerNorm_0"]["scale"].shape[0] == 5


def test_compiled_program_size_does_not_grow_with_depth():
    def hlo_size(depth):
        config = _with_depth(depth)
        params = flow_model.param_shapes(config)

        def loss(p, b):
            return flow_model.compute_loss(p, jax.random.key(0), b, config=config, layout=LAYOUT,
                                       train=True, strategy="uniform")[0]

        return len(jax.jit(jax.grad(loss)).lower(params, _batch()).as_text())

    shallow, deep = hlo_size(2), hlo_size(8)
    assert math.isclose(shallow, deep, rel_tol=0.05), (shallow, deep)


@pytest.mark.slow  # two compilations of the whole tiny model
def test_unrolled_layers_compute_what_the_scan_computes(params):
    unrolled = TINY.replace(unroll_layers=True)
    batch, rng = _batch(), jax.random.key(3)
    scanned_loss = flow_model.compute_loss(params, rng, batch, config=TINY, layout=LAYOUT, train=True,
                                       strategy="uniform")[0]
    unrolled_loss = flow_model.compute_loss(params, rng, batch, config=unrolled, layout=LAYOUT,
                                        train=True, strategy="uniform")[0]
    np.testing.assert_allclose(unrolled_loss, scanned_loss, rtol=1e-6)


def _plain_pi0_loss(params, rng, batch):
    """The pi0 loss as it was before K flow samples existed (one draw per sample)."""
    actions = jnp.asarray(batch["actions"], jnp.float32)
    rng_augment, rng_noise, rng_time = jax.random.split(rng, 3)
    observation = preprocess_observation(rng_augment, batch, config=TINY, train=True)
    noise = jax.random.normal(rng_noise, actions.shape)
    t = jax.random.beta(rng_time, 1.5, 1.0, actions.shape[:1]) * 0.999 + 0.001
    x_t = t[:, None, None] * noise + (1.0 - t[:, None, None]) * actions
    v = pi0.forward_velocity(params, observation, x_t, t, config=TINY)
    valid = ~jnp.asarray(batch["action_is_pad"])
    per_step = jnp.mean(jnp.square(v - (noise - actions)), axis=-1)
    return jnp.sum(per_step * valid) / jnp.sum(valid)


@pytest.mark.slow  # two gradient compilations
def test_one_flow_sample_is_the_plain_pi0_loss_bitwise(params):
    batch, rng = _batch(), jax.random.key(5)
    plain = jax.jit(jax.value_and_grad(lambda p: _plain_pi0_loss(p, rng, batch)))(params)
    one = jax.jit(jax.value_and_grad(lambda p: flow_model.compute_loss(
        p, rng, batch, config=TINY, layout=LAYOUT, train=True, strategy="uniform",
        flow_samples=1)[0]))(params)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(one)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.slow  # a forward compilation per sample count
def test_k_flow_samples_share_the_prefix_and_never_see_each_other(params):
    obs = preprocess_observation(None, _observation(), config=TINY, train=False)
    rng = np.random.default_rng(0)
    x_t = jnp.asarray(rng.standard_normal((3 * BATCH, TINY.action_horizon, TINY.action_dim)),
                      jnp.float32)
    t = jnp.asarray(rng.uniform(0.05, 1.0, 3 * BATCH), jnp.float32)
    together = pi0.forward_velocity(params, obs, x_t, t, config=TINY, samples=3)
    for k in range(3):
        rows = slice(k * BATCH, (k + 1) * BATCH)
        alone = pi0.forward_velocity(params, obs, x_t[rows], t[rows], config=TINY)
        np.testing.assert_allclose(together[rows], alone, rtol=1e-5, atol=1e-5)


@pytest.mark.slow  # k + 1 forward compilations
def test_k_flow_samples_are_the_exact_mean_of_the_k_single_draw_losses_under_the_same_draws(
        params):
    batch, k = _batch(), 4
    loss, _ = flow_model.compute_loss(params, jax.random.key(6), batch, config=TINY, layout=LAYOUT,
                                      train=False, strategy="uniform", flow_samples=k)
    # The same draws, made as compute_loss makes them, then each draw's plain pi0 loss alone.
    _, rng_noise, rng_time = jax.random.split(jax.random.key(6), 3)
    actions = jnp.tile(jnp.asarray(batch["actions"], jnp.float32), (k, 1, 1))
    noise = jax.random.normal(rng_noise, actions.shape)
    t = jax.random.beta(rng_time, 1.5, 1.0, (len(actions),)) * 0.999 + 0.001
    x_t = t[:, None, None] * noise + (1.0 - t[:, None, None]) * actions
    obs = preprocess_observation(None, batch, config=TINY, train=False)
    valid = ~jnp.asarray(batch["action_is_pad"])
    single = []
    for draw in range(k):
        rows = slice(draw * BATCH, (draw + 1) * BATCH)
        v = pi0.forward_velocity(params, obs, x_t[rows], t[rows], config=TINY)
        per_step = jnp.mean(jnp.square(v - (noise[rows] - actions[rows])), axis=-1)
        single.append(float(jnp.sum(per_step * valid) / jnp.sum(valid)))
    assert len(set(single)) == k  # four different draws
    np.testing.assert_allclose(float(loss), np.mean(single), rtol=1e-5)


def test_correlated_noise_has_the_configured_covariance():
    from pi0_armfix.model import noise as noise_lib
    rng = np.random.default_rng(0)
    horizon, width = 4, 3
    basis = rng.standard_normal((horizon * width, horizon * width))
    cov = basis @ basis.T
    correlation = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    factor = noise_lib.correlated_noise_factor(correlation, beta=0.3)
    draws = np.asarray(noise_lib.flow_noise(jax.random.key(0), (200_000, horizon, width),
                                         jnp.asarray(factor)))
    empirical = np.cov(draws.reshape(len(draws), -1), rowvar=False)
    expected = 0.3 * np.eye(horizon * width) + 0.7 * correlation
    np.testing.assert_allclose(empirical, expected, atol=0.015)
