"""The study tool: configs x seeds -> tables with the spread over seeds, resumable."""

import json
import subprocess
import sys

import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import study

LAYOUT = {"preset": "b1k_r1pro", "action_dim": 32}


def _result(config, seed, arm_gain, base_err=1.0, f1=0.5):
    metrics = {f"motion_gain/{g}": arm_gain for g in ("left_arm", "right_arm")}
    metrics |= {"motion_gain/base": 0.8, "err/base": base_err, "gripper_switch/f1": f1,
                "gripper_switch/precision": None}
    return {"config": config, "seed": seed, "steps": 10, "layout": LAYOUT, "metrics": metrics}


def test_aggregate_reports_mean_and_spread_over_seeds_and_the_difference_to_the_baseline():
    results = [_result("uniform", s, g) for s, g in enumerate((0.0, 0.1, 0.2))]
    results += [_result("arm_delta", s, g, base_err=1.05, f1=0.7)
                for s, g in enumerate((0.5, 0.6, 0.7))]
    agg = study.aggregate(results)
    delta = agg["configs"]["arm_delta"]
    assert delta["mean"]["arm_gain"] == pytest.approx(0.6)
    assert delta["std"]["arm_gain"] == pytest.approx(0.1)
    diff, low, high = delta["vs_baseline"]["arm_gain"]
    assert diff == pytest.approx(0.5) and low <= diff <= high
    assert delta["vs_baseline"]["base_err"][0] == pytest.approx(0.05)
    assert delta["targets"] == {"arm_gain": True, "base_err": True, "switch_f1": True}
    assert agg["configs"]["uniform"]["targets"]["arm_gain"] is False
    assert delta["mean"]["gripper_switch/precision"] is None  # no measurement, not a zero


def test_bootstrap_interval_is_deterministic_and_collapses_without_spread():
    a, b = np.array([0.4, 0.5, 0.6]), np.array([0.0, 0.1, 0.2])
    assert study.bootstrap_interval(a, b) == study.bootstrap_interval(a, b)
    assert study.bootstrap_interval(np.full(3, 2.0), np.full(3, 1.0), relative=True) == (
        1.0, 1.0, 1.0)


def test_reports_are_written_and_name_every_config(tmp_path):
    results = [_result(c, s, 0.1 * s) for c in ("uniform", "arm_focused") for s in range(2)]
    study.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    assert "| uniform |" in text and "| arm_focused |" in text and "bootstrap" in text
    assert json.loads((tmp_path / "study.json").read_text())["baseline"] == "uniform"
    assert (tmp_path / "study.png").stat().st_size > 10_000


def test_closed_loop_success_gets_its_own_table_with_the_difference_to_the_baseline(tmp_path):
    results = []
    for config, manipulation in (("uniform", (0.1, 0.2)), ("arm_focused", (0.5, 0.6))):
        for seed, rate in enumerate(manipulation):
            result = _result(config, seed, 0.1)
            result["metrics"] |= {"closed_loop/episodes": 50, "closed_loop/success/task": rate / 2,
                                  "closed_loop/success/navigation": 0.9,
                                  "closed_loop/success/manipulation": rate,
                                  "closed_loop/phase_success/manipulation": rate}
            results.append(result)
    agg = study.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    diff = agg["configs"]["arm_focused"]["vs_baseline"]["closed_loop/success/manipulation"]
    assert diff[0] == pytest.approx(0.4)
    text = (tmp_path / "study.md").read_text()
    assert "## Closed loop in the demo world" in text and "50 episodes per seed" in text
    assert "| arm_focused | 0.900 ± 0.000 | 0.550 ± 0.071 | 0.275 ± 0.035 | n/a |" in text


def test_study_trains_every_run_once_and_skips_finished_ones(tmp_path, cache_dir, demo_root):
    overrides = {k: v for k, v in tf.tiny_overrides(demo_root).items()
                 if not k.startswith("train.total_steps") and k != "eval.every"}
    command = [sys.executable, "-m", "pi0_armfix.study", "--configs=uniform", "--seeds=2",
               "--steps=2", f"--workdir={tmp_path}", "--closed_loop_episodes=1",
               *[f"--override={k}={v}" for k, v in overrides.items()]]
    first = subprocess.run(command, capture_output=True, text=True, env=tf.env(cache_dir),
                           cwd=tf.REPO_ROOT)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "| uniform |" in first.stdout
    results = json.loads((tmp_path / "study.json").read_text())["runs"]
    assert [r["seed"] for r in results] == [0, 1]
    assert results[0]["metrics"] != results[1]["metrics"]  # the seed reaches the run
    assert results[0]["metrics"]["closed_loop/episodes"] == 1
    assert "## Closed loop in the demo world" in first.stdout
    again = subprocess.run(command, capture_output=True, text=True, env=tf.env(cache_dir),
                           cwd=tf.REPO_ROOT)
    assert again.returncode == 0 and "training" not in again.stdout
    assert again.stdout.count("| uniform |") == first.stdout.count("| uniform |")
