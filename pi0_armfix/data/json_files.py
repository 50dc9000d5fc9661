"""JSON files written atomically: a reader (another process of the run, a resumed run, a study)
never sees a partial file, and a crash leaves the previous file whole; and a user's JSON file read
with one-line errors that name it."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def write_json_atomic(path: str | Path, payload: Any, indent: int | None = 2) -> None:
    """Writes `payload` as JSON (`indent`: None for one line) through a temporary file and a
    rename, readable as any file the user writes (the temporary file is created 0600; colleagues
    on a shared cluster read it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.name}.",
                                     delete=False) as tmp:
        tmp.write(json.dumps(payload, indent=indent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp.name, 0o666 & ~umask)
    os.replace(tmp.name, path)


def read_json(path: str | Path, name: str) -> Any:
    """The JSON in `path`; a missing or unreadable file, or one that is not JSON, is a ValueError
    `"<name> does not exist"` / `"<name> is not valid JSON: ..."` (`name` names the file and what
    asked for it, e.g. `f"norm stats file {path}"`)."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"{name} does not exist") from None
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{name} is not valid JSON: {err}") from None
