"""Where the project caches what it builds once: the demo dataset, offline tokenizers, the
on-disk frame columns of a dataset, benchmark datasets, and JAX's compiled programs.

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


COMPILED = "jax_compilation_cache"
# Keep programs whose compile took at least this long: the train step, the samplers, the
# evaluation's; the many tiny programs of a run compile faster than they load.
MIN_COMPILE_SECONDS = 0.5


def host_key() -> dict[str, str]:
    """What a compiled program depends on beyond what JAX keys it by (its program, compile
    options, XLA flags, backend and jax / jaxlib versions): the host's CPU (its instruction-set
    flags: code compiled for one CPU may not run on another) and the platforms asked for."""
    import jax
    import jaxlib

    try:
        flags = next((line for line in Path("/proc/cpuinfo").read_text().splitlines()
                      if line.startswith(("flags", "Features"))), "")
    except OSError:
        flags = ""
    return {"jax": jax.__version__, "jaxlib": jaxlib.__version__,
            "platforms": os.environ.get("JAX_PLATFORMS", ""),
            "xla_flags": os.environ.get("XLA_FLAGS", ""), "cpu": digest(flags)}


def use_compilation_cache() -> Path | None:
    """Turns JAX's persistent compilation cache on in `cache_root()/jax_compilation_cache/<host>`
    (`host_key`'s digest, so that a program compiled on another host or JAX is never loaded),
    unless one is set already (`$JAX_COMPILATION_CACHE_DIR` or `jax_compilation_cache_dir`) or
    `$PI0_ARMFIX_COMPILATION_CACHE=0`. Returns the folder it turned on, or None."""
    import jax

    if (os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir
            or os.environ.get("PI0_ARMFIX_COMPILATION_CACHE") == "0"):
        return None
    folder = cache_root() / COMPILED / digest(host_key())
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    return folder
