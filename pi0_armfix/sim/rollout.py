"""Closed-loop rollouts: a driver steers environments of the demo world in lockstep.

A driver (`Driver`) maps the observations of the environments that need actions to action chunks
`[b, h, 23]` (absolute, dataset units); each environment executes the first `n_exec` actions of
its chunk, then asks again (receding horizon). Drivers here: the scripted expert, the expert
with errors the size of a policy's (`NoisyExpertDriver`), holding the last action, zero actions
and a replay of random recorded chunks (the calibration rows,
`pi0_armfix.tools.closed_loop_calibration`); a trained run drives through
`pi0_armfix.policies.execution.Replanner` around its `RunPolicy` (`pi0_armfix.evaluate
--closed_loop`).

Per episode the result of every phase (`sim.world`), whether navigation, manipulation and the task
succeeded (every phase of that kind did), the time to success, and the traces of the base pose and
the arm joints for the figure.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, Protocol

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from pi0_armfix.sim import env as env_lib  # noqa: E402
from pi0_armfix.sim.expert import demonstration  # noqa: E402
from pi0_armfix.sim.outcomes import FAILURE_REASONS, PhaseResult  # noqa: E402
from pi0_armfix.sim.world import (ACTION_DIM, BASE_DIMS, STATE_ARM, DemoSpec, World,  # noqa: E402
                                  tolerances)

KINDS = ("navigation", "manipulation", "task")


class Driver(Protocol):
    """What steers a rollout: a trained run's `execution.Replanner`, or a calibration row."""

    def start(self, envs: Sequence[env_lib.DemoWorldEnv]) -> None:
        """Called once the environments are reset."""

    def __call__(self, active: Sequence[int], observations: Sequence[dict]) -> np.ndarray:
        """Chunks `[len(active), h, 23]` for the environments `active` (their observations)."""


class ExpertDriver:
    """The scripted teleoperator of each episode (privileged: reads the world)."""

    def start(self, envs):
        self._experts = [env.unwrapped.expert() for env in envs]

    def __call__(self, active, observations):
        return np.stack([self._experts[i].act() for i in active])[:, None]


class NoisyExpertDriver:
    """The scripted teleoperator with an error added to every action: N(0, `noise_std`^2) per dim
    (data units, `[23]`), drawn afresh every `hold` steps and held in between, like the error of a
    sampled chunk, which is off by much the same amount for the steps executed from it. What a
    policy as wrong as a trained one, but otherwise perfect, would achieve."""

    def __init__(self, noise_std: np.ndarray, hold: int, seed: int = 0):
        self.noise_std, self.hold = np.asarray(noise_std, np.float64), max(int(hold), 1)
        self.seed = seed

    def start(self, envs):
        self._experts = [env.unwrapped.expert() for env in envs]
        self._rngs = [np.random.default_rng([self.seed, i]) for i in range(len(envs))]
        self._noise = [np.zeros(ACTION_DIM) for _ in envs]
        self._steps = [0 for _ in envs]

    def __call__(self, active, observations):
        actions = []
        for i in active:
            if self._steps[i] % self.hold == 0:
                self._noise[i] = self._rngs[i].normal(0.0, 1.0, ACTION_DIM) * self.noise_std
            self._steps[i] += 1
            actions.append(self._experts[i].act() + self._noise[i])
        return np.stack(actions)[:, None]


class HoldDriver:
    """Holds the last action: the command the robot starts with (posture, grippers open, base
    still), never changed. Persistence in closed loop."""

    def start(self, envs):
        self._first = [env.unwrapped.world.command.copy() for env in envs]

    def __call__(self, active, observations):
        return np.stack([self._first[i] for i in active])[:, None].astype(np.float32)


class ZeroDriver:
    """Every action 0: base still, joints driven to 0, grippers half-way (closed)."""

    def start(self, envs):
        pass

    def __call__(self, active, observations):
        return np.zeros((len(active), 1, ACTION_DIM), np.float32)


class RecordedChunkDriver:
    """Replays a random chunk of `horizon` recorded actions of the demo dataset (seed 0, its
    first `episodes` episodes), whatever the observation: motion of the right kind and size, at
    the wrong time and place."""

    def __init__(self, horizon: int, seed: int = 0, episodes: int = 10):
        # The demo dataset's actions are the expert's demonstrations in the world of seed 0.
        self.actions = [np.asarray(list(demonstration(World(DemoSpec(), i))), np.float32)
                        for i in range(episodes)]
        self.horizon, self.rng = horizon, np.random.default_rng(seed)

    def start(self, envs):
        pass

    def __call__(self, active, observations):
        chunks = []
        for _ in active:
            episode = self.actions[self.rng.integers(len(self.actions))]
            start = self.rng.integers(len(episode) - self.horizon + 1)
            chunks.append(episode[start:start + self.horizon])
        return np.stack(chunks)


