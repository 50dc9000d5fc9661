"""The command line of the entrypoints: flag parsing whose every mistake is one line naming the
flag, the installed experiment configs (`--config=<name>` from any folder), quiet library logging
unless asked for, and a user's error as one line."""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import logging as std_logging
import os
import re
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

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


def flags_parser(program: str,
                 flag_values: flags.FlagValues = flags.FLAGS) -> Callable[[list[str]], list[str]]:
    """absl's flag parsing for `app.run(main, flags_parser=...)`: `--help` exits 0 (absl's exits
    1, which scripts read as a failure), a bad flag is one line naming it."""

    def parse(argv: list[str]) -> list[str]:
        try:
            return _parse_with_help(argv, flag_values, program)
        except flags.Error as e:
            raise SystemExit(f"{program}: {e} (--help lists the flags)") from None

    return parse


def config_flags_parser(program: str, flag_values: flags.FlagValues = flags.FLAGS
                        ) -> Callable[[list[str]], list[str]]:
    """`flags_parser` for an entrypoint with an experiment config (`--config`, defined with
    `ml_collections.config_flags.DEFINE_config_file(..., lock_config=True)`):

    - `--config=configs/<name>.py[:arg]` (or `--config=<name>`) that names no file here is the
      installed config of that name (`configs_dir()`), so the command works from any folder;
    - a config file that does not exist, a `get_config` that raises (a bad scale argument) and an
      override of a key the locked config lacks are each one line naming the flag, with the fix
      (the known configs, absl's "did you mean" suggestion)."""

    def parse(argv: list[str]) -> list[str]:
        argv = [installed_config(a) for a in argv]
        for arg in argv[1:]:  # before parsing: an override of a missing file would raise from it
            if arg.startswith("--config="):
                _check_config_file(program, arg.partition("=")[2].partition(":")[0])
            elif arg.startswith("--config.") and not arg[len("--config."):].partition("=")[0]:
                raise SystemExit(f"{program}: {arg!r} names no key: an override is "
                                 "--config.<section>.<key>=<value> (e.g. "
                                 "--config.train.total_steps=3000)")
        try:
            return _parse_with_help(argv, flag_values, program)
        except flags.Error as e:
            message = str(e)
            if "Error whilst parsing config file" in message:  # get_config raised: its last line
                lines = [line for line in message.splitlines() if line.strip()]
                given = [a for a in argv[1:] if a.startswith("--config=")][-1:] or ["--config"]
                message = f"{given[0]}: {lines[-1].partition(': ')[2] or lines[-1]}"
            raise SystemExit(f"{program}: {message}") from None
        except (AttributeError, KeyError) as e:
            raise SystemExit(f"{program}: {_missing_key_message(e, argv)}") from None

    return parse


def command_help(program: str, flag_values: flags.FlagValues) -> str:
    """`--help` of a command: its module's docstring and every flag it defined, its own and the
    shared ones (`define_lever_flags`). absl's own lists only the flags of the main module, which
    for an installed console script is the generated wrapper: no description, no flags."""
    doc = getattr(sys.modules.get("__main__"), "__doc__", None)  # `python -m`: the command's
    if not doc:  # a console script's wrapper has none: the command's module
        try:
            doc = importlib.import_module(program).__doc__
        except ImportError:
            doc = ""
    doc = (doc or "").strip()
    ours = [m for m in flag_values.flags_by_module_dict()
            if "pi0_armfix" in m or m in ("__main__", sys.argv[0])]
    listed = "\n".join(flag_values.module_help(m) for m in ours)
    return f"{doc}\n\nflags:\n{listed}\n(--helpfull lists every library's flags too)"


def _parse_with_help(argv: list[str], flag_values: flags.FlagValues, program: str = ""
                     ) -> list[str]:
    if program and any(a in ("--help", "-?", "--helpshort", "-h") for a in argv[1:]):
        print(command_help(program, flag_values))
        raise SystemExit(0)
    try:
        return flag_values(argv)
    except SystemExit as e:  # absl's --help exits 1: a help asked for is no failure
        if e.code == 1 and any(a.split("=")[0] in HELP_FLAGS for a in argv[1:]):
            raise SystemExit(0) from None
        raise


def _missing_key_message(error: AttributeError | KeyError, argv: list[str]) -> str:
    """`--config.<key>: the config has no key '<name>'; Did you mean ...?`: ml_collections' error
    for an override of a key the locked config lacks, on one line, naming the override."""
    # ml_collections nests the KeyError's repr: unescape its quotes and line break.
    message = str(error.args[0] if error.args else error).strip("\"")
    if "\\'" in message:
        message = message[1:-1].replace("\\'", "'").replace("\\n", "\n")
    message = message.replace("\n", "; ")
    missing = re.findall(r"'(\w+)'", message)[:1]
    overrides = [a.split("=")[0] for a in argv[1:] if a.startswith("--config.")]
    culprit = [a for a in overrides if set(missing) & set(a.split("."))] or overrides
    return f"{', '.join(culprit)}: the config has no key {message}"


