"""What the command-line entrypoints print: quiet library logging unless asked for, and a user's
error as one line."""

from __future__ import annotations

import contextlib
import logging as std_logging
from collections.abc import Callable, Iterator

from absl import flags, logging


def quiet_library_logging() -> None:
    """Unless `--verbosity` was given: absl logging at WARNING (orbax logs every file it writes at
    INFO, JAX its backend probing), and no orbax records at all: its warnings are about options it
    adjusts itself (a read-only manager), its errors tracebacks of a failed read or write, which
    the entrypoints report in one line naming the checkpoint; nor asyncio's reports of the
    sibling reads of such a failure."""
    if flags.FLAGS["verbosity"].present:
        return
    logging.set_verbosity(logging.WARNING)
    std_logging.getLogger("absl").addFilter(lambda record: "/orbax/" not in record.pathname)
    # A failed read of a damaged checkpoint fails orbax's sibling reads too; whichever of them
    # nobody awaited is printed by asyncio when collected, with its traceback, after the one-line
    # report (or not, as the collection happens to fall).
    std_logging.getLogger("asyncio").addFilter(
        lambda record: "exception was never retrieved" not in record.getMessage())


@contextlib.contextmanager
def user_errors(program: str) -> Iterator[None]:
    """A ValueError (every user-caused error of the library: config, layout, data, checkpoint)
    ends `program` with its one-line message, not a traceback."""
    try:
        yield
    except ValueError as e:
        raise SystemExit(f"{program}: {e}") from None


HELP_FLAGS = ("--help", "-?", "--helpshort", "--helpfull", "--helpxml")


def flags_parser(program: str) -> Callable[[list[str]], list[str]]:
    """absl's flag parsing for `app.run(main, flags_parser=...)`: `--help` exits 0 (absl's exits
    1, which scripts read as a failure), a bad flag is one line naming it."""

    def parse(argv: list[str]) -> list[str]:
        try:
            return flags.FLAGS(argv)
        except SystemExit as e:
            if e.code == 1 and any(a.split("=")[0] in HELP_FLAGS for a in argv[1:]):
                raise SystemExit(0) from None
            raise
        except flags.Error as e:
            raise SystemExit(f"{program}: {e} (--help lists the flags)") from None

    return parse
