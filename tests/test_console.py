"""The entrypoints' command line (pi0_armfix.console): every mistake in a flag or a config is one
line naming it, and `--config=<name>` finds the installed configs from any folder."""

import importlib
import os
import subprocess
import sys

import pytest
from absl import flags
from ml_collections import config_flags

import train_fixtures as tf
from pi0_armfix import console


def _parse_config_flags(argv: list[str], program: str = "prog") -> flags.FlagValues:
    """`argv` parsed as a config entrypoint parses it, over flags of its own (as `train` defines
    them; the config's overrides are found in `argv` when the flag is defined)."""
    flag_values = flags.FlagValues()
    config_flags.DEFINE_config_file("config", None, "experiment config", lock_config=True,
                                    flag_values=flag_values, sys_argv=argv)
    flags.DEFINE_string("workdir", None, "run folder", flag_values=flag_values)
    console.config_flags_parser(program, flag_values)(argv)
    return flag_values


def _exit_line(call, *args) -> str:
    """The one line `call(*args)` exits with."""
    with pytest.raises(SystemExit) as e:
        call(*args)
    message = str(e.value.code)
    assert "\n" not in message
    return message


def test_a_config_name_is_found_among_the_installed_configs_from_any_folder(tmp_path,
                                                                          monkeypatch):
    monkeypatch.chdir(tmp_path)  # no configs/ here
    flag_values = _parse_config_flags(["prog", "--config=arm_focused", "--config.seed=3"])
    assert flag_values.config.seed == 3
    assert flag_values.config.data.delta_action_mask  # arm_focused's delta actions
    assert console.installed_config("--config=configs/uniform.py:b1k") == (
        f"--config={console.configs_dir() / 'uniform.py'}:b1k")


def test_an_existing_config_file_is_read_as_given(tmp_path, monkeypatch):
    (tmp_path / "mine.py").write_text(
        "from pi0_armfix.configs import base\n\n"
        "def get_config(arg=None):\n    config = base.get_config()\n    config.seed = 11\n"
        "    return config\n")
    monkeypatch.chdir(tmp_path)
    flag_values = _parse_config_flags(["prog", "--config=mine.py"])
    assert flag_values.config.seed == 11


def test_a_mistyped_key_is_one_line_naming_the_override_with_the_suggestion():
    message = _exit_line(_parse_config_flags, ["prog", "--config=configs/arm_focused.py",
                                               "--config.train.totl_steps=3"], "pi0_armfix.train")
    assert message == ("pi0_armfix.train: --config.train.totl_steps: the config has no key "
                       "'totl_steps'; Did you mean \"total_steps\" instead of \"totl_steps\"?")


def test_an_override_that_names_no_key_is_one_line_with_the_form():
    message = _exit_line(_parse_config_flags, ["prog", "--config=configs/arm_focused.py",
                                               "--config.=4"], "pi0_armfix.train")
    assert message.startswith("pi0_armfix.train: '--config.=4' names no key: an override is "
                              "--config.<section>.<key>=<value>")


@pytest.mark.parametrize("argv, expected", [
    (["--config=configs/nope.py"], "--config=configs/nope.py: no such config file; give a path "
                                   "or the name of an installed config: arm_curriculum, arm_delta, "
                                   "arm_delta_correlated_noise,"),
    (["--config=configs/nope.py", "--config.seed=3"], "--config=configs/nope.py: no such config "
                                                      "file"),
    (["--config=configs/arm_focused.py:foo"], "arm_focused.py:foo: config argument 'foo' is not "
                                              "a scale"),
])
def test_a_missing_config_file_or_a_bad_scale_is_one_line_naming_it(argv, expected):
    message = _exit_line(_parse_config_flags, ["prog", *argv], "pi0_armfix.train")
    assert message.startswith("pi0_armfix.train: --config=")
    assert expected in message


def test_an_unknown_flag_is_one_line_pointing_to_help():
    flag_values = flags.FlagValues()
    flags.DEFINE_integer("episodes", 1, "episodes", flag_values=flag_values)
    parse = console.flags_parser("prog", flag_values)
    message = _exit_line(parse, ["prog", "--episods=3"])
    assert message.startswith("prog: ") and "'episods'" in message and "episodes" in message
    assert message.endswith("(--help lists the flags)")


def test_the_installed_config_names_leave_out_the_shared_base():
    names = console.config_names()
    assert "arm_focused" in names and "uniform" in names
    assert "base" not in names and "__init__" not in names


@pytest.mark.parametrize("module, own_flag", [("serve", "--workdir"), ("evaluate", "--closed_loop")])
def test_an_installed_command_help_prints_its_description_and_every_flag(module, own_flag):
    # As a console script runs it: the main module is a wrapper that defines no flag.
    done = subprocess.run(
        [sys.executable, "-c", f"import sys; from pi0_armfix.{module} import cli; "
         f"sys.argv = ['pi0-armfix-{module}', '--help']; cli()"],
        capture_output=True, text=True, timeout=120, cwd=tf.REPO_ROOT,
        env=dict(os.environ, PYTHONPATH=str(tf.REPO_ROOT)))
    assert done.returncode == 0, done.stderr[-2000:]
    description = importlib.import_module(f"pi0_armfix.{module}").__doc__.strip().splitlines()[0]
    assert description in done.stdout
    for flag in (own_flag, "--average_draws", "--temperature"):
        assert flag in done.stdout


def test_the_entrypoints_compilation_cache_is_keyed_by_the_host_and_left_to_a_users_own(
        tmp_path, monkeypatch):
    import jax

    from pi0_armfix import cache

    before = jax.config.jax_compilation_cache_dir
    monkeypatch.setenv("PI0_ARMFIX_CACHE", str(tmp_path))
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    try:
        jax.config.update("jax_compilation_cache_dir", None)
        folder = cache.use_compilation_cache()
        assert folder == tmp_path / cache.COMPILED / cache.digest(cache.host_key())
        assert jax.config.jax_compilation_cache_dir == str(folder)
        monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_some_other_flag")  # another host's programs
        assert cache.digest(cache.host_key()) != folder.name
        assert cache.use_compilation_cache() is None  # one set already: left as it is
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
