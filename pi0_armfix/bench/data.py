"""Data benchmark: `python -m pi0_armfix.bench data [--frames=5000000] [flags]`.

dataset   a LeRobot v3.0 root of `--frames` frames (23-D float32 actions and state, episodes of
          `--episode_frames` on average, `--episodes_per_file` per parquet file, as LeRobot
          writes them), generated once into `<cache>/bench-lerobot-v3-<frames>` (`--cache_dir`,
          else $PI0_ARMFIX_CACHE, else ~/.cache/pi0_armfix). B1K-like values: base velocity
          commands, random-walk joints, grippers at +-1, a constant torso dim.
stats     `compute_norm_stats`' work (mean/std/q01/q99 of actions and state, one streaming pass
          from parquet through `LeRobotSource.iter_blocks`) in a fresh child process; prints
          frames/s (wall and per CPU second: other load on the machine shows as the gap) and the
          child's peak RSS (VmHWM, imports included). Targets: >= 2M frames/s on 2 cores, < 1 GB.
pipeline  the training iterator in `actions_only` mode (normalized, padded action chunks and
          state, no images): `--batch_size` x `--horizon` chunks per step as global jax.Arrays on
          one CPU device; samples/s over `--steps` steps after `--warmup`. Target >= 20k/s.
memory    (`--part=memory`, not in `all`) peak memory of the pipeline at B1K scale: for each of
          `--memory_frames` (default 10 M and 100 M), a synthetic source with B1K's metadata
          (episodes of 3k..21k frames, mean ~12k, 50 task prompts, 23-D float32 actions and
          state) is written into its on-disk frame store by the real builder (disk: 184
          bytes per frame, deleted afterwards), then a fresh process runs the training iterator
          (`--memory_workers` Grain workers, `--batch_size` x `--horizon` chunks, `--steps`
          steps). Prints each process's peak RSS (VmHWM) and its private (RssAnon) and
          file-backed, shared (RssFile) parts, and the builder's peak. Target: < 2 GiB per
          process, growing < 10 % from 10 M to 100 M frames.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.bench import common
from pi0_armfix.cache import cache_root
from pi0_armfix.data.formats.lerobot_writer import LeRobotWriter
from pi0_armfix.data.pipeline.data_spec import DataSpec

_LAYOUT = "b1k_r1pro"


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench data")
    parser.add_argument("--part", choices=("all", "stats", "pipeline", "memory"), default="all")
    parser.add_argument("--frames", type=int, default=5_000_000)
    parser.add_argument("--episode_frames", type=int, default=500)
    parser.add_argument("--episodes_per_file", type=int, default=1000)
    parser.add_argument("--cache_dir", default="")
    parser.add_argument("--batch_size", type=int, default=256)
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--num_workers", type=int, default=0)
    parser.add_argument("--memory_frames", default="10000000,100000000")
    parser.add_argument("--memory_workers", type=int, default=2)
    parser.add_argument("--stats_child", default="", help=argparse.SUPPRESS)
    parser.add_argument("--memory_child", default="", help=argparse.SUPPRESS)
    return parser.parse_args(argv[1:])


# ---------------------------------------------------------------------- dataset

def _episode(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """B1K-like [n, 23] float32 actions and state."""
    t = np.arange(n)[:, None]
    actions = np.zeros((n, 23), np.float32)
    actions[:, 0:3] = 0.3 * np.sin(t / rng.uniform(20, 60) + rng.uniform(0, 6, 3))
    actions[:, 3:6] = rng.normal(size=3) * 0.4
    for arm in (slice(7, 14), slice(15, 22)):
        actions[:, arm] = rng.normal(size=7) * 0.5 + np.cumsum(
            rng.normal(size=(n, 7)) * 0.01, axis=0)
    for gripper in (14, 22):
        actions[:, gripper] = np.where((t[:, 0] // rng.integers(50, 300)) % 2, 1.0, -1.0)
    state = actions + rng.normal(size=actions.shape).astype(np.float32) * 0.01
    return actions, state


def bench_root(frames: int, episode_frames: int, episodes_per_file: int,
               cache_dir: str = "") -> Path:
    """The benchmark dataset, generated on first use (atomically: written aside, then renamed)."""
    cache = cache_root(cache_dir or None)
    root = cache / f"bench-lerobot-v3-{frames}-{episode_frames}-{episodes_per_file}"
    if (root / "meta" / "info.json").is_file():
        return root
    cache.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{root.name}.partial-", dir=cache))
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    written = 0
    with LeRobotWriter(staging / "dataset", version="v3.0", fps=30,
                       episodes_per_file=episodes_per_file, row_group_size=65536) as writer:
        while written < frames:
            n = min(int(rng.integers(episode_frames // 2, 3 * episode_frames // 2)),
                    frames - written)
            actions, state = _episode(rng, max(n, 2))
            writer.add_episode(actions, state, task="tidy up the kitchen")
            written += len(actions)
    os.rename(staging / "dataset", root)
    staging.rmdir()
    print(f"generated {written:,} frames into {root} in {time.perf_counter() - start:.0f} s")
    return root


# ---------------------------------------------------------------------- stats

def _peak_rss_mib() -> float:
    """This process's RSS high-water mark. /proc's VmHWM, unlike `ru_maxrss`, is not inherited
    across exec from the (large) parent."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _stats_child(root: str) -> None:
    """Runs in the child: one stats pass; prints timing and memory as JSON."""
    from pi0_armfix.data.statistics import stats as stats_lib
    from pi0_armfix.data.formats.lerobot import LeRobotSource

    source = LeRobotSource(root, ActionLayout.preset(_LAYOUT))
    frames = int(source.episode_lengths.sum())
    rss_before = _peak_rss_mib()
    cpu, start = _cpu_seconds(), time.perf_counter()
    stats_lib.compute_norm_stats(source.iter_blocks(("actions", "state")), total_frames=frames,
                                 progress=False)
    print(json.dumps({"frames": frames, "seconds": time.perf_counter() - start,
                      "cpu_seconds": _cpu_seconds() - cpu, "peak_rss_mib": _peak_rss_mib(),
                      "rss_before_mib": rss_before}))


