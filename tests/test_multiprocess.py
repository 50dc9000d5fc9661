"""Multi-process training (docs/design.md §6): 2 processes x 2 CPU devices reproduce 1
process x 4."""

import socket
import subprocess

import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)

pytestmark = pytest.mark.slow  # the slow lane: several training processes

STEPS = 5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_two_processes_of_two_devices_reproduce_one_process_of_four(tmp_path, cache_dir,
                                                                    demo_root):
    # fsdp=2 shards the params across the two processes; the final evaluation samples across them.
    overrides = tf.tiny_overrides(demo_root, train__total_steps=STEPS,
                                  train__checkpoint_every=STEPS, sharding__fsdp=2,
                                  eval__every=STEPS)
    config = "configs/arm_focused.py"

    single = subprocess.run(
        tf.train_command(config, tmp_path / "single", overrides),
        env=tf.env(cache_dir, devices=4),
        cwd=tf.REPO_ROOT, capture_output=True, text=True, timeout=600)
    assert single.returncode == 0, single.stderr[-3000:]

    port = _free_port()
    processes = [
        subprocess.Popen(
            tf.train_command(config, tmp_path / "multi", overrides)
            + ["--num_processes=2", f"--coordinator_address=localhost:{port}",
               f"--process_id={i}"],
            env=tf.env(cache_dir, devices=2),
            cwd=tf.REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)]
    try:
        outputs = [p.communicate(timeout=600)[0] for p in processes]
    finally:  # a pair that hangs must not outlive the test and starve the rest of the suite
        for p in processes:
            p.kill()
    for p, output in zip(processes, outputs):
        assert p.returncode == 0, output[-3000:]

    single_records, multi_records = tf.records(tmp_path / "single"), tf.records(tmp_path / "multi")
    losses = [[r["loss"] for r in records if "loss" in r]
              for records in (single_records, multi_records)]
    assert len(losses[0]) == STEPS
    np.testing.assert_allclose(losses[1], losses[0], rtol=0, atol=1e-5)
    errors = [{k: v for k, v in records[-1].items() if k.startswith("err/")}
              for records in (single_records, multi_records)]
    assert errors[0] and errors[0].keys() == errors[1].keys()
    np.testing.assert_allclose(list(errors[1].values()), list(errors[0].values()), rtol=1e-4)
