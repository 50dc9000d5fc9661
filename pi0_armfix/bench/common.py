"""What the benchmarks share: `--set` changes to a config, the config of a bare data run, a
one-device batch sharding, the memory of a process and its descendants."""

from __future__ import annotations

import ast
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def apply_changes(config: Any, changes: Sequence[str]) -> None:
    """Sets each of `changes` ("key=value", the value a Python literal or else a string) in the
    ConfigDict `config`; a key it does not hold is one error naming the change."""
    import ml_collections

    for change in changes:
        key, sep, text = change.partition("=")
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text
        *path, field = key.split(".")
        section = config
        for part in path:
            section = section.get(part) if isinstance(section, ml_collections.ConfigDict) else None
        if not sep or not isinstance(section, ml_collections.ConfigDict) or field not in section:
            raise ValueError(f"--set={change}: name a config key and its value, e.g. "
                             "--set=model.attention=fused (pi0_armfix/configs/base.py has them)")
        try:
            section[field] = value
        except TypeError as e:
            raise ValueError(f"--set={change}: {e}") from None


def data_config(root: str, num_workers: int) -> Any:
    """A config of just what the pipeline reads: all episodes train, no curriculum, z-score.
    Marks absl flags parsed, as Grain's worker processes need."""
    import ml_collections
    from absl import flags

    flags.FLAGS.mark_as_parsed()
    return ml_collections.ConfigDict({
        "seed": 0, "eval": {"episodes": 0},
        "data": {"root": str(root), "format": "lerobot", "norm": "zscore", "curriculum": (),
                 "num_workers": num_workers, "prefetch": 2}})


def batch_sharding() -> Any:
    """The batch sharding of a one-device mesh (global arrays as training gets them)."""
    import jax

    mesh = jax.make_mesh((1,), ("batch",), axis_types=(jax.sharding.AxisType.Auto,))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))


def timed_steps(iterator: Any, steps: int, warmup: int = 0) -> float:
    """Seconds `steps` global batches of a training iterator take, after `warmup` untimed ones."""
    import time

    import jax

    for _ in range(warmup):
        jax.block_until_ready(next(iterator))
    start = time.perf_counter()
    for _ in range(steps):
        jax.block_until_ready(next(iterator))
    return time.perf_counter() - start


def memory(pid: int | str = "self") -> dict[str, float]:
    """MiB of VmHWM (the peak), VmRSS, RssAnon, RssFile of a process (Linux /proc)."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmHWM", "VmRSS", "RssAnon", "RssFile"):
            fields[key] = int(value.split()[0]) / 1024
    return fields


def is_resource_tracker(command: str) -> bool:
    """Whether a process's command line (`/proc/<pid>/cmdline`) is Python's resource tracker. Its
    module is matched as it runs it: every child carries the warning option that names it."""
    return "multiprocessing.resource_tracker import main" in command


def descendants(pid: int) -> list[int]:
    """The pids of a process's children, theirs, and so on."""
    children = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            children += [int(c) for c in (task / "children").read_text().split()]
        except FileNotFoundError:  # a thread that ended while the tasks were listed
            continue
    return [d for c in children for d in [c, *descendants(c)]]
