"""What a robot executes of the sampled chunks: a run's policy as a receding-horizon driver, with
the execution levers of `policies.sampling.Sampling`.

    replanning = Replanner(policy)                  # the levers of policy.sampling
    replanning.start()                              # a new episode
    chunks = replanning(active, observations)       # [len(active), H, A]; execute [:n_exec]

Each request samples a chunk per env, of which the caller executes `n_exec` (`Sampling.executed`)
before asking again. On the way out, in this order:
  rtc                 the new chunk softly follows the last one's unexecuted tail (real-time
                      chunking's soft inpainting, `RunPolicy.infer(follow=...)`);
  temporal_ensemble   each executed action the weighted mean of every chunk still covering its
                      step (ACT, Zhao et al., 2023; `temporal_ensemble`);
  stop_deadband       a velocity group whose every command of a step is within the deadband is
                      commanded 0 (`stop`): the demonstrations stop exactly, a sampler near
                      zero does not;
  gripper_hysteresis  the grippers' commands pass their hysteresis (`hysteresis.GripperLatch`,
                      one stream per env).
Used by the closed-loop evaluation (`evaluation.closed_loop`) and the B1K harness
(`serving.harness`); an openpi client executes the chunks itself, so its server applies only
the per-chunk rules (`stop`, the hysteresis).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from typing import Any

import jax
import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.policies.sampling import Sampling


def temporal_ensemble(plans: Sequence[tuple[int, np.ndarray]], now: int, n_exec: int,
                      decay: float) -> np.ndarray:
    """The chunk to execute at step `now`: `plans` are `(start, chunk [H, A])` oldest first, the
    last the chunk just sampled (its start `now`); its first `n_exec` actions become, per step,
    the mean of every plan covering that step weighted exp(-decay i) for the i-th oldest of
    them (ACT's weights: the oldest weighs most). Returns `[H, A]`, the rest the new chunk's."""
    start, newest = plans[-1]
    if start != now:
        raise ValueError(f"the newest plan starts at {start}, not at the step {now}")
    out = np.array(newest, dtype=np.float64)
    for k in range(min(n_exec, len(newest))):
        covering = np.stack([c[now + k - s] for s, c in plans if 0 <= now + k - s < len(c)])
        weights = np.exp(-decay * np.arange(len(covering)))
        out[k] = weights @ covering / weights.sum()
    return out.astype(np.asarray(newest).dtype)


def stop(chunk: np.ndarray, groups: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """`chunk` `[H, A]` with each velocity group `(dims, deadband [len(dims)])` commanded 0 at
    the steps where every one of its commands lies within its deadband."""
    out = np.array(chunk, copy=True)
    for dims, deadband in groups:
        still = (np.abs(out[:, dims]) < deadband).all(axis=-1)
        out[np.ix_(still, dims)] = 0.0
    return out


def stop_groups(sampling: Sampling, layout: ActionLayout | None, action_std: np.ndarray | None
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The `(dims, deadband)` of each velocity group for `stop`: `stop_deadband` times each dim's
    action std `[real_dim]` (dataset units); [] when off.

    Raises:
      ValueError where a deadband is set on a layout without a velocity group.
    """
    if not sampling.stop_deadband:
        return []
    if not layout.velocity_groups:
        raise ValueError("stop_deadband is set but the layout has no velocity group "
                         "(layout.velocity_groups); set it to 0")
    return [(np.asarray(layout.group_dims(g)),
             sampling.stop_deadband * np.asarray(action_std)[layout.group_dims(g)])
            for g in layout.velocity_groups]


class ChunkRules:
    """The per-chunk execution rules (`stop`, the grippers' hysteresis) of a policy, for a client
    that executes whole chunks itself (openpi's protocol): `rules(stream, chunk)`."""

    def __init__(self, policy: Any, sampling: Sampling | None = None):
        sampling = sampling or getattr(policy, "sampling", Sampling())
        layout = getattr(policy, "layout", None)  # read only where a rule is set
        self.executed = sampling.n_exec or None  # what the client executes, for the latch
        self.stops = stop_groups(sampling, layout, getattr(policy, "action_std", None))
        self.latch = sampling.latch(layout)

    def __call__(self, stream: Hashable, chunk: np.ndarray) -> np.ndarray:
        chunk = stop(chunk, self.stops) if self.stops else chunk
        return chunk if self.latch is None else self.latch(stream, chunk, self.executed)

    def forget(self, stream: Hashable) -> None:
        """Forgets what a stream's commands held (its client left)."""
        if self.latch is not None:
            self.latch.forget(stream)


class Replanner:
    """A run's policy as a receding-horizon driver (`sim.rollout.Driver`, the harness's sessions)
    with the execution levers of `sampling` (None: the policy's own, `RunPolicy.sampling`, or the
    defaults for a policy without one). A
    policy relative to the previous action gets each env's last executed one (the `n_exec`-th of
    its last chunk; none at an episode's start).

    Raises:
      ValueError naming the lever, for `n_exec` beyond the horizon (or leaving no tail with
      `rtc`), a deadband without a velocity group, a hysteresis without grippers.
    """

    def __init__(self, policy: Any, sampling: Sampling | None = None):
        self.policy = policy
        self.sampling = sampling or getattr(policy, "sampling", Sampling())
        layout = getattr(policy, "layout", None)  # read only where a rule is set
        self.n_exec = self.sampling.executed(policy.horizon)
        self.stops = stop_groups(self.sampling, layout, getattr(policy, "action_std", None))
        self.latch = self.sampling.latch(layout)
        self.start()

    def start(self, envs=None):
        """A new episode: no tails, plans or executed action, the latch's held commands
        forgotten."""
        self._tails: dict[int, np.ndarray] = {}
        self._executed: dict[int, np.ndarray] = {}
        self._plans: dict[int, list[tuple[int, np.ndarray]]] = {}
        self._now: dict[int, int] = {}
        if self.latch is not None:
            self.latch.reset()

    def __call__(self, active, observations, rng: jax.Array | None = None):
        """Chunks `[len(active), H, A]` for the envs `active` (their tails followed under `rtc`
        when every one has a tail: a chunk at an episode's start has none); `rng`: the draw's
        key (a caller with its own noise stream), else the policy's next."""
        sampling, follow = self.sampling, None
        if sampling.rtc and all(i in self._tails for i in active):
            follow = np.stack([self._tails[i] for i in active])
        kwargs = {} if rng is None else {"rng": rng}
        if getattr(self.policy, "delta_reference", "state") == "previous_action":
            width = self.policy.layout.real_dim
            kwargs["previous"] = np.stack([self._executed.get(i, np.full(width, np.nan))
                                           for i in active])
        chunks = self.policy.infer(observations, follow=follow, **kwargs)
        out = []
        for i, chunk in zip(active, chunks):
            if sampling.temporal_ensemble:
                now = self._now.get(i, 0)
                plans = [p for p in self._plans.get(i, []) if p[0] + len(p[1]) > now]
                self._plans[i] = plans + [(now, chunk)]
                chunk = temporal_ensemble(self._plans[i], now, self.n_exec,
                                          sampling.temporal_ensemble)
            if self.stops:
                chunk = stop(chunk, self.stops)
            if self.latch is not None:
                chunk = self.latch(i, chunk, self.n_exec)
            self._tails[i] = chunk[self.n_exec:]
            self._executed[i] = chunk[min(self.n_exec, len(chunk)) - 1]
            self._now[i] = self._now.get(i, 0) + self.n_exec
            out.append(chunk)
        return np.stack(out)
