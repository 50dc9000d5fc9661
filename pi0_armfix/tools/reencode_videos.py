"""Re-encodes a LeRobot dataset's camera videos at the model's resolution with short GOPs.

    python -m pi0_armfix.tools.reencode_videos --input=B1K_ROOT --output=B1K_224 \
        [--size=224] [--gop=8] [--codec=libx264] [--crf=18] [--features=matched] [--workers=N]

Why: BEHAVIOR-1K 2025 stores each camera as HEVC (720² head, 480² wrists) with one keyframe per
episode, so reading one random training sample decodes, per camera, everything from the
episode's start up to the sample (half an episode, ~6000 frames, on average): far below what a
GPU consumes (`python -m pi0_armfix.bench video` measures it). B1K's 1st-place team re-encoded
to 224²; so does this tool: every frame is decoded once, in order, resized to fit inside `--size`²
(`video.fit_frames`, aspect kept), and written with a keyframe every `--gop` frames, at the same
timestamps, so a random read costs at most `--gop` small frames per camera.

The output is a LeRobot dataset of the same layout version that the project (and LeRobot) read
like any other: the data parquet files and metadata are hard-linked (copied across file
systems), `meta/info.json` gets the new video shapes and codec, and video features other than
`--features` are left out (`matched`, the default: the cameras training reads, by the alias
table of `pi0_armfix.data.cameras` — B1K's depth and segmentation videos are not needed; `all`;
or a comma-separated list of feature names), from the videos and from every metadata file that
names them (`info.json`, `stats.json`, `episodes_stats.jsonl`, v3.0's `meta/episodes` columns
`videos/<feature>/...` and `stats/<feature>/...`), so LeRobot's tools find no feature half gone.
Written into a staging folder renamed when complete; `--workers` files are encoded at once (default:
every core), with a progress bar.
"""

from __future__ import annotations

import concurrent.futures
import json
import multiprocessing
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pyarrow.parquet as pq
from absl import app, flags
from tqdm import tqdm

from pi0_armfix import console
from pi0_armfix.data import cameras as cameras_lib
from pi0_armfix.data.formats.lerobot_writer import codec_name
from pi0_armfix.data.formats.video import VideoDecoder, VideoWriter


def video_features(info: dict, chosen: str, root: Path) -> list[str]:
    """The video features to re-encode: `matched`, `all` or a comma-separated list."""
    videos = [name for name, f in info["features"].items() if f.get("dtype") == "video"]
    if not videos:
        raise ValueError(f"{root} has no video features; nothing to re-encode")
    if chosen == "all":
        return videos
    if chosen == "matched":
        return list(cameras_lib.match_cameras(videos, None, str(root)).values())
    names = [n.strip() for n in chosen.split(",") if n.strip()]
    unknown = [n for n in names if n not in videos]
    if unknown:
        raise ValueError(f"--features: {unknown} are not video features of {root}; its video "
                         f"features: {videos}")
    return names


def _walk(folder: Path) -> Iterator[Path]:
    """Every file under `folder`, following symlinked folders (a dataset assembled from links)."""
    for parent, _, names in os.walk(folder, followlinks=True):
        for name in names:
            yield Path(parent) / name


def _files_of(root: Path, feature: str) -> list[Path]:
    """Every mp4 of a feature: its name is a folder of the path in every LeRobot layout."""
    return sorted(p for p in _walk(root / "videos")
                  if p.suffix == ".mp4" and feature in p.relative_to(root).parts)


def reencode_file(source: str, target: str, size: int, gop: int, codec: str, crf: int,
                  fps: float) -> tuple[int, tuple[int, int]]:
    """One mp4 -> one mp4 (frames fit inside size², same timestamps). Returns (frames, (h, w))."""
    decoder = VideoDecoder(Path(source), fps, size=(size, size))
    count = 0
    try:
        with VideoWriter(Path(target), fps=fps, height=decoder.height, width=decoder.width,
                         codec=codec, gop=gop, crf=crf, options={"preset": "veryfast"}) as out:
            for seconds, image in decoder.frames():
                out.write(image, seconds)
                count += 1
    finally:
        decoder.close()
    return count, (decoder.height, decoder.width)


def _link_tree(source: Path, target: Path, skip: Path) -> None:
    """Hard-links (or copies, across file systems) every file under `source` but `skip`."""
    for path in _walk(source):
        if skip in path.parents:
            continue
        destination = target / path.relative_to(source)
        destination.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, destination)
        except OSError:
            shutil.copy2(path, destination)


