"""The loss strategies of docs/design.md §3, one behaviour per test."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_armfix import loss as L
from pi0_armfix.action_space import ActionLayout

B1K = ActionLayout.preset("b1k_r1pro")
ARM_WEIGHTS = {"base": 1.0, "torso": 1.0, "left_arm": 3.0, "left_gripper": 3.0, "right_arm": 3.0,
               "right_gripper": 3.0}
EQUAL_WEIGHTS = {g: 2.0 for g in B1K.group_names}
DIM_WEIGHTS = np.r_[np.linspace(0.5, 3.0, 23), np.zeros(9)].astype(np.float32)
LOG_VARS = jnp.linspace(-1.0, 1.0, 6)

# (strategy, kwargs) for every strategy, with and without delta weighting where it applies.
CASES = {
    "uniform": dict(strategy="uniform"),
    "original": dict(strategy="original"),
    "per_group": dict(strategy="per_group", group_weights=ARM_WEIGHTS),
    "per_group_delta": dict(strategy="per_group", group_weights=ARM_WEIGHTS, delta_weighting=True),
    "per_dimension": dict(strategy="per_dimension", dimension_weights=DIM_WEIGHTS),
    "per_dimension_delta": dict(strategy="per_dimension", dimension_weights=DIM_WEIGHTS,
                                delta_weighting=True),
    "loss_balanced": dict(strategy="loss_balanced", group_weights=ARM_WEIGHTS),
    "uncertainty": dict(strategy="uncertainty", log_vars=LOG_VARS),
    "uncertainty_delta": dict(strategy="uncertainty", log_vars=LOG_VARS, group_weights=ARM_WEIGHTS,
                              delta_weighting=True),
}
PADDING_TRAINED = ("uniform", "original")


def _inputs(b=4, h=10, seed=0):
    rng = np.random.default_rng(seed)
    e = rng.uniform(0.0, 2.0, (b, h, 32)).astype(np.float32)
    actions = np.cumsum(rng.normal(0, 0.3, (b, h, 32)), axis=1).astype(np.float32)
    actions[..., 23:] = 0.0
    return jnp.asarray(e), jnp.asarray(actions)


@pytest.mark.parametrize("case", sorted(CASES))
def test_output_shape_is_batch_by_horizon(case):
    e, a = _inputs(3, 7)
    assert L.compute_weighted_loss(e, a, layout=B1K, **CASES[case]).shape == (3, 7)


def test_uniform_equals_mean_over_all_dims_exactly():
    e, a = _inputs()
    np.testing.assert_array_equal(L.compute_weighted_loss(e, a, strategy="uniform", layout=B1K),
                                  jnp.mean(e, -1))


def test_per_group_with_equal_weights_equals_mean_over_real_dims():
    e, a = _inputs()
    out = L.compute_weighted_loss(e, a, strategy="per_group", layout=B1K, group_weights=EQUAL_WEIGHTS)
    np.testing.assert_allclose(out, jnp.mean(e[..., :23], -1), rtol=1e-6)


def test_per_dimension_with_equal_real_weights_matches_per_group_with_equal_weights():
    e, a = _inputs()
    dims = np.r_[np.ones(23), np.zeros(9)]
    np.testing.assert_allclose(
        L.compute_weighted_loss(e, a, strategy="per_dimension", layout=B1K, dimension_weights=dims),
        L.compute_weighted_loss(e, a, strategy="per_group", layout=B1K, group_weights=EQUAL_WEIGHTS),
        rtol=1e-6)


@pytest.mark.parametrize("case", ["per_group", "per_dimension", "per_group_delta"])
def test_static_weights_are_normalized_so_their_scale_does_not_matter(case):
    e, a = _inputs()
    kwargs = dict(CASES[case])
    scaled = dict(kwargs)
    if "group_weights" in kwargs:
        scaled["group_weights"] = {g: 7.0 * w for g, w in kwargs["group_weights"].items()}
    else:
        scaled["dimension_weights"] = 7.0 * kwargs["dimension_weights"]
    np.testing.assert_allclose(L.compute_weighted_loss(e, a, layout=B1K, **kwargs),
                               L.compute_weighted_loss(e, a, layout=B1K, **scaled), rtol=1e-6)


def test_static_weights_have_mean_one_over_all_action_dims():
    w = L.static_dim_weights("per_group", B1K, ARM_WEIGHTS)
    np.testing.assert_allclose(jnp.mean(w), 1.0, rtol=1e-6)
    assert float(w[7]) == pytest.approx(3.0 * float(w[0]))


@pytest.mark.parametrize("case", sorted(CASES))
def test_padding_dims_get_zero_gradient_except_uniform_and_original(case):
    e, a = _inputs()
    grad = jax.grad(lambda x: jnp.sum(L.compute_weighted_loss(x, a, layout=B1K, **CASES[case])))(e)
    if case in PADDING_TRAINED:
        assert np.all(np.asarray(grad[..., 23:]) > 0)
    else:
        np.testing.assert_array_equal(grad[..., 23:], 0.0)
        assert np.all(np.asarray(grad[..., :23]) > 0)


@pytest.mark.parametrize("case", sorted(CASES))
def test_weights_carry_no_gradient_into_the_actions(case):
    e, a = _inputs()
    grad = jax.grad(lambda x: jnp.sum(L.compute_weighted_loss(e, x, layout=B1K, **CASES[case])))(a)
    np.testing.assert_array_equal(grad, 0.0)


@pytest.mark.parametrize("case", ["per_group_delta", "per_dimension_delta", "uncertainty_delta"])
def test_delta_weighted_loss_of_a_batch_is_the_concatenation_of_its_halves(case):
    e, a = _inputs(b=6)
    whole = L.compute_weighted_loss(e, a, layout=B1K, **CASES[case])
    halves = [L.compute_weighted_loss(e[s], a[s], layout=B1K, **CASES[case])
              for s in (slice(0, 3), slice(3, 6))]
    np.testing.assert_allclose(whole, jnp.concatenate(halves), rtol=1e-6)


def test_original_weighting_depends_on_the_rest_of_the_batch():
    e, a = _inputs(b=6)
    a = a.at[3:].set(0.0)  # a still second half lowers the batch mean weight
    whole = L.compute_weighted_loss(e, a, strategy="original", layout=B1K)
    half = L.compute_weighted_loss(e[:3], a[:3], strategy="original", layout=B1K)
    assert not np.allclose(whole[:3], half, rtol=1e-4)


def test_delta_scale_has_mean_one_over_horizon_per_sample_and_group():
    _, a = _inputs()
    c = L.delta_scale(a, B1K)
    assert c.shape == (4, 10, 6)
    np.testing.assert_allclose(jnp.mean(c, axis=1), 1.0, rtol=1e-6)


def test_delta_scale_follows_the_clipped_motion_formula():
    a = np.zeros((1, 3, 32), np.float32)
    a[0, 1, 0] = 0.3   # base moves 0.3 at h=1
    a[0, 2, 0] = 1.3   # and 1.0 at h=2 (min(., 0.5) caps it)
    raw = np.array([0.2, 0.5, 0.7])
    np.testing.assert_allclose(L.delta_scale(jnp.asarray(a), B1K)[0, :, 0], raw / raw.mean(), rtol=1e-6)


def test_original_weights_follow_the_clipped_full_norm_and_have_batch_mean_one():
    a = np.zeros((1, 3, 32), np.float32)
    a[0, 1, :2] = 0.3, 0.4   # ||Δ|| = 0.5
    raw = np.array([0.2, 0.7, 0.7])  # the step back is a motion too
    np.testing.assert_allclose(L.original_temporal_weights(jnp.asarray(a))[0], raw / raw.mean(),
                               rtol=1e-6)


def test_loss_balanced_equals_per_group_with_the_same_effective_weights():
    e, a = _inputs()
    np.testing.assert_array_equal(
        L.compute_weighted_loss(e, a, layout=B1K, **CASES["loss_balanced"]),
        L.compute_weighted_loss(e, a, layout=B1K, **CASES["per_group"]))


def test_uncertainty_loss_is_the_kendall_objective_over_group_losses():
    e, a = _inputs()
    pad = np.zeros((4, 10), bool)
    pad[:, 7:] = True
    loss, aux = L.training_loss(e, a, pad, layout=B1K, strategy="uncertainty", log_vars=LOG_VARS)
    groups = np.array([aux["group_loss"][g] for g in B1K.group_names])
    expected = np.sum(np.exp(-np.asarray(LOG_VARS)) * groups + np.asarray(LOG_VARS))
    np.testing.assert_allclose(loss, expected, rtol=1e-6)


def test_uncertainty_log_variance_gradient_is_one_minus_precision_times_group_loss():
    e, a = _inputs()
    pad = jnp.zeros((4, 10), bool)
    grad = jax.grad(lambda s: L.training_loss(e, a, pad, layout=B1K, strategy="uncertainty",
                                              log_vars=s)[0])(LOG_VARS)
    groups = np.array(list(L.per_group_losses(e, B1K).values()))
    np.testing.assert_allclose(grad, 1.0 - np.exp(-np.asarray(LOG_VARS)) * groups, rtol=1e-5)


def test_uncertainty_log_variance_is_clamped_from_below():
    e, a = _inputs()
    s = jnp.full((6,), -20.0)
    out = L.compute_weighted_loss(e, a, strategy="uncertainty", layout=B1K, log_vars=s, min_log_var=-2.0)
    clamped = L.compute_weighted_loss(e, a, strategy="uncertainty", layout=B1K,
                                      log_vars=jnp.full((6,), -2.0), min_log_var=-2.0)
    np.testing.assert_array_equal(out, clamped)


def test_training_loss_excludes_padded_timesteps():
    e, a = _inputs()
    pad = np.zeros((4, 10), bool)
    pad[:, 6:] = True
    changed = e.at[:, 6:].set(100.0)
    for case in CASES.values():
        np.testing.assert_allclose(L.training_loss(e, a, pad, layout=B1K, **case)[0],
                                   L.training_loss(changed, a, pad, layout=B1K, **case)[0], rtol=1e-6)


def test_per_group_losses_are_unweighted_group_means_over_valid_steps():
    e, _ = _inputs()
    valid = np.ones((4, 10), bool)
    valid[0, 5:] = False
    got = L.per_group_losses(e, B1K, valid)
    e_np = np.asarray(e)
    for g, (start, stop) in B1K.groups.items():
        np.testing.assert_allclose(got[g], e_np[valid][:, start:stop].mean(), rtol=1e-6)


def test_weights_can_be_traced_inside_jit():
    e, a = _inputs()

    @jax.jit
    def f(scale):
        weights = {g: w * scale for g, w in ARM_WEIGHTS.items()}
        return L.compute_weighted_loss(e, a, strategy="per_group", layout=B1K, group_weights=weights,
                                       delta_weighting=True)

    np.testing.assert_allclose(f(2.0), L.compute_weighted_loss(e, a, layout=B1K, **CASES["per_group_delta"]),
                               rtol=1e-6)


def test_compute_weighted_loss_jits_with_static_strategy_and_layout():
    e, a = _inputs()
    f = jax.jit(functools.partial(L.compute_weighted_loss, strategy="per_group", layout=B1K,
                                  group_weights=ARM_WEIGHTS, delta_weighting=True))
    np.testing.assert_allclose(f(e, a), L.compute_weighted_loss(e, a, layout=B1K, **CASES["per_group_delta"]),
                               rtol=1e-6)


def test_group_weight_warmup_ramps_linearly_from_one_to_target():
    target = {"base": 1.0, "left_arm": 3.0}
    assert float(L.warmup_group_weights(target, 0, 100)["left_arm"]) == 1.0
    assert float(L.warmup_group_weights(target, 50, 100)["left_arm"]) == pytest.approx(2.0)
    assert float(L.warmup_group_weights(target, 500, 100)["left_arm"]) == 3.0
    assert float(L.warmup_group_weights(target, 0, 0)["left_arm"]) == 3.0


def test_dimension_weight_warmup_keeps_padding_at_zero():
    w = L.warmup_dimension_weights(DIM_WEIGHTS, 10, 100, B1K)
    np.testing.assert_array_equal(w[23:], 0.0)
    np.testing.assert_allclose(w[:23], 1.0 + (DIM_WEIGHTS[:23] - 1.0) * 0.1, rtol=1e-6)


def test_group_loss_ema_takes_the_first_losses_as_they_are_then_decays():
    ema, count = L.update_group_loss_ema(jnp.zeros(2), jnp.int32(0), jnp.array([4.0, 2.0]), 0.9)
    np.testing.assert_allclose(ema, [4.0, 2.0])
    ema, count = L.update_group_loss_ema(ema, count, jnp.array([0.0, 2.0]), 0.9)
    np.testing.assert_allclose(ema, [3.6, 2.0], rtol=1e-6)
    assert int(count) == 2


def test_loss_balanced_weights_favour_the_group_with_lower_loss_within_the_clamp():
    w = L.loss_balanced_weights(jnp.array([1.0, 4.0, 1000.0]), jnp.array([1.0, 1.0, 2.0]),
                                w_min=0.1, w_max=5.0)
    inverse = np.array([1.0, 0.25, 0.001])
    expected = np.clip(inverse / inverse.mean(), 0.1, 5.0) * [1.0, 1.0, 2.0]
    np.testing.assert_allclose(w, expected, rtol=1e-6)
    assert float(w[0]) > float(w[1])


@pytest.mark.parametrize("kwargs, match", [
    (dict(strategy="mse"), r"unknown loss strategy 'mse'"),
    (dict(strategy="per_group"), r"'per_group' needs group_weights"),
    (dict(strategy="per_dimension"), r"'per_dimension' needs dimension_weights"),
    (dict(strategy="uncertainty"), r"'uncertainty' needs log_vars of shape \(6,\)"),
    (dict(strategy="uniform", delta_weighting=True), r"delta_weighting=True has no meaning .*'uniform'"),
    (dict(strategy="per_group", group_weights={"base": 1.0}), r"missing group\(s\)"),
    (dict(strategy="per_dimension", dimension_weights=np.ones(32)), r"dimension_weights\[23\] = 1.0 is non-zero"),
])
def test_bad_loss_arguments_raise_a_value_error_naming_the_culprit(kwargs, match):
    e, a = _inputs()
    with pytest.raises(ValueError, match=match):
        L.compute_weighted_loss(e, a, layout=B1K, **kwargs)


def test_per_dim_loss_of_the_wrong_width_names_the_expected_shape():
    e, a = _inputs()
    with pytest.raises(ValueError, match=r"expected \[B, H, 32\]"):
        L.compute_weighted_loss(e[..., :23], a[..., :23], strategy="uniform", layout=B1K)


@pytest.mark.parametrize("case", ["original", "per_group_delta", "uncertainty_delta"])
def test_time_normalized_weights_ignore_the_padded_tail_of_a_chunk(case):
    e, a = _inputs()
    pad = np.zeros((4, 10), bool)
    pad[:, 6:] = True
    tail = a.at[:, 6:].set(a[:, 5:6])  # the chunker repeats the episode's last frame
    padded = L.training_loss(e, tail, pad, layout=B1K, **CASES[case])[0]
    cut = L.training_loss(e[:, :6], a[:, :6], pad[:, :6], layout=B1K, **CASES[case])[0]
    np.testing.assert_allclose(padded, cut, rtol=1e-6)


def _gripper_chunk(switch_at=None, h=12):
    """One B1K chunk whose left gripper (dim 14) goes from 1 to -1 at `switch_at`."""
    a = np.zeros((1, h, 32), np.float32)
    a[..., 14] = 1.0
    if switch_at is not None:
        a[0, switch_at:, 14] = -1.0
    return jnp.asarray(a)


def test_switch_emphasis_weighs_the_steps_around_a_gripper_switch():
    w = L.switch_emphasis(_gripper_chunk(switch_at=5), None, B1K, threshold=np.zeros(32),
                          weight=4.0, window=2)
    np.testing.assert_array_equal(w[0], [1, 1, 1, 4, 4, 4, 4, 4, 1, 1, 1, 1])


def test_switch_emphasis_is_one_without_a_switch_and_ignores_padded_steps():
    kwargs = dict(threshold=np.zeros(32), weight=4.0, window=2)
    np.testing.assert_array_equal(L.switch_emphasis(_gripper_chunk(), None, B1K, **kwargs), 1.0)
    valid = np.ones((1, 12), bool)
    valid[0, 8:] = False  # the switch at step 9 lies past the episode end
    np.testing.assert_array_equal(
        L.switch_emphasis(_gripper_chunk(switch_at=9), valid, B1K, **kwargs), 1.0)


def test_switch_emphasis_scales_the_loss_of_the_emphasized_steps():
    a = _gripper_chunk(switch_at=5)
    e = jnp.ones((1, 12, 32))
    pad = np.zeros((1, 12), bool)
    plain = L.training_loss(e, a, pad, layout=B1K, strategy="uniform")[0]
    emphasized = L.training_loss(e, a, pad, layout=B1K, strategy="uniform",
                                 switch_threshold=np.zeros(32), switch_weight=4.0,
                                 switch_window=2)[0]
    np.testing.assert_allclose(emphasized, plain * (7 + 5 * 4) / 12, rtol=1e-6)


@pytest.mark.parametrize("strategy", L.STRATEGIES)
def test_train_state_carries_the_log_variances_and_ema_its_strategy_declares(strategy):
    import optax

    from pi0_armfix.model.config import get_preset
    from pi0_armfix.training.state import create_train_state

    spec = L.loss_strategy(strategy)
    state = create_train_state({"w": jnp.zeros(3)}, model_config=get_preset("tiny"),
                               tx=optax.sgd(0.1), loss_cfg={"strategy": strategy},
                               layout=B1K, ema_decay=0.0)
    assert ("log_vars" in state.loss_params) == spec.learns_log_vars
    assert ("ema" in state.balancer) == spec.balances
    assert spec.learns_log_vars == (strategy == "uncertainty")
    assert spec.balances == (strategy == "loss_balanced")


@pytest.mark.parametrize("per_timestep", [False, True])
def test_a_groups_logged_loss_is_its_mean_over_the_dims_that_carry_loss(per_timestep):
    # The demo's torso: dim 6 is constant, masked out of the loss (its e is 0).
    layout = ActionLayout.preset("b1k_r1pro")
    live = np.ones(layout.action_dim, np.float32)
    live[6] = 0.0
    if per_timestep:
        live = np.tile(live, (4, 1))
    e = np.ones((2, 4, layout.action_dim), np.float32) * live
    losses = L.per_group_losses(jnp.asarray(e), layout, live=live)
    assert float(losses["torso"]) == 1.0  # not 3/4
    assert float(losses["left_arm"]) == 1.0


def test_uncertaintys_group_means_skip_the_dims_that_carry_no_loss():
    layout = ActionLayout.preset("b1k_r1pro")
    live = np.ones(layout.action_dim, np.float32)
    live[6] = 0.0
    e = np.ones((1, 2, layout.action_dim), np.float32) * live
    zeros = jnp.zeros(layout.num_groups)
    per_step = L.compute_weighted_loss(jnp.asarray(e), jnp.zeros_like(e),
                                              strategy="uncertainty", layout=layout,
                                              log_vars=zeros, live=live)
    np.testing.assert_allclose(per_step, layout.num_groups)  # every group's mean error is 1
