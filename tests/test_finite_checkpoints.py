"""The train loop's checkpoint protocol: only finite training is ever kept."""

import jax.numpy as jnp
import pytest

from pi0_armfix.training.finite_checkpoints import FiniteCheckpoints, NonFiniteLossError


class FakeCheckpoints:
    def __init__(self):
        self.saved, self.confirmed, self.aside = [], [], []

    def save(self, step, *args, force):
        self.saved.append(step)

    def confirm(self, step):
        self.confirmed.append(step)

    def set_aside(self, step, why):
        self.aside.append(step)
        return f"checkpoints/{step}.{why}"

    def latest_step(self):
        return self.saved[-1] if self.saved else None


def _metrics(loss):
    return {"loss": jnp.float32(loss), "grad_norm": jnp.float32(1.0), "lr": jnp.float32(0.1)}


def test_the_step_after_a_resumed_checkpoint_confirms_it():
    ckpts = FakeCheckpoints()
    finite = FiniteCheckpoints(ckpts, start=10)
    finite.record(11, _metrics(0.5))
    assert ckpts.confirmed == [10] and ckpts.aside == []


def test_a_non_finite_step_after_a_checkpoint_moves_it_aside_and_names_the_rerun():
    ckpts = FakeCheckpoints()
    finite = FiniteCheckpoints(ckpts, start=0)
    finite.record(1, _metrics(0.5))
    finite.save(1, {"w": jnp.ones(2)}, None, None, None)
    with pytest.raises(NonFiniteLossError, match=r"step 2 has loss nan .*moved to checkpoints/1"):
        finite.record(2, _metrics(float("nan")))
    assert ckpts.aside == [1]


def test_non_finite_params_are_never_saved():
    ckpts = FakeCheckpoints()
    finite = FiniteCheckpoints(ckpts, start=0)
    finite.record(1, _metrics(0.5))
    with pytest.raises(NonFiniteLossError, match="left non-finite parameters"):
        finite.save(1, {"w": jnp.array([1.0, jnp.inf])}, None, None, None)
    assert ckpts.saved == []


def test_a_log_window_with_a_non_finite_step_stops_before_it_is_written():
    finite = FiniteCheckpoints(FakeCheckpoints(), start=0)
    finite.record(1, _metrics(0.5))
    finite.record(2, _metrics(float("inf")))
    with pytest.raises(NonFiniteLossError, match="step 2 has loss inf"):
        finite.take_window()
