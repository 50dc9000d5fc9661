"""Where a command's wall time goes: seconds by part, written beside what the command made.

A run folder's `wall_time.json` holds the parts of its latest start (`python -m pi0_armfix.train`:
opening the data, the norm stats, the state, the first step with its compilation, the other steps,
each evaluation); a closed-loop evaluation writes its own beside its results. `python -m
pi0_armfix.bench walltime` reads them from whole-process runs, with and without the compilation
cache.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path

FILE = "wall_time.json"


class WallTime:
    """Seconds by part, in the order the parts first ran; a part that runs again adds up."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.parts: dict[str, float] = {}

    @contextlib.contextmanager
    def part(self, name: str) -> Iterator[None]:
        """Times the block as `name` (also when it raises: the time was spent)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - start)

    def add(self, name: str, seconds: float) -> None:
        self.parts[name] = self.parts.get(name, 0.0) + seconds

    def record(self) -> dict[str, object]:
        """`{"parts": {name: seconds}, "total": seconds since this object was made}`."""
        return {"parts": dict(self.parts), "total": time.perf_counter() - self.start}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.record(), indent=2))

    def summary(self) -> str:
        """One line: each part's seconds, then the whole."""
        record = self.record()
        parts = ", ".join(f"{name} {seconds:.1f}" for name, seconds in record["parts"].items())
        return f"wall time by part (s): {parts}; in all {record['total']:.1f}"


def load(path: str | Path) -> dict[str, object]:
    """A `wall_time.json` as `WallTime.record` wrote it."""
    return json.loads(Path(path).read_text())
