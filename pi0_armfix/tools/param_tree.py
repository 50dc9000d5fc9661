"""Prints a model preset's flattened parameter tree as JSON, without allocating it.

  python -m pi0_armfix.tools.param_tree --preset=pi0

Output: `{"path/with/slashes": [shape, dtype], ...}` (sorted, the format of
`tests/reference/openpi_param_tree.json`), then a last line `parameters: N`.
"""

from __future__ import annotations

import json

from absl import app, flags

from pi0_armfix import console
from pi0_armfix.model import config as model_config
from pi0_armfix.model import flow_model
from pi0_armfix.model.tree import count_params

_PRESET = flags.DEFINE_enum("preset", "pi0", model_config.PRESETS, "Model preset.")


def main(argv: list[str]) -> None:
    del argv
    tree = flow_model.param_tree(model_config.get_preset(_PRESET.value))
    print(json.dumps(tree, indent=1))
    print(f"parameters: {count_params(tree):,}")



def cli() -> None:
    """The `pi0-armfix-param-tree` console script (also `python -m pi0_armfix.tools.param_tree`)."""
    app.run(main, flags_parser=console.flags_parser("pi0_armfix.tools.param_tree"))


if __name__ == "__main__":
    cli()
