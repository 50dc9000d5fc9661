"""The step's speed and memory options compute the step they replace: the same loss, gradient
norm and updated parameters as the default (einsum attention, each layer rematerialized keeping
nothing), at the tiny preset in float32 (exactly, up to summation order) and bfloat16."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_armfix.bench import step as bench_step
from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model

OPTIONS = [("model.attention=fused",),
           *[(f"model.remat_policy={policy}",) for policy in model_config.REMAT_POLICIES[1:]]]


@functools.cache
def _step(dtype: str, changes: tuple[str, ...] = ()):
    """(loss, grad norm, the gradients) of one step of `arm_focused` at tiny, remat on. AdamW
    with an epsilon far above every gradient and the learning rate as large is a gradient step:
    the update is the gradient, clipped (AdamW's own first step is its sign)."""
    config = bench_step.load_config(
        "arm_focused", preset="tiny", batch=4,
        changes=(f"model.dtype={dtype}", "optim.warmup_steps=0", "optim.lr=1e4", "optim.eps=1e4",
                 "optim.weight_decay=0.0", *changes))
    bench = bench_step.Step(config, remat="on")
    state = bench.init(jax.random.key(0))
    before = jax.device_get(state.params)
    with jax.set_mesh(bench.mesh):
        state, metrics = jax.jit(bench.step_fn)(state, bench.batch)
    gradients = jax.tree.map(lambda new, old: old - new, jax.device_get(state.params), before)
    return float(metrics["loss"]), float(metrics["grad_norm"]), gradients


@pytest.mark.slow
@pytest.mark.parametrize("changes", OPTIONS, ids=lambda c: c[0].split("=")[1])
def test_an_option_gives_the_default_steps_loss_and_gradients(changes):
    loss, grad_norm, gradients = _step("float32", changes)
    base_loss, base_grad_norm, base_gradients = _step("float32")
    np.testing.assert_allclose([loss, grad_norm], [base_loss, base_grad_norm], rtol=1e-5)
    jax.tree.map(functools.partial(np.testing.assert_allclose, rtol=1e-3, atol=1e-6), gradients,
                 base_gradients)


@pytest.mark.slow
@pytest.mark.parametrize("changes", OPTIONS, ids=lambda c: c[0].split("=")[1])
def test_an_option_keeps_the_loss_within_bfloat16_tolerance(changes):
    loss, grad_norm, _ = _step("bfloat16", changes)
    base_loss, base_grad_norm, _ = _step("bfloat16")
    np.testing.assert_allclose([loss, grad_norm], [base_loss, base_grad_norm], rtol=2e-2)


def test_an_unknown_option_value_names_the_key_and_the_choices():
    with pytest.raises(ValueError, match=r"model.attention = 'flash' must be one of \('einsum'"):
        model_config.get_preset("tiny", attention="flash")
    with pytest.raises(ValueError, match=r"model.remat_policy = 'all' must be one of"):
        model_config.get_preset("tiny", remat_policy="all")


def test_the_step_benchmark_refuses_a_change_that_names_no_key():
    with pytest.raises(ValueError, match=r"--set=model.atention=fused: name a config key"):
        bench_step.load_config("arm_focused", preset="tiny", changes=("model.atention=fused",))


@pytest.mark.slow
def test_a_step_over_microbatches_is_the_mean_of_its_strided_parts():
    config = bench_step.load_config(
        "uniform", preset="tiny", batch=4,
        changes=("train.microbatches=2", "optim.warmup_steps=0", "optim.lr=1e4", "optim.eps=1e4",
                 "optim.weight_decay=0.0", "optim.clip_norm=1e9"))
    bench = bench_step.Step(config)
    state = bench.init(jax.random.key(0))
    params = jax.device_get(state.params)
    kwargs = bench.step_fn.keywords
    rng = jax.random.fold_in(kwargs["base_rng"], 0)

    def part_loss(p, i):
        rows = jax.tree.map(lambda x: x[i::2], bench.batch)
        return flow_model.compute_loss(p, jax.random.fold_in(rng, i), rows, config=bench.model,
                                       layout=kwargs["layout"], train=True,
                                       loss_mask=kwargs["loss_mask"], strategy="uniform",
                                       delta_weighting=False)[0]

    losses, grads = zip(*(jax.value_and_grad(part_loss)(params, i) for i in range(2)))
    with jax.set_mesh(bench.mesh):
        state, metrics = jax.jit(bench.step_fn)(state, bench.batch)
    np.testing.assert_allclose(float(metrics["loss"]), np.mean(losses), rtol=1e-6)
    update = jax.tree.map(lambda old, new: old - new, params, jax.device_get(state.params))
    jax.tree.map(functools.partial(np.testing.assert_allclose, rtol=1e-3, atol=1e-6), update,
                 jax.tree.map(lambda a, b: (a + b) / 2, *grads))


def test_microbatches_that_do_not_divide_a_devices_rows_are_refused_naming_the_key():
    config = bench_step.load_config("uniform", preset="tiny", batch=4,
                                    changes=("train.microbatches=3",))
    with pytest.raises(ValueError, match=r"train.microbatches = 3 must be >= 1 and divide the 4"):
        bench_step.Step(config)


@pytest.mark.parametrize("parts", [2, 4])
def test_microbatched_gradients_equal_the_full_batchs_with_unequal_padding(parts):
    from pi0_armfix.training import step as step_lib
    rng = np.random.default_rng(0)
    is_pad = np.zeros((8, 4), bool)
    is_pad[1, 1:] = True  # one row of eight padded on 3 of its 4 steps
    batch = {"x": rng.normal(size=(8, 4, 3)).astype(np.float32),
             "y": rng.normal(size=(8, 4)).astype(np.float32), "action_is_pad": is_pad}

    def masked_mean_loss(w, _, rows):  # a loss over the valid steps, as `loss.training_loss`
        valid = ~rows["action_is_pad"]
        error = jnp.square(jnp.sum(rows["x"] * w, -1) - rows["y"])
        return jnp.sum(error * valid) / jnp.maximum(valid.sum(), 1), {"error": error.max()}

    value_and_grad = jax.value_and_grad(masked_mean_loss, has_aux=True)
    w, key = jnp.array([0.5, -1.0, 2.0]), jax.random.key(0)
    (loss, _), grads = value_and_grad(w, key, batch)
    (micro_loss, _), micro_grads = jax.jit(step_lib.microbatched, static_argnums=(0, 4))(
        value_and_grad, w, key, batch, parts)
    # float32, summed in another order: within 1e-6 of the full batch's
    np.testing.assert_allclose(micro_loss, loss, rtol=1e-6)
    np.testing.assert_allclose(micro_grads, grads, rtol=1e-6)
