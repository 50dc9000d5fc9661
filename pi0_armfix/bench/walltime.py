"""Where a run's wall time goes, before and after the compilation cache: whole processes, by part.

    python -m pi0_armfix.bench walltime [--config=configs/arm_focused.py] [--steps=20] \
        [--evaluations=1] [--episodes=2] [--repeats=3] [--set=KEY=VALUE ...] [--cache=DIR] \
        [--no-prime] [--no-server] [--output=FILE.json]

Each repeat runs, as separate processes and once in each mode, `python -m pi0_armfix.train`
(`--steps` steps into a fresh run folder, `--evaluations` held-out evaluations, the last at the
end), `python -m pi0_armfix.evaluate --closed_loop --episodes=E` on that run (0 skips it), and
`python -m pi0_armfix.serve` until its `/healthz` answers (the server's load and warm-up). The
modes: **before**, `PI0_ARMFIX_COMPILATION_CACHE=0` (every function compiled in every process);
**after**, the project's compilation cache, filled by one untimed pass first (what a user's
second run meets; `--no-prime` where `--cache` holds it already). The modes alternate within a repeat so that machine noise hits both alike. All
processes share one cache folder (`--cache`, default a temporary one) whose demo dataset is
generated once, first, by its own timed process. Printed: each part's median over the repeats
[min, max] in both modes and their ratio; the parts are the run's own `wall_time.json` and the
closed loop's (`pi0_armfix.wall_time`), the whole-process seconds beside them (imports and start-up
are the difference). Run it on quiet cores: the numbers are wall time.
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

REPO_ROOT = Path(__file__).resolve().parents[2]
MODES = ("before", "after")


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
    parser.add_argument("--prime", action=argparse.BooleanOptionalAction, default=True,
                        help="fill the compilation cache with one untimed pass first (--no-prime: "
                        "--cache holds it already, from an earlier pass of the same programs)")
    parser.add_argument("--cache", default="", help="PI0_ARMFIX_CACHE for every process "
                        "('' = a temporary folder)")
    parser.add_argument("--output", default="", help="write every measurement to this JSON file")
    args = parser.parse_args(argv[1:])
    if args.steps < 1 or args.repeats < 1 or args.episodes < 0:
        parser.error("--steps and --repeats must be >= 1, --episodes >= 0")
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


def table(passes: dict[str, list[dict[str, float]]]) -> str:
    """Markdown: each part's median [min, max] over the passes in both modes, and after/before."""
    parts = list(dict.fromkeys(p for mode in MODES for run in passes[mode] for p in run))
    lines = [f"| part | before: no compilation cache, median [min, max] s | after: warm cache "
             f"| after / before |", "|---|---|---|---|"]
    for part in parts:
        cells, medians = [], []
        for mode in MODES:
            values = [run[part] for run in passes[mode] if part in run]
            if not values:
                cells.append("-")
                medians.append(float("nan"))
                continue
            medians.append(statistics.median(values))
            cells.append(f"{medians[-1]:.1f} [{min(values):.1f}, {max(values):.1f}]")
        ratio = medians[1] / medians[0] if medians[0] > 0 else float("nan")
        lines.append(f"| {part} | {cells[0]} | {cells[1]} | {ratio:.2f} |")
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    args = _parse(argv)
    with tempfile.TemporaryDirectory() as scratch:
        cache = Path(args.cache or Path(scratch) / "cache").absolute()
        generation = None
        if not any(o.startswith("data.root=") for o in args.set):  # the embedded demo
            generation = _timed([sys.executable, "-c", "from pi0_armfix.data.formats import "
                                 "demo; demo.demo_root()"], _env(cache, "before"))
            print(f"demo dataset (generated on first use, then read from {cache}): "
                  f"{generation:.1f} s (whole process)", flush=True)
        if args.prime:
            measure(args, Path(scratch) / "prime", cache, "after")  # fills the compilation cache
        passes: dict[str, list[dict[str, float]]] = {mode: [] for mode in MODES}
        for repeat in range(args.repeats):
            for mode in MODES:
                passes[mode].append(measure(args, Path(scratch) / f"{mode}_{repeat}", cache, mode))
                print(f"repeat {repeat + 1}/{args.repeats} {mode}: train "
                      f"{passes[mode][-1]['train: whole process']:.1f} s", flush=True)
    print(f"\n{args.config}, {args.steps} steps, {args.evaluations} held-out evaluation(s)"
          + (f", {args.episodes} closed-loop episodes" if args.episodes else "")
          + f"; {args.repeats} repeats, {os.cpu_count()} cores:\n{table(passes)}")
    if args.output:
        Path(args.output).write_text(json.dumps(
            {"args": vars(args), "demo_generation": generation, "passes": passes}, indent=2))
