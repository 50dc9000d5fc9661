"""What the data benchmarks share: the config of a bare data run and a one-device batch sharding."""

from __future__ import annotations

from typing import Any


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
