"""LeRobot datasets' metadata (codebase v2.0, v2.1, v3.0): versions, file templates, the
episode records of `meta/episodes*` with their files and video segments, the tasks' prompts, and
the parquet and JSON-lines readers that name the file they fail on. What the layouts hold:
`pi0_armfix.data.formats.lerobot`'s docstring."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pi0_armfix.data.formats.files import lfs_pointer_message, unreadable

ACTION = "action"
STATE = "observation.state"
VERSIONS = ("v2.0", "v2.1", "v3.0")

# Data files read ahead of the consumer by a background thread (bounds memory).

V2_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V2_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
V3_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V3_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
V3_EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"


# ====================================================================== shared helpers

FPS_TOLERANCE = 0.01  # relative: the declared fps against the rows' and the videos' rates


def major_version(info: Mapping[str, Any], path: Path) -> int:
    version = str(info["codebase_version"])
    major = version.lstrip("v").split(".")[0]
    if major not in ("2", "3"):
        raise ValueError(f"{path}: codebase_version {version!r} is not supported; "
                         f"supported layouts: {list(VERSIONS)}")
    return int(major)


def open_parquet(path: Path) -> pq.ParquetFile:
    if not path.is_file():
        raise ValueError(f"missing parquet file {path}")
    try:
        return pq.ParquetFile(path)
    except (pa.ArrowException, OSError) as err:
        raise unreadable(path, "parquet file", err) from err


def _read_parquet(path: Path, columns: Sequence[str]) -> pa.Table:
    parquet = open_parquet(path)
    missing = [c for c in columns if c not in parquet.schema_arrow.names]
    if missing:
        raise ValueError(f"{path} has no column(s) {missing}")
    try:
        return parquet.read(columns=list(columns))
    except (pa.ArrowException, OSError) as err:
        raise unreadable(path, "parquet file", err) from err


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        raise ValueError(f"missing LeRobot metadata file {path}")
    try:
        with open(path) as f:
            return [json.loads(line) for line in f if line.strip()]
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(lfs_pointer_message(path) or f"cannot read {path}: {err}") from err


def matrix(column: pa.ChunkedArray | pa.Array, name: str, path: Path) -> np.ndarray:
    """A list column of n rows of equal width w -> [n, w] numpy (zero-copy where arrow allows)."""
    array = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    n = len(array)
    if array.null_count:
        raise ValueError(f"{path}: column {name!r} has {array.null_count} missing values")
    if pa.types.is_fixed_size_list(array.type):
        width = array.type.list_size
    elif pa.types.is_list(array.type) or pa.types.is_large_list(array.type):
        lengths = np.diff(array.offsets.to_numpy())
        width = int(lengths[0]) if n else 0
        if n and (lengths != width).any():
            raise ValueError(f"{path}: column {name!r} has rows of different widths "
                             f"{sorted(set(lengths.tolist()))[:5]}")
    else:
        raise ValueError(f"{path}: column {name!r} has type {array.type}, expected a list of numbers")
    values = array.flatten().to_numpy(zero_copy_only=False)
    return values.reshape(n, width)


def vector(column: pa.ChunkedArray, name: str, path: Path) -> np.ndarray:
    """A scalar (or one-element list) column -> [n] numpy."""
    array = column.combine_chunks()
    if pa.types.is_list(array.type) or pa.types.is_fixed_size_list(array.type):
        return matrix(array, name, path)[:, 0]
    return array.to_numpy(zero_copy_only=False)


# ====================================================================== reader


@dataclasses.dataclass(frozen=True)
class EpisodeRecord:
    """Where one episode's frames are: rows [first_row, first_row + length) of data_file."""

    index: int
    length: int
    task: str
    data_file: Path
    first_row: int
    # camera feature -> (mp4 file, from_timestamp, to_timestamp): the episode's segment of the
    # file (v2: the whole file, to_timestamp infinite)
    videos: Mapping[str, tuple[Path, float, float]]


def _first_task(tasks: Any, where: str) -> str:
    if isinstance(tasks, str):
        return tasks
    if not tasks:
        raise ValueError(f"{where} lists no task")
    return str(tasks[0])


def _template(info: Mapping[str, Any], field: str, path: Path, **values) -> str:
    template = info.get(field)
    if not template:
        raise ValueError(f"{path} has no {field!r} template")
    try:
        return template.format(**values)
    except (KeyError, IndexError, ValueError) as err:
        raise ValueError(f"{path}: cannot fill {field!r} = {template!r}: {err}") from err


