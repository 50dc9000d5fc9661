"""Flattened views of a nested parameter dict, in openpi's naming ("a/b/c")."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def flatten_tree(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dict -> {"a/b/c": leaf} (openpi's flattened names)."""
    flat = {}
    for key, value in tree.items():
        path = f"{prefix}/{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            flat.update(flatten_tree(value, path))
        else:
            flat[path] = value
    return flat


def count_params(tree: Mapping[str, Any]) -> int:
    """Number of scalars of a flattened tree whose values are arrays, shape structs or [shape, dtype]."""
    return sum(math.prod(v[0] if isinstance(v, (list, tuple)) else v.shape) for v in tree.values())
