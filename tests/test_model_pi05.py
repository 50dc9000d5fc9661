"""pi0.5 (docs/design.md §5): openpi's tree, adaptive RMSNorm with gated residuals, the flow time as
the action expert's condition, and the pi0 machinery (K samples, KV-cached sampling) on top."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model, gemma, pi0
from pi0_armfix.model.inputs import fake_observation, preprocess_observation
from pi0_armfix.model.tree import count_params

REFERENCE = Path(__file__).resolve().parent / "reference" / "openpi_param_tree.json"
TINY05 = model_config.get_preset("pi05_tiny")
LAYOUT = ActionLayout.preset("b1k_r1pro")
BATCH = 3


@pytest.fixture(scope="module")
def params():
    """Random params with non-zero adaptive-norm kernels (zero at init: the time would not
    reach the actions, which is openpi's start but hides what the tests look for)."""
    p = flow_model.init_params(TINY05, jax.random.key(0))
    keys = iter(jax.random.split(jax.random.key(1), 8))
    llm = p["PaliGemma"]["llm"]
    for norm in ("pre_attention_norm_1", "pre_ffw_norm_1"):
        dense = llm["layers"][norm]["Dense_0"]
        dense["kernel"] = 0.3 * jax.random.normal(next(keys), dense["kernel"].shape)
        dense["bias"] = 0.3 * jax.random.normal(next(keys), dense["bias"].shape)
    final = llm["final_norm_1"]["Dense_0"]
    final["kernel"] = 0.3 * jax.random.normal(next(keys), final["kernel"].shape)
    return p


def _observation(seed=0):
    return fake_observation(TINY05, BATCH, image_size=(20, 24), seed=seed)


def _x_t_and_t(seed=1, rows=BATCH):
    rng = np.random.default_rng(seed)
    x_t = rng.standard_normal((rows, TINY05.action_horizon, TINY05.action_dim)).astype(np.float32)
    return jnp.asarray(x_t), jnp.asarray(rng.uniform(0.05, 1.0, rows), jnp.float32)


def test_pi05_param_tree_equals_openpi_reference():
    tree = flow_model.param_tree(model_config.get_preset("pi05"))
    assert tree == json.loads(REFERENCE.read_text())["pi05"]
    assert count_params(tree) == 3_353_433_872


@pytest.mark.parametrize("preset", ["pi05_demo", "pi05_tiny"])
def test_small_pi05_presets_use_the_pi05_names(preset):
    names = set(flow_model.param_tree(model_config.get_preset("pi05")))
    assert set(flow_model.param_tree(model_config.get_preset(preset))) == names


def test_adaptive_norm_and_gated_residual_follow_openpi_formula():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((2, 5, 8)).astype(np.float32)
    cond = rng.standard_normal((2, 6)).astype(np.float32)
    kernel = rng.standard_normal((6, 24)).astype(np.float32)
    bias = rng.standard_normal(24).astype(np.float32)
    branch = rng.standard_normal((2, 5, 8)).astype(np.float32)
    out, gate = gemma.RMSNorm().apply({"params": {"Dense_0": {"kernel": kernel, "bias": bias}}},
                                      x, cond)
    residual = gemma.gated_residual(jnp.asarray(x), jnp.asarray(branch), gate)

    modulation = (cond @ kernel + bias)[:, None, :]
    scale, shift, expected_gate = modulation[..., :8], modulation[..., 8:16], modulation[..., 16:]
    normed = x / np.sqrt(np.mean(x**2, axis=-1, keepdims=True) + 1e-6)
    np.testing.assert_allclose(out, normed * (1 + scale) + shift, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(gate, expected_gate, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(residual, x + branch * expected_gate, rtol=1e-5, atol=1e-5)


def test_adaptive_norm_starts_as_the_identity_norm_with_a_closed_gate():
    x = jnp.asarray(np.random.default_rng(0).standard_normal((2, 5, 8)), jnp.float32)
    module = gemma.RMSNorm()
    variables = module.init(jax.random.key(0), x, jnp.ones((2, 6)))
    out, gate = module.apply(variables, x, jnp.ones((2, 6)))
    np.testing.assert_allclose(out, x / jnp.sqrt(jnp.mean(x**2, -1, keepdims=True) + 1e-6),
                               rtol=1e-6)
    np.testing.assert_array_equal(gate, 0.0)


def test_pi05_has_no_state_token_and_ignores_the_state_input(params):
    obs = preprocess_observation(None, _observation(), config=TINY05, train=False)
    x_t, t = _x_t_and_t()
    tokens, _, ar_mask, cond = pi0.embed_suffix(params, obs["state"], x_t, t, config=TINY05)
    assert tokens.shape[1] == TINY05.action_horizon == TINY05.suffix_len
    assert cond.shape == (BATCH, TINY05.action_expert.width)
    assert ar_mask.tolist() == [True] + [False] * (TINY05.action_horizon - 1)
    moved = dict(obs, state=obs["state"] + 5.0)
    np.testing.assert_array_equal(pi0.forward_velocity(params, obs, x_t, t, config=TINY05),
                                  pi0.forward_velocity(params, moved, x_t, t, config=TINY05))


def test_pi05_flow_time_conditions_the_actions(params):
    obs = preprocess_observation(None, _observation(), config=TINY05, train=False)
    x_t, t = _x_t_and_t()
    v = pi0.forward_velocity(params, obs, x_t, t, config=TINY05)
    later = pi0.forward_velocity(params, obs, x_t, t * 0.5, config=TINY05)
    assert float(jnp.max(jnp.abs(v - later))) > 1e-3


def test_pi05_k_flow_samples_equal_separate_passes(params):
    obs = preprocess_observation(None, _observation(), config=TINY05, train=False)
    x_t, t = _x_t_and_t(rows=3 * BATCH)
    together = pi0.forward_velocity(params, obs, x_t, t, config=TINY05, samples=3)
    for k in range(3):
        rows = slice(k * BATCH, (k + 1) * BATCH)
        alone = pi0.forward_velocity(params, obs, x_t[rows], t[rows], config=TINY05)
        np.testing.assert_allclose(together[rows], alone, rtol=1e-5, atol=1e-5)


def test_pi05_kv_cached_sampling_equals_full_recomputation(params):
    noise, _ = _x_t_and_t(seed=4)
    cached = flow_model.sample_actions(params, None, _observation(), config=TINY05, num_steps=5,
                                   noise=noise)
    full = flow_model.sample_actions(params, None, _observation(), config=TINY05, num_steps=5,
                                 noise=noise, use_kv_cache=False)
    np.testing.assert_allclose(cached, full, atol=1e-5)


@pytest.mark.parametrize("strategy, kwargs", [  # the fast lane: the weighted loss, the more general
    pytest.param("uniform", {}, marks=pytest.mark.slow),
    ("per_group", {"group_weights": {g: 2.0 for g in LAYOUT.group_names}})])
def test_pi05_loss_has_finite_gradients_for_every_parameter(params, strategy, kwargs):
    rng = np.random.default_rng(0)
    batch = dict(_observation(),
                 actions=rng.standard_normal((BATCH, TINY05.action_horizon, TINY05.action_dim)
                                             ).astype(np.float32),
                 action_is_pad=np.zeros((BATCH, TINY05.action_horizon), bool))
    loss, grads = jax.jit(jax.value_and_grad(lambda p: flow_model.compute_loss(
        p, jax.random.key(0), batch, config=TINY05, layout=LAYOUT, train=True, strategy=strategy,
        flow_samples=2, **kwargs)[0]))(params)
    assert np.isfinite(loss)
    assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))
    assert float(jnp.abs(grads["time_mlp_in"]["kernel"]).sum()) > 0


@pytest.mark.slow  # a whole training run: the slow lane
def test_pi05_trains_with_correlated_noise_and_gripper_switch_emphasis(params):
    from pi0_armfix.model import noise

    horizon, real = TINY05.action_horizon, LAYOUT.real_dim
    walk = np.cumsum(np.random.default_rng(0).standard_normal((400, horizon, real)), axis=1)
    correlation = np.corrcoef(walk.reshape(400, -1), rowvar=False)
    factor = noise.correlated_noise_factor(correlation, 0.5, horizon=horizon, real_dim=real,
                                           action_dim=TINY05.action_dim)
    rng = np.random.default_rng(1)
    batch = dict(_observation(),
                 actions=rng.standard_normal((BATCH, horizon, TINY05.action_dim)).astype(np.float32),
                 action_is_pad=np.zeros((BATCH, horizon), bool))
    loss, grads = jax.value_and_grad(lambda p: flow_model.compute_loss(
        p, jax.random.key(0), batch, config=TINY05, layout=LAYOUT, train=True, strategy="uniform",
        noise_factor=jnp.asarray(factor), switch_threshold=np.zeros(TINY05.action_dim, np.float32),
        switch_weight=3.0, switch_window=1)[0])(params)
    assert np.isfinite(loss) and all(np.isfinite(g).all() for g in jax.tree.leaves(grads))
