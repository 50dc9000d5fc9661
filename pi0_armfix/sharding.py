"""Device mesh and the sharding of the train state and the batch (docs/design.md §6).

The mesh has two axes, `batch` and `fsdp`. The batch is split over all devices (both axes). The
parameters, and every optimizer / EMA array that mirrors them, are placed by `PARAM_RULES`: the
first rule whose regex matches an array's path wins.

  "fsdp"       shard the array along its largest axis that the fsdp axis size divides, if the
               array is 2-D or more and has at least `FSDP_MIN_SIZE` elements; else replicate.
  "replicate"  a full copy on every device.

Arrays are placed by their path and shape alone, so one rule table covers the params, Adam's
moments (whose paths end in the param's path) and the EMA params, and the sharding of a mirrored
array always equals its param's. Under `fsdp=1` every rule replicates (plain data parallelism).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import AxisType, NamedSharding, PartitionSpec as P

MESH_AXES = ("batch", "fsdp")

# (regex on the "/"-joined path, rule); first match wins.
PARAM_RULES: tuple[tuple[str, str], ...] = (
    (r"(^|.*/)(scale|bias|log_vars)$", "replicate"),  # norms, biases, loss log-variances: small
    (r".*", "fsdp"),
)

# Below this many elements an array is cheaper to replicate than to gather every step.
FSDP_MIN_SIZE = 2**14


def make_mesh(fsdp: int, devices: Sequence[jax.Device] | None = None) -> jax.sharding.Mesh:
    """A `(batch, fsdp)` mesh over all devices (or `devices`), both axes Auto.

    Args:
      fsdp: size of the fsdp axis; -1 = all devices. The batch axis takes the rest.
    """
    devices = list(jax.devices() if devices is None else devices)
    n = len(devices)
    fsdp = n if fsdp == -1 else fsdp
    if not isinstance(fsdp, int) or fsdp < 1 or n % fsdp:
        raise ValueError(f"sharding.fsdp = {fsdp} must be -1 or a positive divisor of the "
                         f"number of devices ({n})")
    return jax.make_mesh((n // fsdp, fsdp), MESH_AXES, axis_types=(AxisType.Auto,) * 2,
                         devices=devices)


def path_name(path: tuple[Any, ...]) -> str:
    """A pytree key path as "a/b/c" (dict keys, attribute names and sequence indices)."""
    parts = []
    for key in path:
        for attr in ("key", "name", "idx"):
            if hasattr(key, attr):
                parts.append(str(getattr(key, attr)))
                break
        else:
            parts.append(str(key))
    return "/".join(parts)


def fsdp_axis(shape: Sequence[int], fsdp: int) -> int | None:
    """The axis an fsdp rule shards: the largest one `fsdp` divides (ties: the last), or None when
    the array stays replicated (1-D, too small, no divisible axis, or fsdp == 1)."""
    if fsdp == 1 or len(shape) < 2 or int(np.prod(shape)) < FSDP_MIN_SIZE:
        return None
    divisible = [(size, axis) for axis, size in enumerate(shape) if size % fsdp == 0]
    return max(divisible)[1] if divisible else None


def partition_spec(name: str, shape: Sequence[int], fsdp: int,
                   rules: Sequence[tuple[str, str]] = PARAM_RULES) -> P:
    """The PartitionSpec of the array at path `name` with `shape` under `rules`."""
    for pattern, rule in rules:
        if re.fullmatch(pattern, name):
            break
    else:
        raise ValueError(f"no sharding rule matches parameter {name!r}")
    if rule == "replicate":
        return P()
    if rule != "fsdp":
        raise ValueError(f"unknown sharding rule {rule!r} for parameter {name!r}")
    axis = fsdp_axis(shape, fsdp)
    if axis is None:
        return P()
    return P(*[("fsdp" if a == axis else None) for a in range(len(shape))])


def tree_shardings(tree: Any, mesh: jax.sharding.Mesh,
                   rules: Sequence[tuple[str, str]] = PARAM_RULES) -> Any:
    """NamedShardings for every array leaf of `tree` (arrays or ShapeDtypeStructs)."""
    fsdp = mesh.shape["fsdp"]
    return jax.tree_util.tree_map_with_path(
        lambda path, x: NamedSharding(mesh, partition_spec(path_name(path), x.shape, fsdp,
                                                           rules)),
        tree)


def batch_sharding(mesh: jax.sharding.Mesh) -> NamedSharding:
    """Leading (batch) axis split over every device of the mesh."""
    return NamedSharding(mesh, P(MESH_AXES))


def replicated(mesh: jax.sharding.Mesh) -> NamedSharding:
    return NamedSharding(mesh, P())


def check_batch_size(batch_size: int, mesh: jax.sharding.Mesh, field: str,
                     microbatches: int = 1) -> None:
    """Raises ValueError unless the global batch divides evenly over the mesh's devices and
    processes (each process feeds its own devices), and each device's rows over `microbatches`
    (`training.step.microbatch`)."""
    devices, processes = mesh.size, jax.process_count()
    if batch_size <= 0 or batch_size % devices or batch_size % processes:
        raise ValueError(f"{field} = {batch_size} must be a positive multiple of the number of "
                         f"devices ({devices}) and of processes ({processes})")
    if microbatches < 1 or (batch_size // devices) % microbatches:
        raise ValueError(f"train.microbatches = {microbatches} must be >= 1 and divide the "
                         f"{batch_size // devices} samples of each device ({field} = "
                         f"{batch_size} over {devices} device(s))")