def reencode_dataset(input_root: str | Path, output_root: str | Path, *, size: int = 224,
                     gop: int = 8, codec: str = "libx264", crf: int = 18,
                     features: str = "matched", workers: int = 0,
                     progress: bool = True) -> dict[str, float]:
    """Writes the re-encoded dataset (see the module docstring). Returns what it did:
    {"files", "frames", "seconds", "frames_per_s"}."""
    input_root, output_root = Path(input_root), Path(output_root)
    info_path = input_root / "meta" / "info.json"
    if not info_path.is_file():
        raise ValueError(f"--input={input_root} is not a LeRobot dataset root: {info_path} is "
                         "missing")
    if output_root.exists():
        raise ValueError(f"--output={output_root} already exists; choose a new folder")
    if size < 16 or gop < 1:
        raise ValueError(f"--size={size} must be >= 16 and --gop={gop} >= 1")
    info = json.loads(info_path.read_text())
    chosen = video_features(info, features, input_root)
    fps = float(info["fps"])
    jobs = [(feature, path) for feature in chosen for path in _files_of(input_root, feature)]
    if not jobs:
        raise ValueError(f"{input_root / 'videos'} holds no mp4 files of {chosen}")

    output_root.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{output_root.name}.partial-",
                                    dir=output_root.parent))
    start, frames, shapes = time.perf_counter(), 0, {}
    try:
        _link_tree(input_root, staging, skip=input_root / "videos")
        if not any(p.suffix == ".parquet" for p in _walk(staging / "data")):
            raise ValueError(f"{input_root / 'data'} holds no parquet file to carry over: the "
                             "output would have videos without rows; point --input at a "
                             "complete dataset root")
        workers = workers or os.cpu_count() or 1
        # Spawned, not forked: the caller may hold threads (JAX, Grain) that fork would copy.
        with concurrent.futures.ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(reencode_file, str(path),
                                   str(staging / path.relative_to(input_root)),
                                   size, gop, codec, crf, fps): feature
                       for feature, path in jobs}
            bar = tqdm(total=len(jobs), unit="video", disable=not progress,
                       desc=f"re-encoding to {size}² (gop {gop})")
            for future in concurrent.futures.as_completed(futures):
                count, shape = future.result()
                frames += count
                shapes[futures[future]] = shape
                bar.update(1)
                bar.set_postfix(frames=frames)
            bar.close()
        _rewrite_info(info, chosen, shapes, codec, gop, staging / "meta" / "info.json")
        dropped = [name for name, f in info["features"].items()
                   if f.get("dtype") == "video" and name not in chosen]
        drop_from_metadata(staging / "meta", dropped)
        os.rename(staging, output_root)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    seconds = time.perf_counter() - start
    return {"files": len(jobs), "frames": frames, "seconds": seconds,
            "frames_per_s": frames / seconds}


def _rewrite_info(info: dict, chosen: Sequence[str], shapes: dict, codec: str, gop: int,
                  path: Path) -> None:
    features = {}
    for name, feature in info["features"].items():
        if feature.get("dtype") == "video":
            if name not in chosen:
                continue
            height, width = shapes[name]
            feature = {**feature, "shape": [height, width, 3]}
            feature["info"] = {**feature.get("info", {}), "video.height": height,
                               "video.width": width, "video.codec": codec_name(codec),
                               "video.pix_fmt": "yuv420p", "video.gop": gop,
                               "video.is_depth_map": False}
        features[name] = feature
    info = {**info, "features": features}
    if "total_videos" in info:
        info["total_videos"] = info["total_episodes"] * len(chosen)
    path.unlink()  # a hard link to the input's info.json: never write through it
    path.write_text(json.dumps(info, indent=4))


def _replace(path: Path, text: str | None = None, table=None) -> None:
    """Writes a metadata file of the staging tree, never through its hard link to the input."""
    path.unlink()
    if table is not None:
        pq.write_table(table, path)
    else:
        path.write_text(text)


def drop_from_metadata(meta: Path, dropped: Sequence[str]) -> None:
    """Removes the `dropped` features from every metadata file under `meta` but `info.json`
    (rewritten by `_rewrite_info`): `stats.json`, `episodes_stats.jsonl`, and the
    `videos/<feature>/...` and `stats/<feature>/...` columns of v3.0's `meta/episodes`."""
    if not dropped:
        return
    stats = meta / "stats.json"
    if stats.is_file():
        kept = {k: v for k, v in json.loads(stats.read_text()).items() if k not in dropped}
        _replace(stats, json.dumps(kept, indent=4))
    per_episode = meta / "episodes_stats.jsonl"
    if per_episode.is_file():
        rows = [json.loads(line) for line in per_episode.read_text().splitlines() if line.strip()]
        for row in rows:
            row["stats"] = {k: v for k, v in row.get("stats", {}).items() if k not in dropped}
        _replace(per_episode, "".join(json.dumps(r) + "\n" for r in rows))
    prefixes = tuple(f"{kind}/{name}/" for name in dropped for kind in ("videos", "stats"))
    for path in sorted((meta / "episodes").rglob("*.parquet")) if (meta / "episodes").is_dir() \
            else []:
        table = pq.read_table(path)
        gone = [c for c in table.column_names if c.startswith(prefixes)]
        if gone:
            _replace(path, table=table.drop_columns(gone))


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    f = flags.FLAGS
    try:
        result = reencode_dataset(f.input, f.output, size=f.size, gop=f.gop, codec=f.codec,
                                  crf=f.crf, features=f.features, workers=f.workers)
    except ValueError as err:
        sys.exit(f"error: {err}")
    print(f"re-encoded {result['files']} videos, {result['frames']:,} frames in "
          f"{result['seconds']:.1f} s ({result['frames_per_s']:.0f} frames/s); "
          f"train on it with --config.data.root={f.output}")



def cli() -> None:
    """The `pi0-armfix-reencode-videos` console script (also `python -m
    pi0_armfix.tools.reencode_videos`)."""
    flags.DEFINE_string("input", None, "the LeRobot dataset root to read", required=True)
    flags.DEFINE_string("output", None, "the new dataset root to write (must not exist)",
                        required=True)
    flags.DEFINE_integer("size", 224, "frames are resized to fit inside size x size")
    flags.DEFINE_integer("gop", 8, "frames between keyframes")
    flags.DEFINE_string("codec", "libx264", "PyAV encoder")
    flags.DEFINE_integer("crf", 18, "the encoder's constant rate factor (lower: better)")
    flags.DEFINE_string("features", "matched",
                        "video features to keep: matched (the cameras training reads), all, or a "
                        "comma-separated list")
    flags.DEFINE_integer("workers", 0, "files encoded at once (0: every core)")
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.reencode_videos"))


if __name__ == "__main__":
    cli()
