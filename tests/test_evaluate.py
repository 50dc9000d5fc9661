"""Held-out stagnation metrics (DESIGN §7) and the offline evaluation of a checkpoint."""

import json
import subprocess
import sys

import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import evaluate
from pi0_armfix.action_space import ActionLayout

LAYOUT = ActionLayout(groups={"base": (0, 2), "arm": (2, 5), "gripper": (5, 6)}, real_dim=6,
                      action_dim=8, velocity_groups=("base",))
H = 6


def _metrics(predicted, true, valid=None):
    valid = np.ones(true.shape[:2], bool) if valid is None else valid
    return evaluate.chunk_metrics(predicted, true, valid, layout=LAYOUT,
                                  gripper_groups=("gripper",),
                                  gripper_threshold=np.zeros(LAYOUT.action_dim))


def _moving_chunks(n=64, seed=0):
    """Chunks whose arm moves linearly, base drives at a constant speed, gripper closes half-way
    in every other chunk."""
    rng = np.random.default_rng(seed)
    true = np.zeros((n, H, LAYOUT.action_dim))
    true[:, :, 0:2] = rng.normal(size=(n, 1, 2))
    true[:, :, 2:5] = rng.normal(size=(n, 1, 3)) + np.linspace(0, 1, H)[:, None] * rng.normal(
        size=(n, 1, 3))
    true[:, :, 5] = 1.0
    true[::2, H // 2:, 5] = -1.0
    return true


def test_a_perfect_policy_has_gain_one_zero_error_and_full_gripper_recall():
    true = _moving_chunks()
    metrics = _metrics(true.copy(), true)
    for g in LAYOUT.group_names:
        assert metrics[f"err/{g}"] == 0
    for g in ("base", "arm"):
        assert metrics[f"motion_gain/{g}"] == pytest.approx(1.0)
        assert metrics[f"motion_ratio/{g}"] == pytest.approx(1.0)
    assert metrics["gripper_switch_recall"] == 1.0


def test_a_policy_that_holds_the_current_action_has_arm_gain_zero():
    true = _moving_chunks()
    still = np.repeat(true[:, :1], H, axis=1)
    metrics = _metrics(still, true)
    assert metrics["motion_gain/arm"] == 0.0
    assert metrics["motion_ratio/arm"] == 0.0
    assert metrics["gripper_switch_recall"] == 0.0


def test_noise_moves_in_magnitude_but_has_gain_near_zero():
    true = _moving_chunks(n=4000)
    noisy = true[:, :1] + np.random.default_rng(1).normal(size=true.shape)
    metrics = _metrics(noisy, true)
    assert abs(metrics["motion_gain/arm"]) < 0.1
    assert metrics["motion_ratio/arm"] > 1.0


def test_base_displacement_is_the_chunk_mean_velocity():
    true = _moving_chunks()
    half_speed = true.copy()
    half_speed[..., 0:2] *= 0.5  # constant velocity per chunk: last - first would be 0
    assert _metrics(half_speed, true)["motion_gain/base"] == pytest.approx(0.5)


def test_padded_tail_of_a_chunk_is_ignored():
    true = _moving_chunks()
    valid = np.ones(true.shape[:2], bool)
    valid[:, -2:] = False
    predicted = true.copy()
    predicted[:, -2:] += 100.0  # whatever the policy says past the episode end
    metrics = _metrics(predicted, true, valid)
    assert metrics["err/arm"] == 0
    assert metrics["motion_gain/arm"] == pytest.approx(1.0)


def test_gripper_switch_must_go_the_same_way():
    true = _moving_chunks()
    opens = -true.copy()  # every switch reversed: closing becomes opening
    assert _metrics(opens, true)["gripper_switch_recall"] == 0.0


def test_metrics_are_nan_where_the_data_gives_nothing_to_measure():
    still = np.zeros((4, H, LAYOUT.action_dim))
    metrics = _metrics(still, still)
    assert np.isnan(metrics["motion_gain/arm"]) and np.isnan(metrics["gripper_switch_recall"])


def test_unknown_group_in_eval_config_is_an_error_naming_the_key():
    eval_cfg = dict(gripper_groups=("claw",), plot_groups=(), batch_size=8, max_chunks=16,
                    num_steps=10)
    with pytest.raises(ValueError, match=r"eval.gripper_groups names \['claw'\]"):
        evaluate.check_eval_config(eval_cfg, LAYOUT, num_devices=1)


def test_offline_evaluation_of_a_checkpoint_prints_metrics_and_writes_figures(
        tmp_path, cache_dir, demo_root):
    workdir = tmp_path / "run"
    trained = tf.run_train("configs/arm_focused.py", workdir,
                           tf.tiny_overrides(demo_root, optim__ema_decay=0.5), cache_dir)
    assert trained.returncode == 0, trained.stderr[-3000:]

    result = subprocess.run([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={workdir}"],
                            env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "step 2" in result.stdout
    for column in ("err", "motion_gain", "motion_ratio", "gripper_switch_recall", "left_arm"):
        assert column in result.stdout
    for figure in ("trajectories.png", "group_losses.png"):
        assert (workdir / "eval" / "step_2" / figure).stat().st_size > 10_000
    saved = json.loads((workdir / "eval" / "step_2" / "metrics.json").read_text())
    assert saved["step"] == 2 and saved["params"] == "ema_params"
    assert f"{saved['motion_gain/left_arm']:.3f}" in result.stdout


def test_offline_evaluation_is_quiet_by_default(tmp_path, cache_dir, demo_root):
    workdir = tmp_path / "run"
    assert tf.run_train("configs/uniform.py", workdir, tf.tiny_overrides(demo_root),
                        cache_dir).returncode == 0
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={workdir}"],
                            env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    logged = [line for line in result.stderr.splitlines()
              if line.startswith(("I", "W", "INFO", "WARNING")) and ":" in line[:40]]
    assert logged == [], logged
    assert "Unable to initialize backend" not in result.stderr


def test_offline_evaluation_without_checkpoints_is_a_clear_error(tmp_path):
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={tmp_path}"],
                            env=tf.env(tmp_path), cwd=tf.REPO_ROOT, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode != 0
    assert f"{tmp_path / 'checkpoints'} has no checkpoint" in result.stderr
