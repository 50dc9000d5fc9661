"""A `Recipe` as a config file that `train`, `evaluate`, `study` and the analysis take as is.

The file builds on `configs/base.py` (the demo model and its defaults), sets what the robot is,
then the lever. Its argument picks the variant: none = the recipe, `uniform` = the same robot
with openpi's plain loss and no lever (the baseline a study compares it with, named first:
`--configs=<name>:uniform,<name>`). Every setting is one line with its reason above it, so a
guess is a line to change.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

from pi0_armfix.recipe.recipe import Recipe, Setting

WIDTH = 100


def _comment(text: str, indent: str = "    ") -> list[str]:
    lines = []
    for paragraph in text.splitlines():
        lines += textwrap.wrap(paragraph, WIDTH - len(indent) - 2, break_on_hyphens=False) or [""]
    return [f"{indent}# {line}".rstrip() for line in lines]


def _assignment(setting: Setting, indent: str = "    ") -> list[str]:
    text = f"{indent}config.{setting.key} = {setting.value!r}"
    if len(text) <= WIDTH or not isinstance(setting.value, dict):
        return [text]
    items = [f"{indent}    {k!r}: {v!r}," for k, v in setting.value.items()]
    return [f"{indent}config.{setting.key} = {{", *items, f"{indent}}}"]


def _settings(settings: Sequence[Setting]) -> list[str]:
    lines = []
    for setting in settings:
        if setting.why:
            lines += _comment(setting.why)
        lines += _assignment(setting)
    return lines


def render(recipe: Recipe, *, name: str, source: str, command: str, verdict: Sequence[str]
           ) -> str:
    """The config file's text.

    Args:
      recipe: what to write.
      name: the file's stem (the study's config name).
      source: the set and the code version it was written from (the docstring's first line).
      command: the command that wrote it (to rerun after a change to the set).
      verdict: the analysis' verdict lines, quoted in the docstring.
    """
    doc = [f"The recipe of {source}.", "",
           f"Written by `{command}`",
           "from the set's feature names and the diagnosis of its data; every line below says "
           "why it was chosen.", "",
           "  python -m pi0_armfix.train --config=configs/" + name + ".py --workdir=runs/" + name,
           "  python -m pi0_armfix.study --configs=" + name + ":uniform," + name + " --seeds=3 "
           "--closed_loop_episodes=0 --workdir=runs/" + name + "_study", "",
           "`:uniform` is the same robot with a uniform loss and no lever: the baseline.", "",
           "The diagnosis (pi0_armfix.tools.analyze_action_magnitudes):",
           *(f"  {line}" for line in verdict),
           "", f"The lever: {recipe.lever_why}."]
    if recipe.notes:
        doc += ["", "Not tested or not chosen:", *(f"  - {line}" for line in recipe.notes)]
    wrapped = []
    for line in doc:
        indent = "    " if line.startswith("  ") else ""
        wrapped += textwrap.wrap(line, WIDTH, subsequent_indent=indent,
                                 break_on_hyphens=False, break_long_words=False) or [""]
    body = [
        '"""' + wrapped[0], *wrapped[1:], '"""', "",
        "from pi0_armfix.configs import base", "",
        "VARIANTS = (\"\", \"uniform\")", "", "",
        "def get_config(arg=None):",
        "    variant = arg or \"\"",
        "    if variant not in VARIANTS:",
        f"        raise ValueError(f\"configs/{name}.py:{{arg}}: the variants are '' (the recipe) \"",
        "                         \"and 'uniform' (the same robot, no lever)\")",
        "    config = base.get_config()",
        *_settings(recipe.robot),
        "    if variant == \"uniform\":",
        "        return config",
        *_comment(recipe.lever_why),
        *(_assignment(s) for s in recipe.lever),
        "    return config", ""]
    return "\n".join(line if isinstance(line, str) else "\n".join(line) for line in body)
