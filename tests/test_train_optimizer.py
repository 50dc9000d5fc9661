"""AdamW + global-norm clipping + warmup-cosine (docs/design.md §6)."""

import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from pi0_armfix.configs import base
from pi0_armfix.training import optimizer


def _optim(**changes) -> ml_collections.ConfigDict:
    optim = base.get_config().optim
    optim.update(changes)
    return optim


def test_learning_rate_warms_up_linearly_then_decays_by_cosine_to_the_end_value():
    schedule = optimizer.learning_rate_schedule(_optim(lr=1.0, warmup_steps=10,
                                                       end_lr_factor=0.1), total_steps=110)
    np.testing.assert_allclose([schedule(0), schedule(5), schedule(10)], [0.0, 0.5, 1.0])
    np.testing.assert_allclose(schedule(60), 0.55, rtol=1e-6)  # half way down the cosine
    np.testing.assert_allclose(schedule(110), 0.1, rtol=1e-6)


def test_a_run_shorter_than_its_warmup_warms_up_over_a_tenth_of_it_and_says_so():
    warmup, note = optimizer.effective_warmup(_optim(warmup_steps=1000), total_steps=20)
    assert warmup == 2 and "optim.warmup_steps = 1000" in note and "2 steps" in note
    schedule = optimizer.learning_rate_schedule(_optim(lr=1.0, warmup_steps=1000), 20)
    assert float(schedule(2)) == pytest.approx(1.0)
    assert optimizer.effective_warmup(_optim(warmup_steps=5), total_steps=20) == (5, None)


def test_negative_warmup_is_a_config_error():
    with pytest.raises(ValueError, match="optim.warmup_steps = -1"):
        optimizer.learning_rate_schedule(_optim(warmup_steps=-1), total_steps=100)


@pytest.mark.parametrize("key, value", [("end_lr_factor", -5.0), ("end_lr_factor", 1.5),
                                        ("b1", 1.5), ("b2", 1.0), ("eps", 0.0), ("lr", 0.0),
                                        ("lr", float("inf")), ("weight_decay", -0.1),
                                        ("clip_norm", 0.0)])
def test_optimizer_values_out_of_range_are_named_with_their_range(key, value):
    with pytest.raises(ValueError, match=rf"optim\.{key} = {value} must be"):
        optimizer.make_optimizer(_optim(**{key: value}), 100)


def test_every_bad_optimizer_value_is_named_at_once():
    with pytest.raises(ValueError, match=r"optim\.b1 = 1\.5 .*; optim\.b2 = 2\.0"):
        optimizer.check_optim_config(_optim(b1=1.5, b2=2.0))


def test_weight_decay_applies_to_model_params_but_not_to_loss_params():
    tx, _ = optimizer.make_optimizer(_optim(lr=0.1, warmup_steps=0, weight_decay=1.0), 10)
    trainable = {"params": {"w": jnp.ones((3,))}, "loss_params": {"log_vars": jnp.ones((3,))}}
    zero_grads = {"params": {"w": jnp.zeros((3,))}, "loss_params": {"log_vars": jnp.zeros((3,))}}
    updates, _ = tx.update(zero_grads, tx.init(trainable), trainable)
    assert np.all(np.asarray(updates["params"]["w"]) < 0)
    np.testing.assert_array_equal(updates["loss_params"]["log_vars"], 0.0)


def test_gradients_are_clipped_to_the_global_norm_before_adam():
    # With a large eps, Adam's first update is -lr * g / (|g| + eps): proportional to g, so it
    # shows whether g was clipped.
    tx, _ = optimizer.make_optimizer(
        _optim(lr=1.0, warmup_steps=0, clip_norm=1.0, eps=1e3, weight_decay=0.0), 10)
    trainable = {"params": {"w": jnp.zeros((4,))}, "loss_params": {}}
    grads = {"params": {"w": jnp.full((4,), 10.0)}, "loss_params": {}}
    updates, _ = tx.update(grads, tx.init(trainable), trainable)
    clipped = 0.5  # 10 * 1 / ||(10, 10, 10, 10)||
    np.testing.assert_allclose(updates["params"]["w"], -clipped / (clipped + 1e3), rtol=1e-5)


def test_ema_decay_of_one_is_a_config_error():
    with pytest.raises(ValueError, match="optim.ema_decay"):
        optimizer.make_optimizer(_optim(ema_decay=1.0), 10)
