"""Where the project caches what it builds once: the demo dataset, offline tokenizers, the
on-disk frame columns of a dataset, benchmark datasets.

`cache_root()` is `$PI0_ARMFIX_CACHE` if set, else `~/.cache/pi0_armfix`; every cached entry is
named by a hash of what it was built from, so an entry is never reused for other inputs.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def cache_root(cache_dir: str | os.PathLike | None = None) -> Path:
    """`cache_dir`, else $PI0_ARMFIX_CACHE, else ~/.cache/pi0_armfix."""
    return Path(cache_dir or os.environ.get("PI0_ARMFIX_CACHE")
                or Path.home() / ".cache" / "pi0_armfix")


def digest(value: Any, length: int = 16) -> str:
    """Hex digest of a JSON-able value (keys sorted): the name of what it builds."""
    text = json.dumps(value, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


@contextlib.contextmanager
def build_lock(entry: Path) -> Iterator[None]:
    """Exclusive lock on `<entry>.lock` beside a cache entry, so that concurrent processes (the
    ranks of one host, or hosts on a shared file system) build it once: hold it, check whether
    the entry exists, build it if not."""
    entry.parent.mkdir(parents=True, exist_ok=True)
    with open(entry.parent / f".{entry.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