def episodes_v2(root: Path, info: Mapping[str, Any], video_keys: Sequence[str]) -> list[EpisodeRecord]:
    path = root / "meta" / "episodes.jsonl"
    info_path = root / "meta" / "info.json"
    chunks_size = int(info.get("chunks_size", 1000))
    episodes = []
    for line, row in enumerate(_read_jsonl(path), 1):
        if "episode_index" not in row or "length" not in row:
            raise ValueError(f"{path} line {line} lacks 'episode_index' or 'length'")
        index = int(row["episode_index"])
        names = dict(episode_chunk=index // chunks_size, episode_index=index)
        episodes.append(EpisodeRecord(
            index=index, length=int(row["length"]),
            task=_first_task(row.get("tasks"), f"{path} line {line}"),
            data_file=root / _template(info, "data_path", info_path, **names), first_row=0,
            videos={key: (root / _template(info, "video_path", info_path, video_key=key, **names),
                          0.0, math.inf) for key in video_keys}))
    return sorted(episodes, key=lambda e: e.index)


def episodes_v3(root: Path, info: Mapping[str, Any], video_keys: Sequence[str]) -> list[EpisodeRecord]:
    files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise ValueError(f"{root / 'meta' / 'episodes'} holds no chunk-*/file-*.parquet files")
    info_path = root / "meta" / "info.json"
    columns = ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index",
               "dataset_from_index"]
    for key in video_keys:
        columns += [f"videos/{key}/chunk_index", f"videos/{key}/file_index",
                    f"videos/{key}/from_timestamp"]
    rows = []
    for file in files:
        present = set(open_parquet(file).schema_arrow.names)
        ends = [f"videos/{key}/to_timestamp" for key in video_keys
                if f"videos/{key}/to_timestamp" in present]
        table = _read_parquet(file, columns + ends)
        rows += [(file, row) for row in table.to_pylist()]
    # v3.0 rows are addressed by the dataset-global `index`; a data file starts at the smallest
    # `dataset_from_index` of the episodes it holds.
    file_start: dict[tuple[int, int], int] = {}
    for _, row in rows:
        key = (row["data/chunk_index"], row["data/file_index"])
        file_start[key] = min(file_start.get(key, row["dataset_from_index"]),
                              row["dataset_from_index"])
    episodes = []
    for file, row in rows:
        chunk, number = row["data/chunk_index"], row["data/file_index"]
        videos = {}
        for key in video_keys:
            video = _template(info, "video_path", info_path, video_key=key,
                              chunk_index=row[f"videos/{key}/chunk_index"],
                              file_index=row[f"videos/{key}/file_index"])
            videos[key] = (root / video, float(row[f"videos/{key}/from_timestamp"]),
                           float(row.get(f"videos/{key}/to_timestamp", math.inf)))
        episodes.append(EpisodeRecord(
            index=int(row["episode_index"]), length=int(row["length"]),
            task=_first_task(row["tasks"], f"{file} episode {row['episode_index']}"),
            data_file=root / _template(info, "data_path", info_path, chunk_index=chunk,
                                       file_index=number),
            first_row=int(row["dataset_from_index"]) - file_start[(chunk, number)],
            videos=videos))
    return sorted(episodes, key=lambda e: e.index)


def task_rows(root: Path) -> list[dict[str, Any]]:
    """The rows of `meta/tasks.jsonl` ([] without the file)."""
    path = root / "meta" / "tasks.jsonl"
    return _read_jsonl(path) if path.is_file() else []


def task_prompts_of(rows: Sequence[Mapping[str, Any]]) -> dict[int, str]:
    """`{task_index: prompt}` of the tasks rows (B1K's: the task ids its evaluation harness
    sends as `task_id`)."""
    return {int(row["task_index"]): row["task"] for row in rows
            if isinstance(row.get("task_index"), int) and isinstance(row.get("task"), str)}


def with_prompts(episodes: list[EpisodeRecord], rows: Sequence[Mapping[str, Any]]
                  ) -> list[EpisodeRecord]:
    """`episodes` whose task is a task name listed in the tasks rows with a prompt, given that
    prompt instead."""
    prompts = {}
    for row in rows:
        name, prompt = row.get("task_name"), row.get("task")
        if isinstance(name, str) and isinstance(prompt, str) and prompt.strip():
            prompts[name] = prompt
    return [dataclasses.replace(e, task=prompts.get(e.task, e.task)) for e in episodes]


def check_row_rate(times: np.ndarray, fps: float, root: Path, episode: EpisodeRecord) -> None:
    """The declared fps against the rows' timestamps of one episode (their median step)."""
    steps = np.diff(times)
    if not len(steps):
        return
    step = float(np.median(steps))
    if step <= 0 or abs(1.0 / step - fps) > FPS_TOLERANCE * fps:
        where = (f"{root / 'meta/info.json'} declares fps {fps:g}, but the rows of "
                 f"episode {episode.index} ({episode.data_file}) are {step:.4f} s apart"
                 + (f" ({1.0 / step:.4g} fps)" if step > 0 else ""))
        if step > 0 and abs(1.0 / step - fps) <= 10 * FPS_TOLERANCE * fps:
            raise ValueError(  # a few % off: a recording clock's stamps, not another rate
                f"{where}: the timestamps drift from the declared rate, as wall-clock stamps "
                "do, and a video frame would be read ever later (no tolerance fixes a "
                "drift). If the data runs at the declared fps, rewrite its timestamp "
                "column from the frame index (timestamp = frame_index / fps); else fix "
                "the declared fps")
        raise ValueError(f"{where}: a video frame would be read at the wrong time; fix the "
                         "declared fps")
