"""Scalar metrics of a run: `metrics.jsonl` (one JSON object per logged step) and TensorBoard.

Only process 0 writes. A resumed run first drops the records of steps after its checkpoint (a
killed run may have logged past it), so the file reads as if the run had never stopped.

The TensorBoard events are written in the training thread, each record on disk when written
(`tensorboard_events`): a failed write stops the mirror with one warning line, and `metrics.jsonl`
goes on, or fails as the run's own error.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping

import jax
from etils import epath

from pi0_armfix.training.tensorboard_events import EventFile

METRICS_FILE = "metrics.jsonl"


def read_metrics(path: epath.PathLike) -> list[dict]:
    """All records of a `metrics.jsonl`, in file order. A torn last line (a run killed while
    writing it) is dropped; an unreadable line before it is an error naming the file and line."""
    path = epath.Path(path)
    if not path.exists():
        return []
    lines = [(number, line) for number, line in enumerate(path.read_text().splitlines(), 1)
             if line.strip()]
    records = []
    for position, (number, line) in enumerate(lines):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            if position == len(lines) - 1:
                break  # the write a kill cut short: the record is written again on resume
            raise ValueError(f"{path} line {number} is not a JSON record ({err}); remove or "
                             "repair that line to resume") from err
    return records


class MetricsWriter:
    """Appends `{"step": N, name: value, ...}` records and mirrors the numbers to TensorBoard.

    Args:
      workdir: the run folder; writes `metrics.jsonl` and `tensorboard/` in it.
      resume_step: the step the run restarts from; records after it are dropped.
    """

    def __init__(self, workdir: epath.PathLike, resume_step: int = 0):
        self._active = jax.process_index() == 0
        if not self._active:
            return
        workdir = epath.Path(workdir)
        self.path = workdir / METRICS_FILE
        kept = [r for r in read_metrics(self.path) if r["step"] <= resume_step]
        self.path.write_text("".join(json.dumps(r) + "\n" for r in kept))
        self._file = self.path.open("a")
        self._tb: EventFile | None = None
        self._tensorboard(lambda: self._open_tensorboard(workdir / "tensorboard"))

    def _open_tensorboard(self, folder: epath.Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self._tb = EventFile(str(folder))

    def _tensorboard(self, action) -> None:
        """`action()` on the TensorBoard mirror; an OSError (a full disk) stops the mirror."""
        try:
            action()
        except OSError as err:
            logging.warning("TensorBoard mirror stopped (%s); %s keeps every record", err,
                            self.path)
            self._tb = None

    def write(self, step: int, scalars: Mapping[str, float | int | str]) -> None:
        """One record; strings are logged to the JSON file only."""
        if not self._active:
            return
        record = {"step": int(step)}
        for name, value in scalars.items():
            record[name] = value if isinstance(value, str) else _json_number(value)
        self._file.write(json.dumps(record) + "\n")
        self._file.flush()
        scalars = {name: float(value) for name, value in record.items()
                   if name != "step" and not isinstance(value, str) and value is not None}
        if self._tb is not None and scalars:
            self._tensorboard(lambda: self._tb.write_scalars(record["step"], scalars))

    def close(self) -> None:
        if self._active:
            self._file.close()
            if self._tb is not None:
                self._tensorboard(self._tb.close)


def _json_number(value) -> float | int | None:
    """Plain Python number; a non-finite float becomes None (JSON has no NaN)."""
    if isinstance(value, int):
        return value
    value = float(value)
    return value if math.isfinite(value) else None
