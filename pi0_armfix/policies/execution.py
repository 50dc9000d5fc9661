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
  deadband            a group holds still where the policy commands less motion than its band
                      (`hold_still`): the base is commanded 0, a position group keeps its last
                      command; the demonstrations stop exactly, a sampler near zero does not;
  gripper_hysteresis  the grippers' commands pass their hysteresis (`hysteresis.GripperLatch`,
                      one stream per env).
Used by the closed-loop evaluation (`evaluation.closed_loop`) and the B1K harness
(`serving.harness`); an openpi client executes the chunks itself, so its server applies only
the per-chunk rules (the deadband and the hysteresis, held per client). The held-out evaluator
applies the deadband too (`hold_still` from each chunk's previous command).
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


Band = tuple[np.ndarray, np.ndarray, bool]  # a group's (dims, band [len(dims)], velocity?)


def hold_still(chunks: np.ndarray, bands: Sequence[Band], held: np.ndarray) -> np.ndarray:
    """Chunks `[..., H, A]` with each group of `bands` held still where it is commanded less
    motion than its band, step by step: a velocity group is commanded 0 at a step whose every
    command lies within its band around 0; a position group keeps its held command at a step
    whose every command lies within its band around it, and any other command passes and is held
    from then on. `held` `[..., A]`: the commands held before the first step (the last executed;
    NaN where there is none: those commands pass)."""
    out = np.array(chunks, dtype=np.float64)
    held = np.array(held, dtype=np.float64)
    for t in range(out.shape[-2]):
        for dims, band, velocity in bands:
            rest = np.zeros_like(held[..., dims]) if velocity else held[..., dims]
            # a dim the data never moves (band 0) has no motion to tell: it follows the others
            inside = ((np.abs(out[..., t, dims] - rest) < band) | (band == 0)).all(
                axis=-1, keepdims=True)
            out[..., t, dims] = np.where(inside, rest, out[..., t, dims])
            if not velocity:
                held[..., dims] = out[..., t, dims]
    return out.astype(np.asarray(chunks).dtype)


def deadband_groups(sampling: Sampling, layout: ActionLayout | None,
                    action_std: np.ndarray | None) -> list[Band]:
    """`hold_still`'s bands: each `deadband` group's dims, k times each dim's action std
    `[real_dim]` (dataset units), and whether it is a velocity group; [] when off.

    Raises:
      ValueError naming a group the layout lacks.
    """
    bands = sampling.deadbands(layout)
    if not bands:
        return []
    std = np.asarray(action_std, np.float64)
    return [(np.asarray(layout.group_dims(g)), k * std[layout.group_dims(g)],
             g in layout.velocity_groups) for g, k in bands.items()]


class ChunkRules:
    """The per-chunk execution rules (the deadband, the grippers' hysteresis) of a policy, for a
    client that executes whole chunks itself (openpi's protocol): `rules(stream, chunk)`, what
    they hold kept per stream as if it executed `n_exec` actions of each chunk (0: all)."""

    def __init__(self, policy: Any, sampling: Sampling | None = None):
        sampling = sampling or getattr(policy, "sampling", Sampling())
        layout = getattr(policy, "layout", None)  # read only where a rule is set
        self.executed = sampling.n_exec or None  # what the client executes, for the latch
        self.bands = deadband_groups(sampling, layout, getattr(policy, "action_std", None))
        self.latch = sampling.latch(layout)
        self._held: dict[Hashable, np.ndarray] = {}

    def __call__(self, stream: Hashable, chunk: np.ndarray) -> np.ndarray:
        if self.bands:
            held = self._held.get(stream, np.full(chunk.shape[-1], np.nan))
            chunk = hold_still(chunk, self.bands, held)
            self._held[stream] = chunk[min(self.executed or len(chunk), len(chunk)) - 1]
        return chunk if self.latch is None else self.latch(stream, chunk, self.executed)

    def forget(self, stream: Hashable) -> None:
        """Forgets what a stream's commands held (its client left)."""
        self._held.pop(stream, None)
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
      `rtc`), a deadband on a group the layout lacks, a hysteresis without grippers.
    """

    def __init__(self, policy: Any, sampling: Sampling | None = None):
        self.policy = policy
        self.sampling = sampling or getattr(policy, "sampling", Sampling())
        layout = getattr(policy, "layout", None)  # read only where a rule is set
        self.n_exec = self.sampling.executed(policy.horizon)
        self.bands = deadband_groups(self.sampling, layout, getattr(policy, "action_std", None))
        self.latch = self.sampling.latch(layout)
        self.start()

    def start(self, envs: Sequence[Any] | None = None) -> None:
        """A new episode of every env: no tails, plans or executed action, the latch's held
        commands forgotten. `envs`: the environments that start it together (`sim.rollout.
        Driver.start`), whose indices `__call__` then takes (one past them is an error); None:
        any index (a harness connection's envs, known only as they come)."""
        self._envs = None if envs is None else len(envs)
        self._tails: dict[int, np.ndarray] = {}
        self._executed: dict[int, np.ndarray] = {}
        self._plans: dict[int, list[tuple[int, np.ndarray]]] = {}
        self._now: dict[int, int] = {}
        if self.latch is not None:
            self.latch.reset()

    def __call__(self, active, observations, rng: jax.Array | None = None,
                 n_exec: int | None = None):
        """Chunks `[len(active), H, A]` for the envs `active` (their tails followed under `rtc`
        when every one has a tail: a chunk at an episode's start has none); `rng`: the draw's
        key (a caller with its own noise stream), else the policy's next; `n_exec`: the actions
        the caller will execute of these chunks, in place of `self.n_exec` (a harness replaying
        a longer chunk)."""
        n_exec = n_exec or self.n_exec
        outside = [i for i in active if self._envs is not None and not 0 <= i < self._envs]
        if outside:
            raise ValueError(f"envs {outside} were not started: start() was given "
                             f"{self._envs} environments")
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
                chunk = temporal_ensemble(self._plans[i], now, n_exec,
                                          sampling.temporal_ensemble)
            if self.bands:
                chunk = hold_still(chunk, self.bands,
                                   self._executed.get(i, np.full(chunk.shape[-1], np.nan)))
            if self.latch is not None:
                chunk = self.latch(i, chunk, n_exec)
            self._tails[i] = chunk[n_exec:]
            self._executed[i] = chunk[min(n_exec, len(chunk)) - 1]
            self._now[i] = self._now.get(i, 0) + n_exec
            out.append(chunk)
        return np.stack(out)
