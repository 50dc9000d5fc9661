"""Closed-loop sanity bounds of the demo world: what a policy that knows the task, one that does
nothing and one that moves at random score, and how fast the environment steps.

    python -m pi0_armfix.bench sim [--episodes=50] [--policies=expert,zero,recorded]

expert     the scripted teleoperator (the demo dataset's operator), one action per step;
zero       every action 0;
recorded   a random chunk of 32 recorded demo actions, 16 executed before the next draw.
Episodes 0..N-1 of world seed 1000 (the closed-loop evaluation's). Prints success over episodes
and phases and the mean progress per kind (`sim.rollout.format_summary`), and environment steps
per second (rendering included).
"""

from __future__ import annotations

import argparse
import time

from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout
from pi0_armfix.sim.world import DemoSpec

POLICIES = ("expert", "zero", "recorded")


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench sim")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--policies", default=",".join(POLICIES))
    return parser.parse_args(argv[1:])


def main(argv: list[str]) -> None:
    args = _parse(argv)
    names = [n for n in args.policies.split(",") if n]
    unknown = [n for n in names if n not in POLICIES]
    if unknown:
        raise SystemExit(f"--policies names {unknown}; choose from {list(POLICIES)}")
    spec = DemoSpec(seed=env_lib.EVAL_SEED)
    for name in names:
        policy, n_exec = {"expert": (rollout.ExpertDriver, 1), "zero": (rollout.ZeroDriver, 1),
                          "recorded": (lambda: rollout.RecordedChunkDriver(32), 16)}[name]
        policy = policy()
        start = time.perf_counter()
        records = rollout.rollout(policy, range(args.episodes), spec=spec, n_exec=n_exec,
                                  desc=name)
        seconds = time.perf_counter() - start
        steps = sum(len(r.pose) - 1 for r in records)
        print(f"== {name}: {args.episodes} episodes, {steps} steps, "
              f"{steps / seconds:,.0f} env steps/s")
        print(rollout.format_summary(rollout.summarize(records)))
