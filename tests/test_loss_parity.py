"""JAX and PyTorch losses agree to 1e-6 relative in float32, values and gradients
(docs/design.md §3)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pi0_armfix import loss as jl
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.torch_mirror import loss as tl

# Relative tolerance per element, plus 1e-6 of the array's largest magnitude for elements that are
# a cancellation of larger terms (e.g. the log-variance gradient 1 - exp(-s) L near 0).
RTOL, ATOL = 1e-6, 1e-6
SETTINGS = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])
# The fast lane checks the main config's loss (uniform) and the most general one (per-group
# weights with delta weighting); every other strategy in the slow lane.
FAST_STRATEGIES = [("uniform", False), ("per_group", True)]
STRATEGIES = FAST_STRATEGIES + [
    pytest.param(strategy, delta, marks=pytest.mark.slow)
    for strategy, delta in [("original", False), ("per_group", False), ("per_dimension", False),
                            ("per_dimension", True), ("loss_balanced", True),
                            ("uncertainty", False), ("uncertainty", True)]]


@st.composite
def layouts(draw):
    """Random layouts: consecutive groups with gaps, real_dim <= action_dim."""
    action_dim = draw(st.integers(2, 40))
    real_dim = draw(st.integers(1, action_dim))
    cuts = sorted(draw(st.sets(st.integers(0, real_dim), min_size=2, max_size=min(real_dim + 1, 7))))
    groups = {f"g{i}": (a, b) for i, (a, b) in enumerate(zip(cuts, cuts[1:]))
              if draw(st.booleans()) or i == 0}
    return ActionLayout(groups, real_dim=real_dim, action_dim=action_dim)


@st.composite
def problems(draw):
    layout = draw(st.one_of(st.just(ActionLayout.preset("b1k_r1pro")), layouts()))
    b, h = draw(st.integers(1, 5)), draw(st.integers(1, 12))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    d = layout.action_dim
    e = rng.uniform(0.0, 3.0, (b, h, d)).astype(np.float32)
    actions = np.cumsum(rng.normal(0, rng.uniform(0.01, 0.5), (b, h, d)), axis=1).astype(np.float32)
    actions[..., layout.real_dim:] = 0.0
    pad = rng.uniform(size=(b, h)) < 0.2
    group_weights = {g: float(w) for g, w in zip(layout.group_names,
                                                 rng.uniform(0.1, 5.0, layout.num_groups))}
    dims = np.where(layout.real_mask(), rng.uniform(0.0, 4.0, d), 0.0).astype(np.float32)
    dims[0] = 1.0  # never all zero
    log_vars = rng.uniform(-3.0, 3.0, layout.num_groups).astype(np.float32)
    return layout, e, actions, pad, group_weights, dims, log_vars


def _kwargs(strategy, delta, group_weights, dims):
    kwargs = dict(strategy=strategy, delta_weighting=delta)
    if strategy in ("per_group", "loss_balanced") or (strategy == "uncertainty" and delta):
        kwargs["group_weights"] = group_weights
    if strategy == "per_dimension":
        kwargs["dimension_weights"] = dims
    return kwargs


def _jax_loss_and_grads(layout, e, actions, pad, log_vars, kwargs):
    @jax.jit  # one compilation per example instead of one per primitive and shape
    def f(e_, s_):
        def loss(e__, s__):
            return jl.training_loss(e__, actions, pad, layout=layout, log_vars=s__, **kwargs)[0]
        per_step = jl.compute_weighted_loss(e_, actions, layout=layout, log_vars=s_, **kwargs)
        return per_step, *jax.value_and_grad(loss, argnums=(0, 1))(e_, s_)

    per_step, value, grads = f(jnp.asarray(e), jnp.asarray(log_vars))
    return [np.asarray(x) for x in (per_step, value, *grads)]


def _torch_loss_and_grads(layout, e, actions, pad, log_vars, kwargs):
    e_t = torch.tensor(e, requires_grad=True)
    s_t = torch.tensor(log_vars, requires_grad=True)
    value = tl.training_loss(e_t, torch.tensor(actions), torch.tensor(pad), layout=layout,
                             log_vars=s_t, **kwargs)[0]
    value.backward()
    s_grad = s_t.grad if s_t.grad is not None else torch.zeros_like(s_t)
    with torch.no_grad():
        per_step = tl.compute_weighted_loss(torch.tensor(e), torch.tensor(actions), layout=layout,
                                            log_vars=torch.tensor(log_vars), **kwargs)
    return [x.detach().numpy() for x in (per_step, value, e_t.grad, s_grad)]


@pytest.mark.parametrize("strategy, delta", STRATEGIES)
@SETTINGS
@given(problem=problems())
def test_jax_and_torch_losses_and_gradients_agree(strategy, delta, problem):
    layout, e, actions, pad, group_weights, dims, log_vars = problem
    kwargs = _kwargs(strategy, delta, group_weights, dims)
    got_jax = _jax_loss_and_grads(layout, e, actions, pad, log_vars, kwargs)
    got_torch = _torch_loss_and_grads(layout, e, actions, pad, log_vars, kwargs)
    for name, a, b in zip(("per-step loss", "loss", "d loss / d e", "d loss / d log_vars"),
                          got_jax, got_torch):
        scale = max(float(np.max(np.abs(a), initial=0.0)), 1e-30)
        np.testing.assert_allclose(b, a, rtol=RTOL, atol=ATOL * scale, err_msg=name)


@SETTINGS
@given(problem=problems())
def test_jax_and_torch_group_losses_agree(problem):
    layout, e, _, pad, *_ = problem
    valid = ~pad
    got_jax = jl.per_group_losses(e, layout, valid)
    got_torch = tl.per_group_losses(torch.tensor(e), layout, torch.tensor(valid))
    for g in layout.group_names:
        np.testing.assert_allclose(got_torch[g].numpy(), got_jax[g], rtol=RTOL)


def test_jax_and_torch_adaptive_state_updates_agree():
    ema, losses = np.array([0.5, 2.0, 0.1], np.float32), np.array([0.4, 3.0, 0.2], np.float32)
    j_ema, _ = jl.update_group_loss_ema(ema, jnp.int32(3), losses, 0.95)
    t_ema, _ = tl.update_group_loss_ema(torch.tensor(ema), torch.tensor(3), torch.tensor(losses), 0.95)
    np.testing.assert_allclose(t_ema.numpy(), j_ema, rtol=RTOL)
    static = np.array([1.0, 3.0, 3.0], np.float32)
    np.testing.assert_allclose(tl.loss_balanced_weights(t_ema, torch.tensor(static), 0.2, 5.0).numpy(),
                               jl.loss_balanced_weights(j_ema, static, 0.2, 5.0), rtol=RTOL)
    target = {"a": 1.0, "b": 3.0}
    j_w, t_w = jl.warmup_group_weights(target, 30, 100), tl.warmup_group_weights(target, 30, 100)
    for g in target:
        np.testing.assert_allclose(float(t_w[g]), float(j_w[g]), rtol=RTOL)


def test_torch_mirror_raises_the_same_errors():
    layout = ActionLayout.preset("b1k_r1pro")
    e = torch.zeros(1, 2, 32)
    with pytest.raises(ValueError, match="unknown loss strategy 'mse'"):
        tl.compute_weighted_loss(e, e, strategy="mse", layout=layout)
    with pytest.raises(ValueError, match=r"missing group\(s\)"):
        tl.compute_weighted_loss(e, e, strategy="per_group", layout=layout, group_weights={"base": 1.0})


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), window=st.integers(0, 4))
def test_jax_and_torch_switch_emphasis_agree(seed, window):
    layout = ActionLayout.preset("b1k_r1pro")
    rng = np.random.default_rng(seed)
    actions = rng.normal(size=(3, 10, 32)).astype(np.float32)
    valid = rng.uniform(size=(3, 10)) > 0.2
    threshold = rng.normal(size=32).astype(np.float32)
    kwargs = dict(threshold=threshold, weight=3.0, window=window)
    got_jax = jl.switch_emphasis(jnp.asarray(actions), jnp.asarray(valid), layout, **kwargs)
    got_torch = tl.switch_emphasis(torch.tensor(actions), torch.tensor(valid), layout, **kwargs)
    np.testing.assert_array_equal(got_torch.numpy(), np.asarray(got_jax))


def test_jax_and_torch_group_losses_agree_over_the_live_dims():
    layout = ActionLayout.preset("b1k_r1pro")
    rng = np.random.default_rng(0)
    live = (rng.uniform(size=(4, layout.action_dim)) > 0.2).astype(np.float32)
    e = rng.uniform(size=(3, 4, layout.action_dim)).astype(np.float32) * live
    valid = np.ones((3, 4), bool)
    got_jax = jl.per_group_losses(e, layout, valid, live)
    got_torch = tl.per_group_losses(torch.tensor(e), layout, torch.tensor(valid), live)
    for g in layout.group_names:
        np.testing.assert_allclose(got_torch[g].numpy(), got_jax[g], rtol=RTOL)
