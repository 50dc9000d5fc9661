"""Tiny training runs for the training tests: a small demo dataset and the overrides of a tiny run.

Runs go through `python -m pi0_armfix.train` in a subprocess (the entrypoint as users start it)
or `train.train_and_evaluate` in-process. Compiled programs are shared through JAX's persistent
compilation cache in one folder per test process (xdist worker), so a run that another test
module already compiled (the tiny `uniform` run, say) does not compile again.
Test modules import the fixtures `cache_dir`, `demo_root` and `arm_delta_run` from here.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

from pi0_armfix.data.formats import demo

REPO_ROOT = Path(__file__).resolve().parents[1]
TINY_EPISODES = 8  # 6 to train on, 2 held out
TIMING_KEYS = ("steps_per_sec", "data_wait")


def write_tiny_demo(path: Path) -> Path:
    """A demo dataset of `TINY_EPISODES` episodes (~3k frames, 2 MB) at `path`."""
    return demo.write_demo_dataset(path, demo.DemoSpec(num_episodes=TINY_EPISODES))


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    """Compilation and tokenizer caches shared by the runs of a test module."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def demo_root(tmp_path_factory) -> Path:
    """The tiny demo dataset of a test module."""
    return write_tiny_demo(tmp_path_factory.mktemp("data") / "demo")


@pytest.fixture(scope="session")
def arm_delta_run(tmp_path_factory) -> Path:
    """A tiny run of `configs/arm_delta.py` (delta torso and arms on a state reordered into the
    action order, as on B1K) on its own tiny demo, shared by the modules that only read it and
    write beside it (serving, export): one training for both."""
    data = write_tiny_demo(tmp_path_factory.mktemp("arm_delta_data") / "demo")
    return trained_tiny_run("configs/arm_delta.py", tmp_path_factory.mktemp("arm_delta_run"), data)


def tiny_overrides(data_root: Path, **changes: Any) -> dict[str, Any]:
    """Flat config overrides (`"train.total_steps": 4`, ...) of a run of the tiny preset on the
    tiny demo: batch 8, no evaluation, a checkpoint at the end. `changes` use `__` for `.`."""
    overrides = {
        "model.preset": "tiny",
        "data.root": str(data_root),
        "train.total_steps": 2,
        "train.batch_size": 8,
        "train.log_every": 1,
        "train.checkpoint_every": 2,
        "optim.warmup_steps": 1,
        "eval.every": 0,
        "eval.episodes": 2,
        "eval.batch_size": 8,
        "eval.max_chunks": 16,
    }
    overrides.update({key.replace("__", "."): value for key, value in changes.items()})
    return overrides


def flags(overrides: Mapping[str, Any]) -> list[str]:
    """`--config.<key>=<value>` flags; strings as they are, other values as Python literals."""
    return [f"--config.{key}={value if isinstance(value, str) else repr(value)}"
            for key, value in overrides.items()]


def env(cache_dir: Path, devices: int = 1) -> dict[str, str]:
    """Environment of a training subprocess: `devices` CPU devices, the repo importable, the
    test process's compilation cache, the module's own tokenizer cache, and XLA's cheapest CPU code generation (tiny
    programs compile ~2x faster; both sides of every comparison use it)."""
    xla_flags = (f"--xla_force_host_platform_device_count={devices} "
                 "--xla_backend_optimization_level=0")
    return dict(os.environ, PYTHONPATH=str(REPO_ROOT), JAX_PLATFORMS="cpu", XLA_FLAGS=xla_flags,
                JAX_COMPILATION_CACHE_DIR=str(cache_dir.parent / "jax_compilation_cache"),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                PI0_ARMFIX_CACHE=str(cache_dir / "pi0_armfix"))


def train_command(config: str, workdir: Path | None, overrides: Mapping[str, Any]) -> list[str]:
    """The entrypoint's command line; no `--workdir` when `workdir` is None."""
    return [sys.executable, "-m", "pi0_armfix.train", f"--config={REPO_ROOT / config}",
            *([f"--workdir={workdir}"] if workdir is not None else []), *flags(overrides)]


def run_train(config: str, workdir: Path | None, overrides: Mapping[str, Any], cache_dir: Path,
              cwd: Path = REPO_ROOT, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(train_command(config, workdir, overrides), env=env(cache_dir),
                          cwd=cwd, capture_output=True, text=True, timeout=timeout)


def trained_tiny_run(config: str, workdir: Path, data_root: Path, **changes: Any) -> Path:
    """`workdir` after a tiny run of `config` (`configs/<name>.py`) on the tiny demo at
    `data_root` (`changes`: as `tiny_overrides`'), trained in-process."""
    from pi0_armfix import train

    run_config = importlib.import_module(f"pi0_armfix.configs.{Path(config).stem}").get_config()
    run_config.update_from_flattened_dict(tiny_overrides(data_root, **changes))
    train.train_and_evaluate(run_config, str(workdir))
    return workdir


def records(workdir: Path) -> list[dict]:
    """`metrics.jsonl` records without the timing fields (which no two runs share)."""
    lines = (workdir / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k not in TIMING_KEYS} for line in lines]


def tiny_b1k_config(scale: str, root: Path, **overrides: Any):
    """`configs/arm_focused.py:<scale>` (`b1k` or `b1k2026`) shrunk to the tiny preset on a
    B1K-layout fixture at `root`: two steps of batch 8, an evaluation on 2 held-out episodes."""
    from pi0_armfix.configs import arm_focused

    config = arm_focused.get_config(scale)
    config.update_from_flattened_dict({
        "model.preset": "tiny", "model.tokenizer": "", "data.root": str(root),
        "data.num_workers": 0, "train.total_steps": 2, "train.batch_size": 8,
        "train.log_every": 1, "train.checkpoint_every": 2, "optim.warmup_steps": 1,
        "sharding.fsdp": 1, "eval.every": 2, "eval.episodes": 2, "eval.batch_size": 8,
        "eval.max_chunks": 16, **overrides})
    return config
