"""Exact resume (docs/design.md §6): a run killed after a checkpoint and restarted ends where an
uninterrupted run ends, bitwise, with the same logged losses and curriculum phases."""

import json
import os
import signal
import subprocess
import time

import jax
import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import sharding
from pi0_armfix.training import checkpoint

pytestmark = pytest.mark.slow  # the slow lane: a run killed and restarted

N = 3  # the checkpoint the run is killed after; the run has 2N steps


def _overrides(tmp_path, demo_root):
    # loss_balanced (balancer state), EMA params, and a curriculum phase switch after step N.
    arm_heavy = tmp_path / "arm_heavy.json"
    arm_heavy.write_text(json.dumps({"episodes": [1, 3]}))
    return tf.tiny_overrides(
        demo_root, train__total_steps=2 * N, train__checkpoint_every=N, eval__every=N,
        optim__ema_decay=0.9, data__arm_heavy_episodes=str(arm_heavy),
        data__curriculum=((N + 1, {"full": 1.0}), (2 * N, {"full": 0.5, "arm_heavy": 0.5})))


def _final_state(workdir):
    state, _, _ = checkpoint.Checkpoints(workdir / "checkpoints", read_only=True).restore_for_eval(
        2 * N, sharding.make_mesh(1), items=None)
    return jax.device_get(state)


def test_run_killed_after_a_checkpoint_and_restarted_matches_an_uninterrupted_run(
        tmp_path, cache_dir, demo_root):
    overrides = _overrides(tmp_path, demo_root)
    config = "configs/loss_balanced.py"

    reference = tf.run_train(config, tmp_path / "reference", overrides, cache_dir)
    assert reference.returncode == 0, reference.stderr[-3000:]

    workdir = tmp_path / "killed"
    with open(tmp_path / "killed.log", "w") as log:
        run = subprocess.Popen(tf.train_command(config, workdir, overrides), env=tf.env(cache_dir),
                               cwd=tf.REPO_ROOT, stdout=log, stderr=subprocess.STDOUT)
        finalized = workdir / "checkpoints" / str(N)  # orbax renames it into place when complete
        deadline = time.monotonic() + 600
        while not finalized.exists():
            assert run.poll() is None, (tmp_path / "killed.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "no checkpoint of step N within 10 minutes"
            time.sleep(0.01)
        run.send_signal(signal.SIGKILL)
        run.wait()
    assert not (workdir / "checkpoints" / str(2 * N)).exists(), \
        "the run finished before it was killed: the test did not interrupt it"

    restarted = tf.run_train(config, workdir, overrides, cache_dir)
    assert restarted.returncode == 0, restarted.stderr[-3000:]
    assert f"resumed from {workdir / 'checkpoints' / str(N)}" in restarted.stdout

    expected, actual = _final_state(tmp_path / "reference"), _final_state(workdir)
    assert jax.tree.structure(actual) == jax.tree.structure(expected)
    jax.tree.map(np.testing.assert_array_equal, actual, expected)

    def train_records(records):
        return [r for r in records if "loss" in r]

    expected_records, actual_records = tf.records(tmp_path / "reference"), tf.records(workdir)
    assert train_records(actual_records) == train_records(expected_records)
    assert [r["phase"] for r in train_records(actual_records)] == [0, 0, 0, 0, 1, 1]
    assert actual_records[-1] == expected_records[-1]  # the final evaluation


def test_a_forked_worker_ignores_the_signals_its_run_handles():
    from pi0_armfix.training import preemption
    with preemption.stop_on_signals(lambda line: None) as stop:
        child = os.fork()
        if child == 0:  # a data worker: the terminal's two Ctrl-C reach it too
            try:
                os.kill(os.getpid(), signal.SIGINT)
                os.kill(os.getpid(), signal.SIGINT)
                os._exit(0 if stop.signum is None else 3)
            except BaseException:  # noqa: BLE001 - an Abandoned raised in the worker
                os._exit(4)
        _, status = os.waitpid(child, 0)
    assert os.waitstatus_to_exitcode(status) == 0


def test_a_run_stopped_at_once_kills_its_worker_processes():
    import multiprocessing
    import time as time_lib
    from pi0_armfix.training import preemption
    worker = multiprocessing.get_context("fork").Process(target=time_lib.sleep, args=(60,))
    worker.start()
    preemption.stop_workers()
    assert not worker.is_alive()