def configs_dir() -> Path:
    """The experiment configs installed with the package (`pi0_armfix/configs/`)."""
    from pi0_armfix import configs

    return Path(configs.__file__).parent


LOCAL_CONFIGS = Path("configs")  # a user's own configs (tools.write_config's), from where it runs


def config_names() -> list[str]:
    """The experiment configs a user can name: the installed ones and those in `configs/` of the
    current folder (`base` is every config's base, not one of them)."""
    files = [*configs_dir().glob("*.py"), *LOCAL_CONFIGS.glob("*.py")]
    return sorted({p.stem for p in files} - {"__init__", "base"})


def config_path(name: str) -> Path | None:
    """The file of the experiment config `name`: `configs/<name>.py` of the current folder where
    there is one (as `--config=configs/<name>.py` reads it), else the installed one; None where
    neither exists."""
    for path in (LOCAL_CONFIGS / f"{name}.py", configs_dir() / f"{name}.py"):
        if path.is_file():
            return path
    return None


def load_config(name: str, arg: str = ""):
    """The `ConfigDict` of the experiment config `name` (`config_path`) with its argument."""
    path = config_path(name)
    if path is None:
        raise ValueError(f"no config {name!r}: configs are {', '.join(config_names())}")
    spec = importlib.util.spec_from_file_location(f"_pi0_armfix_config_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.get_config(arg or None)


def installed_config(arg: str) -> str:
    """`--config=configs/<name>.py[:arg]` (or `--config=<name>`) that names no file here: the
    installed config of that name; any other argument unchanged."""
    if not arg.startswith("--config="):
        return arg
    path, colon, scale = arg.removeprefix("--config=").partition(":")
    if os.path.isfile(path):
        return arg
    name = Path(path).name
    installed = configs_dir() / (name if name.endswith(".py") else f"{name}.py")
    return f"--config={installed}{colon}{scale}" if installed.is_file() else arg


def _check_config_file(program: str, path: str) -> None:
    if not os.path.isfile(path):
        raise SystemExit(f"{program}: --config={path}: no such config file; give a path or the "
                         f"name of an installed config: {', '.join(config_names())}")


def define_lever_flags() -> None:
    """How this command executes the policy (`policies.sampling.Sampling.for_run`, whose
    docstrings say what each lever does): `--execution`, then each lever in place of the
    execution's (unset: the run's `eval.<lever>`, else the execution's)."""
    from pi0_armfix.policies.sampling import EXECUTIONS  # here: the console stays free of jax
    flags.DEFINE_enum("execution", None, list(EXECUTIONS), "adopted: the world's adopted "
                      "execution (the demo world's, else every lever off); none: every lever off "
                      "(unset: the run's eval.execution, adopted by default)")
    flags.DEFINE_integer("average_draws", None, "each executed chunk the mean of this many draws "
                         "(unset: the run's eval.average_draws)")
    flags.DEFINE_float("temperature", None, "the initial noise scaled by this, in (0, 1] (unset: "
                       "the run's eval.temperature)")
    flags.DEFINE_string("group_draws", None, "group=k+group=k: those groups the mean of k draws, "
                        "the rest of --average_draws (e.g. base=4+torso=8; unset: the run's "
                        "eval.group_draws)")
    flags.DEFINE_string("deadband", None, "group=k+group=k: each group holds still where the "
                        "policy commands less motion than k action stds (the base: 0; a joint "
                        "group: its last command; e.g. base=0.2+torso=0.5; unset: the run's "
                        "eval.deadband)")
    flags.DEFINE_integer("n_exec", None, "actions executed of each chunk before replanning (0: "
                         "half the horizon; served to an openpi client: what it executes, for the "
                         "gripper hysteresis, 0: all; unset: the run's eval.n_exec)")
    flags.DEFINE_bool("rtc", None, "each new chunk softly follows the unexecuted tail of the last "
                      "(real-time chunking's soft inpainting; closed loop, b1k harness; unset: the "
                      "run's eval.rtc)")
    flags.DEFINE_float("temporal_ensemble", None, "ACT's temporal ensembling of overlapping "
                       "chunks, weight exp(-m i) for the i-th oldest (m > 0; 0: off; closed loop, "
                       "b1k harness; unset: the run's eval.temporal_ensemble)")
    flags.DEFINE_list("gripper_hysteresis", None, "open_above,close_below of the grippers' "
                      "hysteresis (pi0_armfix.policies.hysteresis), in action units, for the "
                      "executed chunks (closed loop, server); unset: the run's "
                      "eval.gripper_hysteresis; empty: none")


def lever_flags() -> dict[str, Any]:
    """The levers given on the command line (`define_lever_flags`), as `Sampling` fields."""
    # Here, not at the top: the console stays free of jax for the commands that never sample.
    from pi0_armfix.policies.sampling import LEVERS
    return {key: flags.FLAGS[key].value for key in ("execution", *LEVERS)
            if flags.FLAGS[key].value is not None}
