"""Prints a model preset's flattened parameter tree as JSON, without allocating it.

  python -m pi0_armfix.tools.param_tree --preset=pi0

Output: `{"path/with/slashes": [shape, dtype], ...}` (sorted, the format of
`shared/reference/openpi_param_tree.json`), then a last line `parameters: N`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

from absl import app, flags

from pi0_armfix.model import config as model_config
from pi0_armfix.model import policy

_PRESET = flags.DEFINE_enum("preset", "pi0", model_config.PRESETS, "Model preset.")


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dict -> {"a/b/c": leaf}."""
    flat = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, path + "/"))
        else:
            flat[path] = value
    return flat


def param_tree(config: model_config.Pi0Config) -> dict[str, list]:
    """{path: [shape, dtype]} of the preset's parameters (openpi's reference-file format)."""
    flat = flatten(policy.param_shapes(config))
    return {path: [list(leaf.shape), str(leaf.dtype)] for path, leaf in sorted(flat.items())}


def count(tree: Mapping[str, list]) -> int:
    return sum(math.prod(shape) for shape, _ in tree.values())


def main(argv: list[str]) -> None:
    del argv
    tree = param_tree(model_config.get_preset(_PRESET.value))
    print(json.dumps(tree, indent=1))
    print(f"parameters: {count(tree):,}")


if __name__ == "__main__":
    app.run(main)
