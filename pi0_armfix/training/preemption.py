"""Stopping a run cleanly on SIGTERM (a cluster's preemption notice) and SIGINT (Ctrl-C).

The first signal asks the loop to stop after the step in flight: it saves that step when
`train.save_on_preemption` is set, waits for the save and exits with one line (exit status
128 + signal number, so that a scheduler sees an interrupted job). A second signal abandons at
once, also a save in flight: orbax finalizes a step by renaming it into place, so an abandoned
save leaves the previous checkpoint as the latest one.

Multi-process runs must stop at the same step on every process (a save is collective): there
JAX's preemption service catches SIGTERM on any process and `reached_preemption_sync_point`
names the common step; Ctrl-C keeps Python's default there.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Iterator

import jax
from jax.experimental import multihost_utils

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Abandoned(BaseException):
    """A second stop signal: leave now, without waiting for anything (a BaseException, so that no
    handler of ordinary errors catches it)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopRequest:
    """Whether the run was asked to stop, and by which signal."""

    def __init__(self):
        self.signum: int | None = None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum else "SIGTERM"

    def due(self, steps_done: int) -> bool:
        """Whether to stop now, `steps_done` steps into the run (call it at every step)."""
        if jax.process_count() > 1:
            return multihost_utils.reached_preemption_sync_point(steps_done)
        return self.signum is not None


@contextlib.contextmanager
def stop_on_signals(say: Callable[[str], None]) -> Iterator[StopRequest]:
    """Within the block, SIGTERM and SIGINT set the returned request (the first) or raise
    `Abandoned` (the second); the previous handlers are restored after it."""
    request = StopRequest()
    if jax.process_count() > 1 or threading.current_thread() is not threading.main_thread():
        yield request
        return
    owner = os.getpid()

    def handle(signum, frame):
        del frame
        if os.getpid() != owner:
            # A forked data worker inherits this handler and gets the terminal's signal too:
            # the run (its parent) stops it; raising here would only leave it spinning.
            return
        if request.signum is not None:
            raise Abandoned(signum)
        request.signum = signum
        say(f"received {signal.Signals(signum).name}: stopping after the current step "
            "(send it again to stop at once)")

    previous = {s: signal.signal(s, handle) for s in SIGNALS}
    try:
        yield request
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def stop_workers() -> None:
    """Kills this process's worker processes (the data loader's): what a run stopped at once
    does before it exits, since exiting at once skips their orderly shutdown and would leave
    them running."""
    for child in multiprocessing.active_children():
        child.kill()
    for child in multiprocessing.active_children():
        child.join(timeout=5)
