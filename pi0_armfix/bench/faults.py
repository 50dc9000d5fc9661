"""Fault injection: a training run killed again and again resumes bitwise every time.

    python -m pi0_armfix.bench faults [--kills=20] [--steps=40] [--seed=0]

1. A reference run: `pi0_armfix/configs/loss_balanced.py` (loss-balancer state) with EMA params
   and a curriculum switch, on the `tiny` preset and a small demo dataset, `--steps` steps
   uninterrupted, a checkpoint after every step and a record of every step.
2. The same command in another folder, interrupted and restarted until `--kills` faults are in
   (a run that finishes first is followed by another), then run to its end. The faults cycle
   through
     kill-random   SIGKILL at a random moment of the steps still to run (start-up included),
     kill-saving   SIGKILL the moment a checkpoint's temporary folder appears (a save in flight),
     term-random   SIGTERM at a random moment (a preemption: the run saves and exits 143).
   It saves every 3 steps, so kills land between, before and during saves.
3. Checks: every restart resumed from a checkpoint equal, array for array, to the reference's
   checkpoint of that step; no checkpoint was damaged or set aside; each run's final state and
   every logged loss equal the reference's. A tally is printed; the exit status is 1 on a
   mismatch.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

FAULTS = ("kill-random", "kill-saving", "term-random")
REPO = Path(__file__).resolve().parents[2]
TIMING_KEYS = ("steps_per_sec", "data_wait")


def _overrides(root: Path, steps: int, checkpoint_every: int) -> list[str]:
    arm_heavy = root.parent / "arm_heavy.json"
    arm_heavy.write_text(json.dumps({"episodes": [1, 3]}))
    values = {
        "model.preset": "tiny", "data.root": str(root), "train.total_steps": steps,
        "train.batch_size": 8, "train.log_every": 1, "train.checkpoint_every": checkpoint_every,
        "train.keep_checkpoints": 10_000, "optim.warmup_steps": 1, "optim.ema_decay": 0.9,
        "eval.every": 0, "eval.episodes": 2, "data.arm_heavy_episodes": str(arm_heavy),
        "data.curriculum": ((steps // 2, {"full": 1.0}),
                            (steps, {"full": 0.5, "arm_heavy": 0.5})),
    }
    return [f"--config.{k}={v if isinstance(v, str) else repr(v)}" for k, v in values.items()]


def _command(workdir: Path, overrides: list[str]) -> list[str]:
    return [sys.executable, "-m", "pi0_armfix.train",
            f"--config={REPO / 'configs' / 'loss_balanced.py'}", f"--workdir={workdir}", *overrides]


def _env(cache: Path) -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(REPO), JAX_PLATFORMS="cpu",
                JAX_COMPILATION_CACHE_DIR=str(cache / "jax"),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", PI0_ARMFIX_CACHE=str(cache))


def _temporary(workdir: Path) -> set[str]:
    """Orbax's temporary step folders (a save in flight, or one a kill cut short)."""
    folder = workdir / "checkpoints"
    return ({p.name for p in folder.iterdir() if ".orbax-checkpoint-tmp" in p.name}
            if folder.is_dir() else set())


def _latest_checkpoint(workdir: Path) -> int:
    folder = workdir / "checkpoints"
    steps = [int(p.name) for p in folder.iterdir() if p.name.isdigit()] if folder.is_dir() else []
    return max(steps, default=0)


def _steps_done(workdir: Path, since: float) -> int | None:
    """The last step logged since the time `since` (the run logs every step); None if none."""
    path = workdir / "metrics.jsonl"
    if not path.exists() or path.stat().st_mtime < since:
        return None
    try:
        records = _records(workdir)
    except ValueError:  # a line being rewritten by a restart
        return None
    return max((r["step"] for r in records if "loss" in r), default=None)


def _interrupted_run(workdir: Path, overrides: list[str], env: dict[str, str], fault: str,
                     target: int, pause: float, log: Path) -> tuple[int | None, str]:
    """Starts the run and injects `fault` once it has logged step `target` (0: in its start-up),
    `pause` seconds later for the random faults, at its next save in flight for `kill-saving`;
    returns (its exit status, what happened) once it has ended."""
    with open(log, "a") as out:
        stale = _temporary(workdir)  # left by an earlier kill: not a save of this process
        start = time.time()
        process = subprocess.Popen(_command(workdir, overrides), env=env, cwd=REPO, stdout=out,
                                   stderr=subprocess.STDOUT)
        reached = None  # when step `target` was logged
        what = "finished before the fault"
        while process.poll() is None:
            done = _steps_done(workdir, start)
            if reached is None and (target == 0 or (done or 0) >= target):
                reached = time.time()
            saving = bool(_temporary(workdir) - stale)
            due = reached is not None and (
                saving if fault == "kill-saving" else time.time() - reached >= pause)
            if due:
                process.send_signal(signal.SIGTERM if fault == "term-random" else signal.SIGKILL)
                logged = "nothing logged yet" if done is None else f"last logged step {done}"
                what = (f"{fault} {time.time() - start:.2f} s into the process ({logged})"
                        + (", save in flight" if saving else ""))
                break
            time.sleep(0.002)
        return process.wait(), what