@dataclasses.dataclass
class EpisodeRecord:
    """One closed-loop episode. `pose`: [T, 3] base x, y, heading; `arms`: [T, 14] measured arm
    joints (left, right); `seconds`: to the end of the plan (success or not)."""

    episode: int
    task: str
    results: list[PhaseResult]
    success: dict[str, bool]
    seconds: float
    pose: np.ndarray
    arms: np.ndarray


def _arms(state: np.ndarray) -> np.ndarray:
    return np.concatenate([state[STATE_ARM["left"]], state[STATE_ARM["right"]]])


def rollout(driver: Driver, episodes: Sequence[int], *, spec: DemoSpec, n_exec: int = 1,
            progress: bool = True, desc: str = "closed loop") -> list[EpisodeRecord]:
    """Runs `driver` on `episodes` of `spec` (one environment each, in lockstep).

    Args:
      n_exec: actions of each chunk executed before the driver is asked again (chunks shorter
        than that are executed whole).
    """
    if n_exec < 1:
        raise ValueError(f"n_exec = {n_exec} must be >= 1 (actions executed per chunk)")
    envs = [env_lib.DemoWorldEnv(spec) for _ in episodes]
    observations = [env.reset(seed=int(e))[0] for env, e in zip(envs, episodes)]
    driver.start(envs)
    queues: list[list[np.ndarray]] = [[] for _ in envs]
    poses = [[env.world.pose.copy()] for env in envs]
    arms = [[_arms(o[env_lib.STATE])] for o in observations]
    active = list(range(len(envs)))
    bar = tqdm(total=len(envs), desc=desc, unit="ep", disable=not progress, leave=False)
    while active:
        asking = [i for i in active if not queues[i]]
        if asking:
            chunks = driver(asking, [observations[i] for i in asking])
            for i, chunk in zip(asking, chunks):
                queues[i] = list(chunk[:n_exec])
        for i in list(active):
            observations[i], _, terminated, _, _ = envs[i].step(queues[i].pop(0))
            poses[i].append(envs[i].world.pose.copy())
            arms[i].append(_arms(observations[i][env_lib.STATE]))
            if terminated:
                active.remove(i)
                bar.update()
    bar.close()
    records = []
    for env, episode, pose, arm in zip(envs, episodes, poses, arms):
        world = env.world
        records.append(EpisodeRecord(int(episode), world.task.prompt, list(world.results),
                                     env_lib.episode_success(world.results),
                                     world.frame / spec.fps, np.array(pose), np.array(arm)))
    return records


def summarize(records: Sequence[EpisodeRecord]) -> dict[str, Any]:
    """Success rates over episodes (`success/<kind>`: every phase of that kind succeeded), over
    phases (`phase_success/<kind>`), the phases' mean progress (`progress/<kind>`, see
    `PhaseResult`), the fraction of phases that failed for each reason
    (`failure/<kind>/<reason>`, `sim.outcomes.FAILURE_REASONS`: they add up to 1 - phase success),
    the gripper switches per phase (`gripper_switches/<kind>`), why the base did not stop
    (`not_stopped/slowest_base_median`: over the `not_stopped` phases, the median of the base
    command nearest a stop within the radius, `PhaseResult.slowest_base`; `not_stopped/held_by/
    <x|y|yaw>`: the share of them whose largest component there was that one) and the mean
    seconds to a successful task."""
    summary: dict[str, Any] = {"episodes": len(records)}
    for kind in KINDS:
        summary[f"success/{kind}"] = float(np.mean([r.success[kind] for r in records]))
    for kind in KINDS[:2]:
        phases = [p for r in records for p in r.results if p.kind == kind]
        for name, value in (("phase_success", lambda p: p.success), ("progress",
                                                                    lambda p: p.progress)):
            summary[f"{name}/{kind}"] = (float(np.mean([value(p) for p in phases])) if phases
                                         else float("nan"))
        for reason in FAILURE_REASONS[kind]:
            summary[f"failure/{kind}/{reason}"] = (
                float(np.mean([p.reason == reason for p in phases])) if phases else float("nan"))
        summary[f"gripper_switches/{kind}"] = (
            float(np.mean([p.gripper_switches for p in phases])) if phases else float("nan"))
    creeping = [p for r in records for p in r.results if p.reason == "not_stopped"]
    summary["not_stopped/slowest_base_median"] = (
        float(np.median([p.slowest_base for p in creeping])) if creeping else float("nan"))
    for dim in BASE_DIMS:
        summary[f"not_stopped/held_by/{dim}"] = (
            float(np.mean([p.slowest_dim == dim for p in creeping])) if creeping
            else float("nan"))
    done = [r.seconds for r in records if r.success["task"]]
    summary["seconds_to_success"] = float(np.mean(done)) if done else float("nan")
    return summary


