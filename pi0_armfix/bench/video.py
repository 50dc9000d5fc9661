"""Video benchmark: can the pipeline feed a GPU from B1K-like camera videos?

    python -m pi0_armfix.bench video [--episodes=6] [--episode_frames=240] [--batch_size=16]
                                     [--steps=8] [--num_workers=2] [--gop=8] [--size=224]
                                     [--stream_workers=0,1,2] [--stream_episodes=16]
                                     [--stream_shuffle=256] [--stream_stride=4]
                                     [--diversity_samples=10000,100000]
                                     [--original_gop=0]
                                     [--parts=random,stream,diversity,reencode,cache]

dataset    a LeRobot v2.1 root like BEHAVIOR-1K 2025's cameras: head 720², wrists 480², HEVC
           (libx265) with ONE keyframe per episode (`--original_gop=8`: a keyframe every 8
           frames, as B1K 2026 writes them), `--episodes` x `--episode_frames` frames of textured
           moving scenes, generated once into `<cache>/bench-b1k-video-<hash>`; the line says
           what `data.video_access='auto'` chooses for it, and why.
original   random frames read as training reads them (3 cameras, resized in the decoder to
           `--size`²): ms per sample and frames decoded per sample. The cost grows with the
           position in the episode (decode from the episode's only keyframe); the line also
           extrapolates to B1K's mean episode (119 M frames / 10 000 episodes = 11 900 frames).
stream     the training iterator on the ORIGINAL with `data.video_access='stream'` (episodes
           decoded front to back, `--stream_episodes` open, every `--stream_stride`-th frame a
           sample, window shuffle of `--stream_shuffle`), for each of
           `--stream_workers` Grain workers: samples/s (3 cameras at `--size`², chunks, prompts,
           batches as the train step gets them) over whole shuffle windows, the RSS of the main
           process and the peak of each worker, and the resume latency (a new iterator restored
           from the state after the timed steps, to its first batch: each open episode decoded
           from its keyframe).
diversity  which episodes the samples come from, at B1K's scale (10 000 episodes of 11 900 frames;
           episode order and shuffle only, no decoding): over 10 000 consecutive samples the
           number of distinct episodes, and the chance that two samples k apart share their
           episode, for the stream against random access (openpi's loader draws every sample
           uniformly from all frames); and the episodes read in 100 000 samples (the stride's
           lever: k times as many) (`--diversity_samples`).
reencode   `python -m pi0_armfix.tools.reencode_videos --size --gop` on it: frames/s on this
           machine, and the hours B1K's 3 x 119 M camera frames would take per core.
           Random reads of the copy with fresh decoders: the cost per sample at B1K's scale, where
           a shuffled stream almost never meets an open file twice.
training   the training iterator (images, prompts, chunks) on the re-encoded copy with
           `--num_workers` Grain workers: samples/s. Target >= 20 samples/s on 2 cores
           (one H100 at openpi's speed consumes ~19).
cache      `data.frame_cache` on the original (a short GOP: `--original_gop=2` is a G1's AV1
           keyframe spacing): the one-time decode of every frame at `--size`² (frames/s, MiB on
           disk, into a scratch cache folder), then a random sample's 3 cameras read from it
           against decoding them on request (warm decoders, as a training process keeps them),
           and the training iterator with `--num_workers` workers on each.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.bench import common
from pi0_armfix.cache import build_lock, cache_root, digest
from pi0_armfix.data.formats.lerobot_writer import LeRobotWriter

_LAYOUT = "b1k_r1pro"
_CAMERAS = ("observation.images.rgb.head", "observation.images.rgb.left_wrist",
            "observation.images.rgb.right_wrist")
B1K_MEAN_EPISODE_FRAMES = 11_900
PARTS = ("random", "stream", "diversity", "reencode", "cache")


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m pi0_armfix.bench video")
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--episode_frames", type=int, default=240)
    parser.add_argument("--head", type=int, default=720)
    parser.add_argument("--wrist", type=int, default=480)
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--gop", type=int, default=8)
    parser.add_argument("--samples", type=int, default=12, help="random reads of the original")
    parser.add_argument("--batch_size", type=int, default=16)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--num_workers", type=int, default=2)
    parser.add_argument("--stream_workers", default="0,1,2",
                        help="Grain worker counts of the streamed training iterator")
    parser.add_argument("--stream_episodes", type=int, default=16)
    parser.add_argument("--stream_shuffle", type=int, default=256)
    parser.add_argument("--stream_stride", type=int, default=4)
    parser.add_argument("--diversity_samples", default="10000,100000",
                        help="consecutive samples of the diversity figures, short and long")
    parser.add_argument("--content", choices=("pan", "subpixel"), default="pan",
                        help="the scene pans by whole pixels, or by fractions of one per frame")
    parser.add_argument("--original_gop", type=int, default=0,
                        help="frames between the original's keyframes (0: one per episode)")
    parser.add_argument("--parts", default=",".join(PARTS),
                        help=f"what to measure, of {','.join(PARTS)}")
    args = parser.parse_args(argv[1:])
    args.parts = [p for p in args.parts.split(",") if p]
    unknown = sorted(set(args.parts) - set(PARTS))
    if unknown or args.original_gop < 0:
        parser.error(f"--parts {unknown} is not of {PARTS}" if unknown
                     else f"--original_gop = {args.original_gop} must be >= 0")
    counts = args.diversity_samples.split(",")
    if (len(counts) != 2 or not all(c.isdigit() for c in counts)
            or not 0 < int(counts[0]) <= int(counts[1])):
        parser.error(f"--diversity_samples = {args.diversity_samples!r} must be two counts "
                     "SHORT,LONG with 0 < SHORT <= LONG (e.g. 10000,100000)")
    args.diversity_samples = tuple(int(c) for c in counts)
    return args


# ---------------------------------------------------------------------- dataset

def _camera_frames(rng: np.random.Generator, n: int, side: int, subpixel: bool = False
                   ) -> np.ndarray:
    """uint8 [n, side, side, 3]: a textured scene panning under a moving object (what a codec
    has to work for, unlike flat colours). `subpixel`: the scene pans by fractions of a pixel per
    frame (interpolated), as a real camera's view drifts, which costs the decoder far more than
    whole-pixel shifts."""
    texture = rng.integers(0, 256, (side // 8, side // 8, 3), np.uint8)
    texture = np.repeat(np.repeat(texture, 8, 0), 8, 1).astype(np.float32)
    frames = np.empty((n, side, side, 3), np.uint8)
    for t in range(n):
        if subpixel:
            dy, dx = t * 0.37, t * 0.23
            iy, ix, fy, fx = int(dy), int(dx), dy - int(dy), dx - int(dx)
            shifted = np.roll(texture, (iy, ix), axis=(0, 1))
            below, right = np.roll(shifted, 1, axis=0), np.roll(shifted, 1, axis=1)
            diagonal = np.roll(below, 1, axis=1)
            frame = ((1 - fy) * (1 - fx) * shifted + fy * (1 - fx) * below
                     + (1 - fy) * fx * right + fy * fx * diagonal).astype(np.uint8)
        else:
            frame = np.roll(texture, (t * side // 240, t * side // 360), axis=(0, 1)).astype(
                np.uint8)
        y, x = (side // 4 + t * 3) % (side - side // 5), (side // 3 + t * 2) % (side - side // 5)
        frame[y:y + side // 5, x:x + side // 5] = (255, 120, 0)
        frames[t] = frame
    return frames


def bench_root(episodes: int, frames: int, head: int, wrist: int, content: str = "pan",
               gop: int = 0) -> Path:
    """The B1K-like video dataset, generated on first use (atomically, under a lock);
    `content`: 'pan' (whole-pixel shifts) or 'subpixel' (fractional-pixel pans); `gop`: frames
    between keyframes (0: one keyframe per episode)."""
    spec = {"episodes": episodes, "frames": frames, "head": head, "wrist": wrist, "v": 1,
            **({"content": content} if content != "pan" else {}),
            **({"gop": gop} if gop else {})}
    root = cache_root() / f"bench-b1k-video-{digest(spec)}"
    with build_lock(root):
        if (root / "meta" / "info.json").is_file():
            return root
        staging = Path(tempfile.mkdtemp(prefix=f".{root.name}.partial-", dir=root.parent))
        rng = np.random.default_rng(0)
        start = time.perf_counter()
        sides = dict(zip(_CAMERAS, (head, wrist, wrist)))
        with LeRobotWriter(staging / "dataset", version="v2.1", fps=30, image_format="video",
                           cameras={c: (s, s) for c, s in sides.items()}, video_codec="libx265",
                           video_gop=gop or frames + 1, video_crf=28,
                           video_options={"preset": "ultrafast",
                                          "x265-params": "log-level=none"}) as writer:
            for _ in range(episodes):
                t = np.arange(frames)[:, None] / 30.0
                actions = np.sin(t + rng.uniform(0, 6, 23)).astype(np.float32)
                writer.add_episode(actions, actions + 0.01, "tidy up the kitchen",
                                   {c: _camera_frames(rng, frames, s, content == "subpixel")
                                    for c, s in sides.items()})
        os.rename(staging / "dataset", root)
        staging.rmdir()
        print(f"generated {episodes} x {frames} frames x 3 HEVC cameras into {root} in "
              f"{time.perf_counter() - start:.0f} s")
    return root


# ---------------------------------------------------------------------- measurements

def random_reads(root: Path, size: int, samples: int) -> dict[str, float]:
    """Random frames of the original through the training reader (fresh decoders per sample,
    as a shuffled stream across thousands of episodes meets them)."""
    from pi0_armfix.data.formats.lerobot import LeRobotSource

    source = LeRobotSource(root, ActionLayout.preset(_LAYOUT))
    rng = np.random.default_rng(0)
    frames = rng.integers(0, int(source.episode_lengths.sum()), samples)
    seconds, positions = [], []
    for frame in frames:
        table = source.load_table(images=True, image_size=(size, size))  # empty decoder caches
        start = time.perf_counter()
        table.images(int(frame))
        seconds.append(time.perf_counter() - start)
        episode = int(table.episode_of_frame(np.array([frame]))[0])
        positions.append(int(frame - table.episode_starts[episode]))
    seconds, positions = np.array(seconds), np.array(positions)
    # Decoding from the keyframe: cost ~ a + b * position; fit it to extrapolate to B1K.
    slope, intercept = np.polyfit(positions, seconds, 1)
    return {"ms_per_sample": 1000 * seconds.mean(), "mean_position": positions.mean(),
            "ms_per_position": 1000 * slope, "ms_fixed": 1000 * intercept,
            "b1k_ms_per_sample": 1000 * (intercept + slope * B1K_MEAN_EPISODE_FRAMES / 2)}


def _tokenize(prompt: str) -> tuple[np.ndarray, np.ndarray]:
    """A stand-in tokenizer (picklable for the workers): 48 tokens."""
    tokens = np.zeros(48, np.int32)
    tokens[:len(prompt)] = [ord(c) % 256 for c in prompt[:48]]
    return tokens, tokens > 0


def training_throughput(root: Path, size: int, batch_size: int, steps: int,
                        num_workers: int, video_access: str = "random",
                        stream: tuple[int, int, int] = (16, 256, 4),
                        frame_cache: bool = False) -> dict[str, Any]:
    """The training iterator's samples/s; for a stream also the memory of its processes and the
    latency of a resume from the state after the timed steps. `stream`: (open episodes, shuffle
    window, stride)."""
    from pi0_armfix.data.pipeline import dataset as dataset_lib
    from pi0_armfix.data.pipeline import pipeline
    from pi0_armfix.data.formats import sources
    from pi0_armfix.data.pipeline.data_spec import DataSpec

    config = common.data_config(str(root), num_workers)
    (config.data.stream_episodes, config.data.stream_shuffle,
     config.data.stream_stride) = stream
    config.data.frame_cache = frame_cache
    spec = DataSpec.from_config(config, ActionLayout.preset(_LAYOUT))
    source = sources.open_source(spec.options, spec.layout)
    stats = dataset_lib.dataset_norm_stats(spec, action_horizon=50, source=source,
                                           progress=False)

    def make():
        return pipeline.make_train_iterator(
            spec, norm_stats=stats, action_horizon=50, global_batch_size=batch_size,
            sharding=common.batch_sharding(), tokenize=_tokenize, source=source,
            image_size=(size, size), video_access=video_access)

    # A stream yields a window of samples after filling it, then the next: time whole windows,
    # after the first (filled before the first batch).
    window_steps = -(-stream[1] // batch_size) if video_access == "stream" else 0
    steps = max(steps, 4 * window_steps)
    iterator = make()
    try:
        batch = next(iterator)  # workers start, decoders open
        shapes = {c: tuple(batch["image"][c].shape[1:]) for c in batch["image"]}
        seconds = common.timed_steps(iterator, steps, warmup=max(window_steps - 1, 0))
        workers = [pid for pid in common.descendants(os.getpid())
                   if not common.is_resource_tracker(Path(f"/proc/{pid}/cmdline").read_text())]
        memory = {"main": common.memory()["VmRSS"],
                  "workers": [common.memory(pid)["VmHWM"] for pid in workers]}
        state = iterator.get_state()
    finally:
        iterator.close()
    result = {"samples_per_s": steps * batch_size / seconds, "shapes": shapes, "memory": memory,
              "samples": steps * batch_size}
    if video_access == "stream":
        resumed = make()
        try:
            resumed.set_state(state)
            start = time.perf_counter()
            next(resumed)
            result["resume_s"] = time.perf_counter() - start
        finally:
            resumed.close()
    return result


def frame_cache(root: Path, size: int, samples: int, scratch: Path) -> dict[str, float]:
    """The one-time decode of `root`'s frames into a frame cache under `scratch`, and random
    reads of a sample's cameras from it against decoding on request (one table each, its
    decoders kept warm as a training process keeps them)."""
    from pi0_armfix.data.formats.lerobot import LeRobotSource

    layout = ActionLayout.preset(_LAYOUT)
    previous = os.environ.get("PI0_ARMFIX_CACHE")
    os.environ["PI0_ARMFIX_CACHE"] = str(scratch)
    try:
        cached = LeRobotSource(root, layout, frame_cache=True)
        cached.frame_store  # noqa: B018 - the frame columns first, so that only decoding is timed
        start = time.perf_counter()
        cached_table = cached.load_table(images=True, image_size=(size, size))
        build_s = time.perf_counter() - start
    finally:
        if previous is None:
            os.environ.pop("PI0_ARMFIX_CACHE")
        else:
            os.environ["PI0_ARMFIX_CACHE"] = previous
    decoded_table = LeRobotSource(root, layout).load_table(images=True, image_size=(size, size))
    frames = np.random.default_rng(0).integers(0, cached_table.num_frames, samples)

    def ms_per_sample(table) -> float:
        start = time.perf_counter()
        for frame in frames:
            table.images(int(frame))
        return 1000 * (time.perf_counter() - start) / samples

    disk = sum(f.stat().st_size for f in (scratch / "images").rglob("*.npy"))
    return {"frames": cached_table.num_frames, "build_s": build_s,
            "frames_per_s": cached_table.num_frames / build_s, "mib": disk / 2**20,
            "cached_ms": ms_per_sample(cached_table), "decoded_ms": ms_per_sample(decoded_table)}


class _EpisodeLengths:
    """Stands in for a table's images in `video_stream.stream_frames`: episodes of given lengths
    whose frames are their row numbers (the order of samples without decoding a frame)."""

    def __init__(self, lengths: np.ndarray):
        self.starts = np.concatenate([[0], np.cumsum(lengths)])

    def episode_reader(self, position: int) -> "_EpisodeLengths._Reader":
        return self._Reader(int(self.starts[position]),
                            int(self.starts[position + 1] - self.starts[position]))

    class _Reader:
        def __init__(self, start: int, length: int):
            self.start, self.length = start, length

        def images(self, offset: int) -> dict:
            return {}

        def close(self) -> None:
            pass


def sample_diversity(episodes: int, mean_frames: int, open_episodes: int, window: int,
                     stride: int, samples: int = 10_000, long_samples: int = 0,
                     lags: tuple[int, ...] = (1, 16, 256, 1024)) -> dict[str, dict[str, float]]:
    """Distinct episodes among `samples` consecutive samples (`distinct`; among `long_samples`
    too where > 0: `distinct_long`) and the chance that two samples `lag` apart share their
    episode, streamed and drawn at random."""
    from pi0_armfix.data.pipeline import video_stream

    rng = np.random.default_rng(0)
    lengths = rng.integers(mean_frames // 2, 3 * mean_frames // 2 + 1, episodes)
    table = _EpisodeLengths(lengths)
    stream = iter(video_stream.stream_frames(
        table, video_stream.episode_order(range(episodes), seed=0), seed=0,
        open_episodes=open_episodes, shuffle_window=window, stride=stride))
    total = max(samples, long_samples)
    streamed = np.array([int(next(stream)["frame"]) for _ in range(total)])
    stream.close()
    drawn = rng.integers(0, int(table.starts[-1]), total)
    result = {}
    for name, frames in (("stream", streamed), ("random access", drawn)):
        episode = np.searchsorted(table.starts, frames, side="right") - 1
        first = episode[:samples]
        result[name] = {"distinct": float(len(np.unique(first))),
                        **{f"same@{k}": float(np.mean(first[k:] == first[:-k])) for k in lags}}
        if long_samples:
            result[name]["distinct_long"] = float(len(np.unique(episode)))
    return result


def main(argv: list[str]) -> None:
    from pi0_armfix.data.pipeline import video_stream
    from pi0_armfix.data.formats.lerobot import LeRobotSource
    from pi0_armfix.tools.reencode_videos import reencode_dataset

    args = _parse(argv)
    root = bench_root(args.episodes, args.episode_frames, args.head, args.wrist, args.content,
                      args.original_gop)
    cores = os.cpu_count()
    keyframes = (f"a keyframe every {args.original_gop} frames" if args.original_gop
                 else "one keyframe per episode")
    _, why = video_stream.choose_access(
        "auto", LeRobotSource(root, ActionLayout.preset(_LAYOUT)).video_keyframes(),
        open_episodes=args.stream_episodes, shuffle_window=args.stream_shuffle,
        stride=args.stream_stride)
    print(f"dataset: {root} ({args.episodes} episodes x {args.episode_frames} frames; HEVC "
          f"{args.head}² head, {args.wrist}² wrists, {keyframes}, {args.content} content; "
          f"{cores} cores); {why}")

    reads = random_reads(root, args.size, args.samples) if "random" in args.parts else None
    if reads and args.original_gop:
        # A short GOP bounds what a read decodes: its cost does not grow along the episode.
        print(f"original, random reads: {reads['ms_per_sample']:.0f} ms per sample (3 cameras "
              f"-> {args.size}², fresh decoders, at most {args.original_gop} frames decoded "
              f"each, wherever in the episode) = "
              f"{1000 * cores / reads['ms_per_sample']:.1f} samples/s on {cores} cores")
    elif reads:
        print(f"original, random reads: {reads['ms_per_sample']:.0f} ms per sample (3 cameras "
              f"-> {args.size}², mean position {reads['mean_position']:.0f} frames into its "
              f"episode; {reads['ms_fixed']:.0f} ms + {reads['ms_per_position']:.2f} ms per "
              f"frame from the episode's start) -> at B1K's mean episode "
              f"({B1K_MEAN_EPISODE_FRAMES} frames) ~{reads['b1k_ms_per_sample'] / 1000:.1f} s "
              f"per sample = {1000 * cores / reads['b1k_ms_per_sample']:.2f} samples/s on "
              f"{cores} cores")

    stream = (args.stream_episodes, args.stream_shuffle, args.stream_stride)
    stream_workers = sorted({int(w) for w in args.stream_workers.split(",") if w})
    for workers in stream_workers if "stream" in args.parts else []:
        result = training_throughput(root, args.size, args.batch_size, args.steps, workers,
                                     "stream", stream)
        memory = result["memory"]
        total = memory["main"] + sum(memory["workers"])
        print(f"stream from the original, {workers} workers: {result['samples_per_s']:.1f} "
              f"samples/s over {result['samples']} samples (3 cameras "
              f"{sorted(set(result['shapes'].values()))}, 50-step chunks, prompt tokens; "
              f"{args.stream_episodes} episodes open per stream, "
              + (f"a sample every {args.stream_stride} frames, " if args.stream_stride > 1 else "")
              + f"window {args.stream_shuffle}); "
              f"RSS {total:.0f} MiB (main process now {memory['main']:.0f}"
              + "".join(f", worker peak {m:.0f}" for m in memory["workers"]) + " MiB); resume to "
              f"the first batch {result['resume_s']:.1f} s (reopening the open episodes, "
              "decoding each to its offset, refilling the window)")

    # A short-GOP original (B1K 2026's) is read on request by 'auto': that path's throughput too.
    for workers in stream_workers if "random" in args.parts and args.original_gop else []:
        result = training_throughput(root, args.size, args.batch_size, args.steps, workers)
        print(f"random access on the original, {workers} workers: "
              f"{result['samples_per_s']:.1f} samples/s (3 cameras "
              f"{sorted(set(result['shapes'].values()))}, 50-step chunks, prompt tokens)")

    short, long = args.diversity_samples
    diversity = (sample_diversity(10_000, B1K_MEAN_EPISODE_FRAMES, *stream, samples=short,
                                  long_samples=long) if "diversity" in args.parts else {})
    for name, d in diversity.items():
        print(f"diversity, {name} (B1K's 10 000 episodes of ~{B1K_MEAN_EPISODE_FRAMES} frames; "
              f"{short:,} consecutive samples): {d['distinct']:.0f} distinct episodes; same "
              "episode at lag " + ", ".join(f"{k.split('@')[1]}: {v:.3f}" for k, v in d.items()
                                            if k.startswith("same@"))
              + f"; {d['distinct_long']:.0f} distinct in {long:,} samples")

    if "cache" in args.parts:
        with tempfile.TemporaryDirectory(dir=root.parent) as scratch:
            cache = frame_cache(root, args.size, max(args.samples, 100), Path(scratch))
        print(f"frame cache: {cache['frames']:,} frames x 3 cameras decoded once at {args.size}² "
              f"in {cache['build_s']:.1f} s = {cache['frames_per_s']:.0f} frames/s on {cores} "
              f"cores, {cache['mib']:.0f} MiB; a random sample read from it "
              f"{cache['cached_ms']:.3f} ms against {cache['decoded_ms']:.1f} ms decoded on "
              "request (warm decoders)")
        for cached in (False, True):
            result = training_throughput(root, args.size, args.batch_size, args.steps,
                                         args.num_workers, frame_cache=cached)
            print(f"training iterator on the original, {args.num_workers} workers, "
                  + ("from the frame cache" if cached else "decoded on request")
                  + f": {result['samples_per_s']:.1f} samples/s")
    if "reencode" not in args.parts:
        return
    with tempfile.TemporaryDirectory(dir=root.parent) as scratch:
        output = Path(scratch) / "reencoded"
        done = reencode_dataset(root, output, size=args.size, gop=args.gop, workers=cores,
                                progress=False)
        per_core = done["frames_per_s"] / cores
        b1k_hours = 3 * 119e6 / per_core / 3600
        print(f"re-encode to {args.size}², gop {args.gop}: {done['frames']:,} frames in "
              f"{done['seconds']:.1f} s = {done['frames_per_s']:.0f} frames/s on {cores} cores "
              f"({per_core:.0f} per core; B1K's 3 x 119 M camera frames: ~{b1k_hours:,.0f} "
              f"core-hours, {b1k_hours / 64:.0f} h on 64 cores)")
        cold = random_reads(output, args.size, args.samples)
        print(f"re-encoded, random reads with fresh decoders (every sample opens its 3 files, as "
              f"in a shuffled stream over 10 000 episodes): {cold['ms_per_sample']:.1f} ms per "
              f"sample = {1000 * cores / cold['ms_per_sample']:.0f} samples/s on {cores} cores "
              f"(independent of the position: {cold['ms_per_position']:.3f} ms per frame)")
        for workers in sorted({0, args.num_workers}):
            result = training_throughput(output, args.size, args.batch_size, args.steps,
                                         workers)
            print(f"training iterator on the re-encoded copy, {workers} workers: "
                  f"{result['samples_per_s']:.1f} samples/s (target >= 20; batches of "
                  f"{args.batch_size}: 3 cameras {sorted(set(result['shapes'].values()))}, "
                  "50-step chunks, prompt tokens)")
