"""What the command-line entrypoints print: quiet library logging unless asked for."""

from __future__ import annotations

import logging as std_logging

from absl import flags, logging


def quiet_library_logging() -> None:
    """Unless `--verbosity` was given: absl logging at WARNING (orbax logs every file it writes at
    INFO, JAX its backend probing), and no orbax records at all: its warnings are about options it
    adjusts itself (a read-only manager), its errors tracebacks of a failed read or write, which
    the entrypoints report in one line naming the checkpoint."""
    if flags.FLAGS["verbosity"].present:
        return
    logging.set_verbosity(logging.WARNING)
    std_logging.getLogger("absl").addFilter(lambda record: "/orbax/" not in record.pathname)