def format_summary(summary: dict[str, Any]) -> str:
    """Success over episodes and over phases, and the phases' mean progress, per kind."""
    lines = [f"{'':<14}{'episodes':>10}{'phases':>10}{'progress':>10}"]
    for kind in KINDS:
        cells = [summary.get(f"{name}/{kind}") for name in ("phase_success", "progress")]
        lines.append(f"{kind:<14}{summary[f'success/{kind}']:>10.3f}"
                     + "".join(f"{c:>10.3f}" if c is not None else f"{'':>10}" for c in cells))
    for kind in KINDS[:2]:
        reasons = ", ".join(f"{reason} {summary[f'failure/{kind}/{reason}']:.2f}"
                            for reason in FAILURE_REASONS[kind]
                            if summary.get(f"failure/{kind}/{reason}", 0) > 0)
        lines.append(f"{kind} phases failed: {reasons or 'none'}; gripper switches per phase "
                     f"{summary[f'gripper_switches/{kind}']:.1f}")
    if not math.isnan(summary.get("not_stopped/slowest_base_median", math.nan)):
        held = ", ".join(f"{dim} {summary[f'not_stopped/held_by/{dim}']:.2f}" for dim in BASE_DIMS)
        lines.append(f"not stopped: the base command nearest a stop, median "
                     f"{summary['not_stopped/slowest_base_median']:.3f} (largest component: "
                     f"{held})")
    lines.append(f"{summary['episodes']} episodes; mean time to task success "
                 f"{summary['seconds_to_success']:.1f} s")
    return "\n".join(lines)


def episode_details(records: Sequence[EpisodeRecord]) -> list[dict[str, Any]]:
    """Per episode, what a study resamples and a reader audits: its task, whether each kind
    succeeded, its seconds and every phase's result (`PhaseResult` as a dict)."""
    return [{"episode": r.episode, "task": r.task, **r.success, "seconds": r.seconds,
             "phases": [dataclasses.asdict(p) for p in r.results]} for r in records]


def success_curve(driver: Driver, episodes: Sequence[int], *, spec: DemoSpec,
                  factors: Sequence[float], n_exec: int = 1, progress: bool = True
                  ) -> dict[str, dict[str, Any]]:
    """`{factor: summarize(...) | {"episodes_detail": episode_details(...)}}`: `driver` on
    `episodes` in the world with every success tolerance times each factor
    (`sim.world.tolerances`; 1 = the world as it is), so a policy that misses by a little is told
    from one that misses by far; the per-episode outcomes kept so that a study's interval at each
    factor holds the episodes' sampling error too."""
    curve = {}
    for factor in factors:
        records = rollout(driver, episodes, spec=tolerances(spec, factor), n_exec=n_exec,
                          progress=progress, desc=f"closed loop at {factor:g}x tolerance")
        curve[f"{factor:g}"] = summarize(records) | {"episodes_detail": episode_details(records)}
    return curve


def plot_success_curves(curves: dict[str, dict[str, dict[str, Any]]], path, title: str) -> None:
    """Phase success of navigation and manipulation against the tolerance factor, one line per
    policy (`{name: success_curve(...)}`)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, kind in zip(axes, KINDS[:2]):
        for name, curve in curves.items():
            factors = [float(f) for f in curve]
            ax.plot(factors, [curve[f][f"phase_success/{kind}"] for f in curve], "o-", label=name)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("tolerance factor (1 = the world's arrival radius, heading, stop speed, "
                      "reach)", fontsize=8)
        ax.set_ylabel(f"{kind} phases succeeded")
        ax.set_ylim(-0.03, 1.03)
        ax.set_title(kind)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_rollouts(records: Sequence[EpisodeRecord], expert: Sequence[EpisodeRecord],
                  path, title: str) -> None:
    """One row per episode: the top-down base path and two arm joints of each arm over time,
    the policy (solid) against the expert on the same episode (dashed)."""
    rows = len(records)
    # constrained: the suptitle and every panel's title get their room (tight_layout cut them)
    fig, axes = plt.subplots(rows, 3, figsize=(13, 3.2 * rows + 0.6), squeeze=False,
                             layout="constrained")
    for row, (mine, theirs) in enumerate(zip(records, expert)):
        ax = axes[row, 0]
        for record, style in ((theirs, "--"), (mine, "-")):
            ax.plot(record.pose[:, 0], record.pose[:, 1], style, color="C0" if style == "-"
                    else "0.5")
        ax.plot(*mine.pose[0, :2], "ko", ms=4)
        ax.set_aspect("equal", adjustable="datalim")
        flags = " ".join(f"{k[:3]} {'ok' if mine.success[k] else 'fail'}" for k in KINDS)
        ax.set_title(f"episode {mine.episode}: {flags}", fontsize=9)
        for col, (name, joints) in enumerate((("left arm", (0, 3)), ("right arm", (7, 10))),
                                             start=1):
            ax = axes[row, col]
            for j, colour in zip(joints, ("C1", "C2")):
                for record, style in ((theirs, "--"), (mine, "-")):
                    seconds = np.linspace(0, record.seconds, len(record.arms))
                    ax.plot(seconds, record.arms[:, j], style, color=colour,
                            alpha=0.6 if style == "--" else 1.0,
                            label=f"joint {j % 7}" if style == "-" else None)
            ax.set_title(f"{name} (policy solid, expert dashed)", fontsize=9)
            ax.set_xlabel("s")
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(title)
    fig.savefig(path, dpi=80)
    plt.close(fig)