def bench_stats(root: Path) -> dict[str, float]:
    """Runs `_stats_child` in a fresh process (its memory is the stats' alone)."""
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.bench", "data",
                             f"--stats_child={root}"], capture_output=True, text=True,
                            check=True)
    child = json.loads(result.stdout.strip().splitlines()[-1])
    return {**child, "frames_per_s": child["frames"] / child["seconds"],
            "frames_per_cpu_s": child["frames"] / child["cpu_seconds"]}


# ---------------------------------------------------------------------- pipeline

def bench_pipeline(root: Path, batch_size: int, horizon: int, steps: int, warmup: int,
                   num_workers: int) -> dict[str, float]:
    from pi0_armfix.data.pipeline import dataset as dataset_lib
    from pi0_armfix.data.pipeline import pipeline
    from pi0_armfix.data.statistics import stats as stats_lib

    spec = DataSpec.from_config(common.data_config(str(root), num_workers),
                                ActionLayout.preset(_LAYOUT))
    stats_path = root / "bench_norm_stats.json"
    if not stats_path.is_file():
        stats_lib.save_norm_stats(stats_path, dataset_lib.dataset_norm_stats(
            spec, action_horizon=horizon))
    stats = stats_lib.load_norm_stats(stats_path)
    sharding = common.batch_sharding()
    start = time.perf_counter()
    iterator = pipeline.make_train_iterator(spec, norm_stats=stats, action_horizon=horizon,
                                            global_batch_size=batch_size, sharding=sharding,
                                            actions_only=True)
    setup = time.perf_counter() - start
    try:
        seconds = common.timed_steps(iterator, steps, warmup)
    finally:
        iterator.close()
    return {"samples_per_s": steps * batch_size / seconds, "steps": steps,
            "batch_size": batch_size, "setup_s": setup}


# ---------------------------------------------------------------------- memory at B1K scale

B1K_TASKS = tuple(f"behavior task {t}: tidy the room and put the items away" for t in range(50))