def _resumed_steps(log: Path) -> list[int]:
    return [int(s) for s in re.findall(r"resumed from \S+/checkpoints/(\d+)", log.read_text())]


def _state(workdir: Path, step: int):
    import jax

    from pi0_armfix import sharding
    from pi0_armfix.training import checkpoint

    ckpts = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True)
    state, _, _ = ckpts.restore_for_eval(step, sharding.make_mesh(1), items=None)
    return jax.device_get(state)


def _equal(a, b) -> bool:
    import jax
    import numpy as np

    if jax.tree.structure(a) != jax.tree.structure(b):
        return False
    return all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def _records(workdir: Path) -> list[dict]:
    from pi0_armfix.training import metrics_log

    return metrics_log.read_metrics(workdir / metrics_log.METRICS_FILE)


def _losses(workdir: Path) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in _records(workdir)]


def run(kills: int, steps: int, seed: int, folder: Path) -> dict[str, object]:
    """The benchmark in `folder`; returns its tally."""
    from pi0_armfix.data.formats import demo

    root = demo.write_demo_dataset(folder / "demo", demo.DemoSpec(num_episodes=8))
    env = _env(folder / "cache")
    reference = folder / "reference"
    result = subprocess.run(_command(reference, _overrides(root, steps, 1)), env=env, cwd=REPO,
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"the reference run failed:\n{result.stderr[-3000:]}")
    rates = sorted(r["steps_per_sec"] for r in _records(reference) if "steps_per_sec" in r)
    seconds_per_step = 1.0 / rates[len(rates) // 2]

    rng = random.Random(seed)
    overrides = _overrides(root, steps, 3)
    tally: dict[str, object] = {f: 0 for f in FAULTS}
    events, statuses, resumed, equal_resumes, set_aside = [], [], [], 0, []
    finals, records = [], []
    while len(events) < kills:  # a run that finishes before all faults are in: another run
        workdir = folder / f"interrupted-{len(finals)}"
        log = folder / f"interrupted-{len(finals)}.log"
        while len(events) < kills and _latest_checkpoint(workdir) < steps:
            fault = FAULTS[len(events) % len(FAULTS)]
            # A moment among the steps still to run (from the start-up on).
            target = rng.randint(_latest_checkpoint(workdir), steps - 1)
            status, what = _interrupted_run(workdir, overrides, env, fault, target,
                                            rng.uniform(0.0, seconds_per_step), log)
            if what == "finished before the fault":
                continue
            events.append(what)
            statuses.append(status)
            tally[fault] += 1
            print(f"  fault {len(events)}/{kills}: {what}; exit {status}", flush=True)
        for _ in range(3):  # restarts until it has finished
            if _latest_checkpoint(workdir) == steps:
                break
            with open(log, "a") as out:
                subprocess.run(_command(workdir, overrides), env=env, cwd=REPO, stdout=out,
                               stderr=subprocess.STDOUT)
        else:
            raise SystemExit(f"the interrupted run does not finish: see {log}")
        steps_resumed = _resumed_steps(log)
        resumed += steps_resumed
        equal_resumes += sum(_equal(_state(workdir, s), _state(reference, s))
                             for s in steps_resumed)
        set_aside += sorted(str(p) for p in workdir.glob("checkpoints.*"))
        finals.append(_equal(_state(workdir, steps), _state(reference, steps)))
        records.append(_losses(workdir) == _losses(reference))
    tally.update(
        faults=len(events), runs=len(finals),
        during_save=sum("save in flight" in e for e in events),
        preemption_exits_143=statuses.count(128 + signal.SIGTERM),
        resumes=len(resumed), bitwise_resumes=equal_resumes,
        set_aside_folders=set_aside,
        final_states_bitwise=f"{sum(finals)}/{len(finals)}",
        records_equal=f"{sum(records)}/{len(records)}",
    )
    return tally


def main(argv: Sequence[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench faults")
    parser.add_argument("--kills", type=int, default=20, help="faults injected")
    parser.add_argument("--steps", type=int, default=40, help="steps of the run")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random moments")
    args = parser.parse_args(argv[1:])
    with tempfile.TemporaryDirectory(prefix="faults-") as folder:
        print(f"fault injection: {args.kills} faults into a {args.steps}-step run "
              "(pi0_armfix/configs/loss_balanced.py, tiny preset, EMA, curriculum)", flush=True)
        tally = run(args.kills, args.steps, args.seed, Path(folder))
    print("tally:")
    for key, value in tally.items():
        print(f"  {key:<24}{value}")
    runs = f"{tally['runs']}/{tally['runs']}"
    ok = (tally["bitwise_resumes"] == tally["resumes"] and tally["final_states_bitwise"] == runs
          and tally["records_equal"] == runs and not tally["set_aside_folders"])
    print("every restart resumed bitwise" if ok else "MISMATCH: see the tally")
    if not ok:
        sys.exit(1)


if __name__ == "__main__":
    main(sys.argv)
