"""Checkpoints that are only ever of finite training: the train loop's save/confirm protocol.

A step's loss and gradient norm are read back only in batches (a device round trip per step would
stall the accelerator), so a non-finite step is found some steps after it ran. The protocol keeps
the last checkpoint valid whatever is found:
  - the steps since the last check are kept (`window`) and checked before a save and at each log;
    a state is saved only when every step that led to it was finite and its params are too;
  - a checkpoint is *unconfirmed* until the step computed from it is known finite (orbax keeps
    an unconfirmed one from being the only one left); if that step is not finite, the checkpoint
    is moved aside (`Checkpoints.set_aside`) and the run stops, naming the checkpoint a rerun
    resumes from.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_armfix.training import checkpoint

StepMetrics = Mapping[str, jax.Array]


class NonFiniteLossError(RuntimeError):
    """The loss or gradient of a step is NaN or infinite."""


def first_non_finite(window: Sequence[tuple[int, StepMetrics]]
                     ) -> tuple[int, float, float] | None:
    """`(step, loss, grad_norm)` of the first step of `window` whose loss or gradient norm is not
    finite (a non-finite gradient would have poisoned the params it updated), or None."""
    values = jax.device_get([(m["loss"], m["grad_norm"]) for _, m in window])
    for (step, _), (loss, grad_norm) in zip(window, values):
        if not (np.isfinite(loss) and np.isfinite(grad_norm)):
            return step, float(loss), float(grad_norm)
    return None


@jax.jit
def all_finite(tree: Any) -> jax.Array:
    """Whether every float leaf of `tree` is finite: bool `[]`."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)
              if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.bool_(True)


def summarize(window: Sequence[tuple[int, StepMetrics]]) -> dict[str, float]:
    """Means over the window of the step metrics; `lr` of the last step."""
    values = jax.device_get([m for _, m in window])
    record = {name: float(np.mean([v[name] for v in values])) for name in values[-1]}
    record["lr"] = float(values[-1]["lr"])
    return record


class FiniteCheckpoints:
    """The protocol of the module docstring around a run's `checkpoint.Checkpoints`.

    Args:
      checkpoints: the run's checkpoints.
      start: the step the run resumed from (0: a fresh run); its checkpoint is unconfirmed until
        the step computed from it is known finite.
    """

    def __init__(self, checkpoints: checkpoint.Checkpoints, start: int):
        self.checkpoints = checkpoints
        self.window: list[tuple[int, StepMetrics]] = []  # the steps since the last log
        self._checked = 0  # window entries known to be finite
        self._unconfirmed = start or None
        self.saved = start  # the step of the latest checkpoint

    def record(self, step: int, metrics: StepMetrics) -> None:
        """Keeps a step's metrics; the step computed from an unconfirmed checkpoint confirms it,
        or moves it aside and raises `NonFiniteLossError`."""
        self.window.append((step, metrics))
        if self._unconfirmed is None:
            return
        bad = first_non_finite(self.window[-1:])
        if bad:
            moved = self.checkpoints.set_aside(self._unconfirmed, "nonfinite")
            raise self._error(_describe(bad), f"Checkpoint {self._unconfirmed}, the state it "
                              f"started from, was moved to {moved}; ")
        self.checkpoints.confirm(self._unconfirmed)
        self._unconfirmed = None

    def take_window(self) -> list[tuple[int, StepMetrics]]:
        """The steps since the last log, checked finite (else `NonFiniteLossError`); the window
        starts anew."""
        self._check_window()
        window, self.window, self._checked = self.window, [], 0
        return window

    def save(self, step: int, state: Any, data_state: Any, norm_stats_json: Any,
             config_json: Any) -> None:
        """Saves `state` after `step` if every step of the window and its params are finite
        (else `NonFiniteLossError`, nothing saved); unconfirmed until the next step is known."""
        self._check_window()
        if not bool(all_finite(state)):
            raise self._error(f"the update of step {step} left non-finite parameters (its loss "
                              "and gradient were finite)", "It was not saved; ")
        self.checkpoints.save(step, state, data_state, norm_stats_json, config_json, force=True)
        self._unconfirmed, self.saved = step, step

    def confirm_final(self, step: int) -> None:
        """The final state has no next step: its own finiteness (checked at its save) confirms
        it."""
        self.checkpoints.confirm(step)
        self._unconfirmed = None

    def _check_window(self) -> None:
        bad = first_non_finite(self.window[self._checked:])
        if bad:
            raise self._error(_describe(bad), "")
        self._checked = len(self.window)

    def _error(self, what: str, resume_note: str) -> NonFiniteLossError:
        latest = self.checkpoints.latest_step()
        resume = (f"a rerun resumes from checkpoint {latest}" if latest
                  else "no checkpoint is left: a rerun starts from step 0")
        return NonFiniteLossError(f"{what}: stopping. {resume_note}{resume}; lower optim.lr or "
                                  "raise optim.warmup_steps first")


def _describe(bad: tuple[int, float, float]) -> str:
    step, loss, grad_norm = bad
    return f"step {step} has loss {loss} and gradient norm {grad_norm}"
