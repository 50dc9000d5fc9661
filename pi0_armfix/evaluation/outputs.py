"""What an evaluation writes: its folder checked writable before the work, strict JSON."""

from __future__ import annotations

import math
from typing import Any

from etils import epath


def writable_folder(folder: epath.Path,
                    fix: str = "make the run folder writable (or evaluate a copy of it)", *,
                    create: bool = True) -> None:
    """Checks that a file can be written in `folder` (created when `create`; else probed in the
    nearest folder that exists, so a refused command leaves nothing behind), or raises ValueError
    naming it and `fix` (before the work, which would otherwise be lost at its end)."""
    folder = epath.Path(folder)
    probed = folder
    if not create:
        while not probed.exists() and probed.parent != probed:
            probed = probed.parent
    try:
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        elif not probed.is_dir():
            raise NotADirectoryError(f"{probed} is not a folder")
        probe = probed / ".write_check"
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
