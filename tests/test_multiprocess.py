"""Multi-process training (docs/design.md §6): 2 processes x 2 CPU devices reproduce 1
process x 4."""

import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)

pytestmark = pytest.mark.slow  # the slow lane: several training processes

STEPS = 5
TIMEOUT = 300  # s per training (alone 30-60 s, beside the rest of the suite)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _start(command: list[str], devices: int, cache_dir, log: Path) -> subprocess.Popen:
    """A training process writing into the file `log` (a pipe read only after the other process
    of the pair could fill and block it mid-collective). faulthandler: a SIGABRT prints every
    thread's Python stack before the process ends."""
    with log.open("w") as out:
        return subprocess.Popen(command, cwd=tf.REPO_ROOT, stdout=out, stderr=subprocess.STDOUT,
                                env={**tf.env(cache_dir, devices=devices),
                                     "PYTHONFAULTHANDLER": "1"})


def _native_stacks(pid: int) -> str:
    """Every thread's native stack of process `pid` (gdb, where installed)."""
    if shutil.which("gdb") is None:
        return "(no gdb on this machine)"
    try:
        return subprocess.run(["gdb", "-p", str(pid), "-batch", "-ex", "thread apply all bt 25"],
                              capture_output=True, text=True, timeout=120).stdout[-20000:]
    except subprocess.TimeoutExpired:
        return "(gdb did not answer in 120 s)"


def _wait(processes: list[subprocess.Popen], logs: list[Path]) -> None:
    """Returns once every process exited 0. Processes still running after `TIMEOUT` s fail the
    test with their native and Python stacks (a hang seen once in a full CI pass sat in XLA's
    compiler, and alone the test never hangs: the stacks are what would say why) and are
    killed, never left to starve the rest of the suite."""
    deadline = time.monotonic() + TIMEOUT
    try:
        try:
            for p in processes:
                p.wait(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            stacks = [_native_stacks(p.pid) for p in processes]
            for p in processes:
                p.send_signal(signal.SIGABRT)
            for p in processes:
                try:
                    p.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    pass
            pytest.fail(f"still running after {TIMEOUT} s:\n" + "\n".join(
                f"--- process {i}: native stacks\n{native}\n--- process {i}: output, Python "
                f"stacks last\n{log.read_text()[-20000:]}"
                for i, (native, log) in enumerate(zip(stacks, logs))))
    finally:
        for p in processes:
            p.kill()
    for p, log in zip(processes, logs):
        assert p.returncode == 0, log.read_text()[-3000:]


def test_two_processes_of_two_devices_reproduce_one_process_of_four(tmp_path, cache_dir,
                                                                    demo_root):
    # fsdp=2 shards the params across the two processes; the final evaluation samples across them.
    overrides = tf.tiny_overrides(demo_root, train__total_steps=STEPS,
                                  train__checkpoint_every=STEPS, sharding__fsdp=2,
                                  eval__every=STEPS)
    config = "configs/arm_focused.py"

    logs = [tmp_path / f"{name}.log" for name in ("single", "multi_0", "multi_1")]
    _wait([_start(tf.train_command(config, tmp_path / "single", overrides), 4, cache_dir,
                  logs[0])], logs[:1])
    port = _free_port()
    _wait([_start(tf.train_command(config, tmp_path / "multi", overrides)
                  + ["--num_processes=2", f"--coordinator_address=localhost:{port}",
                     f"--process_id={i}"], 2, cache_dir, log)
           for i, log in enumerate(logs[1:])], logs[1:])

    single_records, multi_records = tf.records(tmp_path / "single"), tf.records(tmp_path / "multi")
    losses = [[r["loss"] for r in records if "loss" in r]
              for records in (single_records, multi_records)]
    assert len(losses[0]) == STEPS
    np.testing.assert_allclose(losses[1], losses[0], rtol=0, atol=1e-5)
    errors = [{k: v for k, v in records[-1].items() if k.startswith("err/")}
              for records in (single_records, multi_records)]
    assert errors[0] and errors[0].keys() == errors[1].keys()
    np.testing.assert_allclose(list(errors[1].values()), list(errors[0].values()), rtol=1e-4)
