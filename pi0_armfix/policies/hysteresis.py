"""Grippers that commit: hysteresis on a policy's gripper commands, between sampling and the robot.

A flow-matching policy samples each chunk afresh, so a gripper command near the open/close boundary
changes sign from one chunk (or step) to the next, and every sign change opens or closes the
gripper at once: opening while holding drops the object. The filter lets a command through only
when it is decisive (above `open_above`, or below `close_below`, in the action's units) and
otherwise repeats the last decisive command. B1K 2025's winning team post-processed its grippers
this way (open above about 0.9, closed below about -0.98 of a [-1, 1] command).

    latch = GripperLatch(dims=(14, 22), open_above=0.9, close_below=-0.98)
    chunk = latch(stream, chunk, executed=n_exec)   # per robot (stream): [H, A] -> [H, A]

Used by the closed-loop evaluation (`evaluate --closed_loop`) and the policy server, with the run's
`eval.gripper_hysteresis` or their `--gripper_hysteresis` flag (`policies.sampling.Sampling.latch`).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import numpy as np


def check_thresholds(thresholds: Sequence[float], what: str) -> tuple[float, float] | None:
    """`(open_above, close_below)` from a config value or flag `what` (empty: no filter)."""
    if not len(thresholds):
        return None
    if len(thresholds) != 2 or not float(thresholds[0]) > float(thresholds[1]):
        raise ValueError(f"{what} = {tuple(thresholds)} must be (open_above, close_below) with "
                         "open_above > close_below, in the gripper action's units (e.g. 0.9,-0.98 "
                         "for a [-1, 1] command), or empty for no filter")
    return float(thresholds[0]), float(thresholds[1])


def gripper_hysteresis(commands: np.ndarray, held: np.ndarray, open_above: float,
                       close_below: float) -> tuple[np.ndarray, np.ndarray]:
    """Commands `[T, G]` of G grippers filtered in time order.

    A command above `open_above` or below `close_below` passes and becomes the held command; any
    other is replaced by the held one. `held` `[G]`: the held commands before the first step (NaN
    where there is none yet: such a gripper's commands pass until its first decisive one).
    Returns the filtered `[T, G]` and the held commands after the last step `[G]`.
    """
    out = np.array(commands, dtype=np.float64)
    held = np.array(held, dtype=np.float64)
    for t in range(len(out)):
        decisive = (out[t] > open_above) | (out[t] < close_below)
        held = np.where(decisive, out[t], held)
        out[t] = np.where(np.isnan(held), out[t], held)
    return out.astype(np.asarray(commands).dtype), held


class GripperLatch:
    """`gripper_hysteresis` on the gripper dims of action chunks, the held commands kept per
    stream (an environment, a client connection) across chunks."""

    def __init__(self, dims: Sequence[int], open_above: float, close_below: float):
        self.dims = np.asarray(dims, int)
        self.open_above, self.close_below = open_above, close_below
        self._held: dict[Hashable, np.ndarray] = {}

    def reset(self) -> None:
        """Forgets every stream's held commands (a new episode)."""
        self._held.clear()

    def forget(self, stream: Hashable) -> None:
        """Forgets one stream's held commands (its client left)."""
        self._held.pop(stream, None)

    def __call__(self, stream: Hashable, chunk: np.ndarray, executed: int | None = None
                 ) -> np.ndarray:
        """`chunk` [H, A] with its gripper dims filtered. `executed`: how many of its actions the
        robot carries out before the next chunk (None: all); the held commands are those after
        them, so an unexecuted tail does not change what the next chunk starts from."""
        held = self._held.get(stream, np.full(len(self.dims), np.nan))
        executed = len(chunk) if executed is None else min(executed, len(chunk))
        out = np.array(chunk, copy=True)
        out[:executed, self.dims], self._held[stream] = gripper_hysteresis(
            chunk[:executed, self.dims], held, self.open_above, self.close_below)
        out[executed:, self.dims], _ = gripper_hysteresis(
            chunk[executed:, self.dims], self._held[stream], self.open_above, self.close_below)
        return out
