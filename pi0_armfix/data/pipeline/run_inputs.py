"""What a trained run's policy needs of its dataset, kept in the run folder.

A policy reads an observation as training read a sample: the stored state selected into the
model's state (`data.state_preset` / `data.state_indices`, e.g. B1K 2026's finger sums), the
prompt tokenized with the run's tokenizer (the offline demo tokenizer is built from the task
prompts), the cameras it was trained with. Training writes these into the run folder
(`policy_inputs.json`, and the tokenizer's sentencepiece model as `tokenizer.model`), so that
`pi0_armfix.serve` and `evaluate --closed_loop` read a run without its dataset: a run folder
copied to a robot-side machine serves there. A run trained before they existed opens its data.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from pi0_armfix.data import json_files
from pi0_armfix.data import selection as selection_lib

INPUTS_FILE = "policy_inputs.json"
TOKENIZER_FILE = "tokenizer.model"


@dataclasses.dataclass(frozen=True)
class PolicyInputs:
    """The source attributes a policy reads (`state_selection`, `state_width`, `tasks`, `cameras`,
    `fps`), as a data source has them."""

    state_selection: selection_lib.Selection | None
    state_width: int
    tasks: tuple[str, ...]
    cameras: dict[str, str]
    fps: float
    task_prompts: dict[int, str]  # {task id: prompt} where the dataset lists them (B1K)


def _selection_json(selection: selection_lib.Selection | None) -> dict[str, Any] | None:
    if selection is None:
        return None
    indices = (None if selection.indices is None else
               [list(i) if isinstance(i, tuple) else i for i in selection.indices])
    return {"field": selection.field, "stored_width": selection.stored_width,
            "indices": indices, "preset": selection.preset.name if selection.preset else ""}


def save(workdir: Path, source: Any, tokenizer_model: bytes) -> None:
    """Writes what the policy needs of `source` into `workdir`, and the run's tokenizer
    (`tokenizer_model`: its serialized sentencepiece model)."""
    workdir = Path(workdir)
    json_files.write_json_atomic(workdir / INPUTS_FILE, {
        "state_selection": _selection_json(getattr(source, "state_selection", None)),
        "state_width": int(source.state_width),
        "tasks": sorted(set(source.tasks)),
        "cameras": dict(getattr(source, "cameras", {}) or {}),
        "fps": float(getattr(source, "fps", 0.0)),
        "task_prompts": {str(k): v for k, v in getattr(source, "task_prompts", {}).items()},
    })
    partial = workdir / (TOKENIZER_FILE + ".partial")
    partial.write_bytes(tokenizer_model)
    partial.replace(workdir / TOKENIZER_FILE)


def load(workdir: Path) -> PolicyInputs | None:
    """The saved inputs of a run folder, or None when it has none (trained before they were
    kept: the policy then opens the run's dataset)."""
    path = Path(workdir) / INPUTS_FILE
    if not path.exists():
        return None
    try:
        saved = json.loads(path.read_text())
        chosen = saved["state_selection"]
        selection = None if chosen is None else selection_lib.make_selection(
            int(chosen["stored_width"]),
            indices=[tuple(i) if isinstance(i, list) else i for i in chosen["indices"]]
            if chosen["indices"] is not None else None,
            preset=chosen["preset"], field=chosen["field"], feature="the stored state",
            where=str(path))
        return PolicyInputs(selection, int(saved["state_width"]), tuple(saved["tasks"]),
                            dict(saved["cameras"]), float(saved["fps"]),
                            {int(k): v for k, v in saved.get("task_prompts", {}).items()})
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path} cannot be read ({e}): restore it from the run's training "
                         "machine, or serve the run where its data.root is") from None


def tokenizer_path(workdir: Path) -> Path | None:
    """The run's own copy of its tokenizer model, or None (a run trained before it was kept)."""
    path = Path(workdir) / TOKENIZER_FILE
    return path if path.is_file() else None
