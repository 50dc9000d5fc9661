"""Where a run's wall time goes, before and after the compilation cache: whole processes, by part.

    python -m pi0_armfix.bench walltime [--config=configs/arm_focused.py] [--steps=20] \
        [--evaluations=1] [--episodes=2] [--repeats=3] [--modes=before,first,after] \
        [--set=KEY=VALUE ...] [--cache=DIR] [--no-server] [--output=FILE.json]

A pass runs, as separate processes, `python -m pi0_armfix.train` (`--steps` steps into a fresh
run folder, `--evaluations` held-out evaluations, the last at the end), `python -m
pi0_armfix.evaluate --closed_loop --episodes=E` on that run (0 skips it), and `python -m
pi0_armfix.serve` until its `/healthz` answers (the server's load and warm-up). The modes:
**before**, `PI0_ARMFIX_COMPILATION_CACHE=0` (every function compiled in every process);
**first**, one pass with the project's compilation cache empty for these programs (it compiles
them all and writes them: a user's first run); **after**, the cache warm (a user's next run).
`--repeats` passes of before and after alternate so that machine noise hits both alike. All
processes share one cache folder (`--cache`, default a temporary one) whose demo dataset is
generated once, first, by its own timed process. Printed: each part's median over its passes
[min, max] per mode and after over before; the parts are the run's own `wall_time.json` and the
closed loop's (`pi0_armfix.wall_time`), the whole-process seconds beside them (imports and
start-up are the difference). Run it on quiet cores: the numbers are wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pi0_armfix import wall_time
from pi0_armfix.bench import serve as bench_serve

REPO_ROOT = bench_serve.REPO_ROOT
MODES = ("before", "first", "after")


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench walltime")
    parser.add_argument("--config", default="configs/arm_focused.py")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a config override for the run (repeatable): --set=model.preset=tiny")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--evaluations", type=int, default=1,
                        help="held-out evaluations, evenly spaced, the last at the end")
    parser.add_argument("--episodes", type=int, default=2,
                        help="closed-loop episodes in the demo world (0: no closed loop)")
    parser.add_argument("--server", action=argparse.BooleanOptionalAction, default=True,
                        help="time the server's start until /healthz answers")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--modes", default="before,first,after",
                        help="which of before (no cache), first (one run that fills the cache) "
                        "and after (the cache warm) to measure; after without first needs a "
                        "--cache that holds these programs already")
    parser.add_argument("--cache", default="", help="PI0_ARMFIX_CACHE for every process "
                        "('' = a temporary folder)")
    parser.add_argument("--output", default="", help="write every measurement to this JSON file")
    args = parser.parse_args(argv[1:])
    if args.steps < 1 or args.repeats < 1 or args.episodes < 0:
        parser.error("--steps and --repeats must be >= 1, --episodes >= 0")
    unknown = set(args.modes.split(",")) - set(MODES)
    if unknown or not args.modes:
        parser.error(f"--modes={args.modes}: each must be one of {', '.join(MODES)}")
    if not 1 <= args.evaluations <= args.steps or args.steps % args.evaluations:
        parser.error(f"--evaluations={args.evaluations} must divide --steps={args.steps} "
                     "(evaluated every steps / evaluations steps)")
    return args


def _env(cache: Path, mode: str) -> dict[str, str]:
    env = dict(os.environ, PI0_ARMFIX_CACHE=str(cache), PYTHONPATH=str(REPO_ROOT))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the project's own cache, or none
    env.pop("PI0_ARMFIX_COMPILATION_CACHE", None)
    if mode == "before":
        env["PI0_ARMFIX_COMPILATION_CACHE"] = "0"
    return env


def _timed(command: list[str], env: dict[str, str]) -> float:
    """Seconds the whole process took; its output is shown only when it fails."""
    start = time.perf_counter()
    done = subprocess.run(command, cwd=REPO_ROOT, env=env, capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}:\n"
                           f"{done.stdout[-3000:]}{done.stderr[-3000:]}")
    return time.perf_counter() - start


def measure(args: argparse.Namespace, folder: Path, cache: Path, mode: str) -> dict[str, float]:
    """One pass in one mode: `{part: seconds}`, whole processes and their parts."""
    env = _env(cache, mode)
    workdir = folder / "run"
    every = args.steps // args.evaluations
    seconds = {"train: whole process": _timed(
        [sys.executable, "-m", "pi0_armfix.train", f"--config={args.config}",
         f"--workdir={workdir}", f"--config.train.total_steps={args.steps}",
         f"--config.eval.every={every}", *(f"--config.{o}" for o in args.set)], env)}
    spent = wall_time.load(workdir / wall_time.FILE)
    seconds |= {f"train: {name}": s for name, s in spent["parts"].items()}
    seconds["train: outside the run (imports, flags, exit)"] = (
        seconds["train: whole process"] - spent["total"])
    if args.episodes:
        seconds["closed loop: whole process"] = _timed(
            [sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={workdir}",
             "--closed_loop", f"--episodes={args.episodes}"], env)
        spent = wall_time.load(sorted(workdir.glob(f"eval/step_*/*.{wall_time.FILE}"))[-1])
        seconds |= {f"closed loop: {name}": s for name, s in spent["parts"].items()}
    if args.server:
        start = time.perf_counter()
        server = bench_serve.start_server(workdir, bench_serve.free_port(), env=env)
        seconds["server: start to /healthz (load, warm-up)"] = time.perf_counter() - start
        server.terminate()
        server.wait(30)
    return seconds


MODE_NAMES = {"before": "before: no compilation cache", "first": "first run: the cache filled",
              "after": "after: warm cache"}


def table(passes: dict[str, list[dict[str, float]]]) -> str:
    """Markdown: each part's median [min, max] over the passes of each mode measured, and after
    over before (over the first run where no pass ran without the cache)."""
    modes = [m for m in MODES if passes.get(m)]
    parts = list(dict.fromkeys(p for mode in modes for run in passes[mode] for p in run))
    base = "before" if "before" in modes else "first"
    lines = ["| part | " + " | ".join(f"{MODE_NAMES[m]}, median [min, max] s" for m in modes)
             + f" | after / {base} |", "|---" * (len(modes) + 2) + "|"]
    for part in parts:
        cells, medians = [], {}
        for mode in modes:
            values = [run[part] for run in passes[mode] if part in run]
            if not values:
                cells.append("-")
                continue
            medians[mode] = statistics.median(values)
            cells.append(f"{medians[mode]:.1f}" if len(values) == 1 else
                         f"{medians[mode]:.1f} [{min(values):.1f}, {max(values):.1f}]")
        ratio = (f"{medians['after'] / medians[base]:.2f}"
                 if medians.get(base, 0) > 0 and "after" in medians else "-")
        lines.append(f"| {part} | " + " | ".join(cells) + f" | {ratio} |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    args = _parse(argv)
    modes = args.modes.split(",")
    with tempfile.TemporaryDirectory() as scratch:
        cache = Path(args.cache or Path(scratch) / "cache").absolute()
        generation = None
        if not any(o.startswith("data.root=") for o in args.set):  # the embedded demo
            generation = _timed([sys.executable, "-c", "from pi0_armfix.data.formats import "
                                 "demo; demo.demo_root()"], _env(cache, "before"))
            print(f"demo dataset (generated on first use, then read from {cache}): "
                  f"{generation:.1f} s (whole process)", flush=True)
        passes: dict[str, list[dict[str, float]]] = {mode: [] for mode in modes}
        if "first" in modes:  # once: it fills the compilation cache the "after" passes read
            passes["first"].append(measure(args, Path(scratch) / "first", cache, "after"))
            _said("first run", passes["first"][-1])
        for repeat in range(args.repeats):
            for mode in (m for m in ("before", "after") if m in modes):
                passes[mode].append(measure(args, Path(scratch) / f"{mode}_{repeat}", cache, mode))
                _said(f"repeat {repeat + 1}/{args.repeats} {mode}", passes[mode][-1])
    print(f"\n{args.config}, {args.steps} steps, {args.evaluations} held-out evaluation(s)"
          + (f", {args.episodes} closed-loop episodes" if args.episodes else "")
          + f"; {args.repeats} repeats, {os.cpu_count()} cores:\n{table(passes)}")
    if args.output:
        Path(args.output).write_text(json.dumps(
            {"args": vars(args), "demo_generation": generation, "passes": passes}, indent=2))


def _said(what: str, seconds: dict[str, float]) -> None:
    print(f"{what}: train {seconds['train: whole process']:.1f} s", flush=True)