class SyntheticSource:
    """A Source with B1K 2025's metadata and `frames` frames of synthetic 23-D actions and state
    (a fixed random block repeated: the store's bytes, not their values, are what is measured)."""

    block_keys = ("actions", "state")
    fps = 30.0
    cameras: dict = {}

    def __init__(self, frames: int, seed: int = 0):
        rng = np.random.default_rng(seed)
        lengths = []
        while sum(lengths) < frames:
            lengths.append(int(rng.integers(3_000, 21_000)))
        lengths[-1] -= sum(lengths) - frames
        self.episode_lengths = np.array(lengths, np.int64)
        tasks = np.sort(rng.integers(0, 50, len(lengths)))  # ids task * 10000 + 10 n, sorted
        first = np.searchsorted(tasks, tasks)
        self.episode_index = (tasks * 10_000 + (np.arange(len(lengths)) - first) * 10
                              ).astype(np.int64)
        self.tasks = tuple(B1K_TASKS[t] for t in tasks)
        self.num_episodes = len(lengths)
        self.root = f"synthetic-b1k-{frames}"
        self._block = rng.normal(size=(65_536, 23)).astype(np.float32)

    def identity(self) -> dict:
        return {"root": self.root, "synthetic": 1}

    def episode_file(self, episode: int) -> str:
        return f"synthetic episode {episode}"

    def iter_blocks(self, keys=("actions", "state"), episodes=None):
        assert episodes is None  # the store reads every episode
        starts = np.concatenate([[0], np.cumsum(self.episode_lengths)])
        for start in range(0, int(starts[-1]), len(self._block)):
            n = min(len(self._block), int(starts[-1]) - start)
            episode = np.searchsorted(starts, np.arange(start, start + n), side="right") - 1
            block = {key: self._block[:n] for key in keys}
            block["episode_index"] = self.episode_index[episode]
            yield block

    @property
    def frame_store(self):
        from pi0_armfix.data.formats.frame_store import FrameStore

        return FrameStore.open(self, progress=False)

    def load_table(self, episodes=None, *, images=True, image_size=None):
        from pi0_armfix.data.episodes import EpisodeTable

        positions = np.searchsorted(self.episode_index, episodes) if episodes is not None \
            else np.arange(self.num_episodes)
        lengths = self.episode_lengths[positions]
        store = self.frame_store
        return EpisodeTable(
            actions=store.column("actions", positions), state=store.column("state", positions),
            episode_starts=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
            episode_index=self.episode_index[positions],
            tasks=[self.tasks[p] for p in positions], fps=self.fps)


def _memory_child(arg: str) -> None:
    """In a fresh process: `build:FRAMES` builds the store; `train:FRAMES:WORKERS:B:H:STEPS`
    runs the iterator. Prints the memory as JSON."""
    parts = arg.split(":")
    source = SyntheticSource(int(parts[1]))
    if parts[0] == "build":
        start = time.perf_counter()
        store = source.frame_store
        print(json.dumps({"seconds": time.perf_counter() - start, "root": str(store.root),
                          "main": common.memory()}))
        return
    import jax

    from pi0_armfix.data.pipeline import pipeline
    from pi0_armfix.data.statistics import stats as stats_lib

    workers, batch_size, horizon, steps = (int(p) for p in parts[2:])
    spec = DataSpec.from_config(common.data_config(source.root, workers),
                                ActionLayout.preset(_LAYOUT))
    unit = stats_lib.NormStats(mean=np.zeros(23), std=np.ones(23), q01=-np.ones(23),
                               q99=np.ones(23))
    sharding = common.batch_sharding()
    before = common.memory()
    iterator = pipeline.make_train_iterator(
        spec, norm_stats={"actions": unit, "state": unit},
        action_horizon=horizon, global_batch_size=batch_size, sharding=sharding,
        actions_only=True, source=source)
    try:
        for _ in range(steps):
            jax.block_until_ready(next(iterator))
        workers_memory = []
        for pid in common.descendants(os.getpid()):
            command = Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ")
            role = ("resource tracker" if common.is_resource_tracker(command) else
                    "Grain worker" if "python" in command else command[:40])
            workers_memory.append({**common.memory(pid), "role": role})
        print(json.dumps({"main": common.memory(), "main_before": before,
                          "workers": workers_memory}))
    finally:
        iterator.close()


