"""What an evaluation writes: its folder checked writable before the work, strict JSON."""

from __future__ import annotations

import math
from typing import Any

from etils import epath


def writable_folder(folder: epath.Path,
                    fix: str = "make the run folder writable (or evaluate a copy of it)") -> None:
    """Creates `folder` and checks that a file can be written there, or raises ValueError naming
    it and `fix` (before the work, which would otherwise be lost at its end)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / ".write_check"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"cannot write the results into {folder} ({e.strerror or e}); "
                         f"{fix}") from None


def strict_json(value: Any) -> Any:
    """`value` with every non-finite float replaced by None (JSON has no NaN: null)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value