def bench_memory(frames: int, workers: int, batch_size: int, horizon: int, steps: int
                 ) -> dict:
    run = lambda arg: json.loads(subprocess.run(  # noqa: E731
        [sys.executable, "-m", "pi0_armfix.bench", "data", f"--memory_child={arg}"],
        capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1])
    build = run(f"build:{frames}")
    try:
        train = run(f"train:{frames}:{workers}:{batch_size}:{horizon}:{steps}")
    finally:
        shutil.rmtree(build["root"], ignore_errors=True)
    return {"build": build, "train": train}


def _print_memory(frames: int, result: dict) -> None:
    build, train = result["build"], result["train"]
    line = lambda m: (f"peak {m['VmHWM']:.0f} MiB (now {m['RssAnon']:.0f} private + "  # noqa: E731
                      f"{m['RssFile']:.0f} file-backed)")
    print(f"memory @ {frames / 1e6:.0f} M frames: store built in {build['seconds']:.0f} s, "
          f"builder {line(build['main'])}")
    print(f"  training process: {line(train['main'])}; before the iterator "
          f"{train['main_before']['VmHWM']:.0f} MiB (imports)")
    for worker in train["workers"]:
        print(f"  {worker['role']}: {line(worker)}")


def main(argv: list[str]) -> None:
    args = _parse(argv)
    if args.stats_child:
        _stats_child(args.stats_child)
        return
    if args.memory_child:
        _memory_child(args.memory_child)
        return
    if args.part == "memory":
        results = {}
        for frames in (int(f) for f in args.memory_frames.split(",")):
            results[frames] = bench_memory(frames, args.memory_workers, args.batch_size,
                                           args.horizon, args.steps)
            _print_memory(frames, results[frames])
        if len(results) > 1:
            low, high = results[min(results)]["train"], results[max(results)]["train"]
            peaks = lambda r: [r["main"]["VmHWM"]] + [  # noqa: E731
                w["VmHWM"] for w in r["workers"] if w["role"] == "Grain worker"]
            growth = max(b / a - 1 for a, b in zip(peaks(low), peaks(high)))
            print(f"growth of the peak RSS from {min(results) / 1e6:.0f} M to "
                  f"{max(results) / 1e6:.0f} M frames: {100 * growth:+.1f} % at most over the "
                  f"processes (target < 10 %); largest peak {max(peaks(high)):.0f} MiB "
                  "(target < 2048)")
        return
    root = bench_root(args.frames, args.episode_frames, args.episodes_per_file, args.cache_dir)
    print(f"dataset: {root} (LeRobot v3.0, {args.frames:,} frames, {os.cpu_count()} cores)")
    if args.part in ("all", "stats"):
        stats = bench_stats(root)
        print(f"stats:    {stats['frames']:,} frames (actions + state, 23-D) in "
              f"{stats['seconds']:.2f} s = {stats['frames_per_s'] / 1e6:.2f} M frames/s "
              f"(target >= 2; {stats['cpu_seconds']:.2f} CPU s, "
              f"{stats['frames_per_cpu_s'] / 1e6:.2f} M frames per CPU s); peak RSS "
              f"{stats['peak_rss_mib']:.0f} MiB (target < 1 GB; {stats['rss_before_mib']:.0f} "
              f"MiB before the pass); load average {os.getloadavg()[0]:.1f}")
    if args.part in ("all", "pipeline"):
        result = bench_pipeline(root, args.batch_size, args.horizon, args.steps, args.warmup,
                                args.num_workers)
        print(f"pipeline: {result['samples_per_s']:,.0f} samples/s (target >= 20,000): "
              f"batches of {result['batch_size']} normalized, padded chunks of "
              f"{args.horizon} x 32 + state as jax.Arrays, no images, "
              f"{args.num_workers} workers; setup (table load) {result['setup_s']:.1f} s")
