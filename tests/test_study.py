"""The study tool: configs x seeds -> tables with the spread over seeds, resumable."""

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix.configs import arm_focused
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.evaluation import intervals
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.study import aggregate, report
from pi0_armfix.study import curves as curves_lib
from pi0_armfix.study import main as study_main
from pi0_armfix.study import run as study_run

LAYOUT = {"preset": "b1k_r1pro", "action_dim": 32}


def _result(config, seed, arm_gain, base_skill=0.2, f1=0.5, arm_skill=None):
    arm_skill = arm_gain - 0.4 if arm_skill is None else arm_skill
    metrics = {}
    for g in ("left_arm", "right_arm"):
        metrics |= {f"motion_gain/{g}": arm_gain, f"skill/{g}": arm_skill,
                    f"persistence/motion_gain/{g}": 0.0, f"persistence/skill/{g}": 0.0}
    metrics |= {"motion_gain/base": 0.8, "skill/base": base_skill, "err/base": 1.0,
                "gripper_switch/f1": f1, "gripper_switch/precision": None,
                "persistence/motion_gain/base": 0.95, "persistence/skill/base": 0.0,
                "persistence/gripper_switch/f1": 0.0}
    return {"config": config, "seed": seed, "steps": 10, "layout": LAYOUT, "metrics": metrics}


def test_aggregate_reports_mean_and_spread_over_seeds_and_the_difference_to_the_baseline():
    results = [_result("uniform", s, g) for s, g in enumerate((0.0, 0.1, 0.2))]
    results += [_result("arm_delta", s, g, base_skill=0.19, f1=0.7, arm_skill=0.3 + 0.02 * s)
                for s, g in enumerate((0.5, 0.6, 0.7))]
    agg = aggregate.aggregate(results)
    delta = agg["configs"]["arm_delta"]
    assert delta["mean"]["arm_gain"] == pytest.approx(0.6)
    assert delta["std"]["arm_gain"] == pytest.approx(0.1)
    assert delta["headline"]["arm_gain"] == pytest.approx([0.5, 0.6, 0.7])  # per seed
    diff, low, high = delta["vs_baseline"]["arm_gain"]
    assert diff == pytest.approx(0.5) and low < diff < high
    assert delta["vs_baseline"]["base_skill"][0] == pytest.approx(-0.01)
    assert delta["comparison"] == "primary" and agg["primary"] == "arm_delta"
    assert delta["targets"] == {"arm_skill": True, "arm_gain": True, "base_skill": True,
                                "switch_f1": True}
    assert agg["configs"]["uniform"]["targets"]["arm_gain"] is False
    assert delta["mean"]["gripper_switch/precision"] is None  # no measurement, not a zero
    assert agg["anecdotal"] and agg["min_seeds"] == 3


def test_do_nothing_rows_come_from_the_runs_baseline_metrics():
    agg = aggregate.aggregate([_result("uniform", s, 0.1) for s in range(2)])
    persistence = agg["do_nothing"]["persistence"]
    assert persistence["motion_gain/base"] == 0.95 and persistence["arm_gain"] == 0.0


def test_arm_gain_target_follows_the_ceiling_where_the_ceiling_is_low():
    results = [_result("uniform", s, 0.0) for s in range(3)]
    results += [_result("fix", s, 0.4 + 0.01 * s) for s in range(3)]
    assert not aggregate.aggregate(results)["configs"]["fix"]["targets"]["arm_gain"]
    ceiling = {"motion_gain/left_arm": 0.55, "motion_gain/right_arm": 0.55}
    assert aggregate.aggregate(results, ceiling=ceiling)["configs"]["fix"]["targets"]["arm_gain"]


def test_secondary_comparisons_get_bonferroni_corrected_intervals():
    results = [_result(c, s, g + 0.05 * s) for c, g in (("uniform", 0.0), ("a", 0.3), ("b", 0.3),
                                                         ("c", 0.3)) for s in range(5)]
    agg = aggregate.aggregate(results, primary="a")
    primary, secondary = agg["configs"]["a"], agg["configs"]["b"]
    assert primary["confidence"] == 0.95 and secondary["confidence"] == pytest.approx(0.975)
    width = lambda c: c["vs_baseline"]["arm_gain"][2] - c["vs_baseline"]["arm_gain"][1]  # noqa
    assert width(secondary) > width(primary)


def test_the_secondary_family_holds_only_trained_configs_with_two_seeds_or_more():
    # uniform, the primary a, one secondary b; a one-seed screen and two lever variants
    results = [_result(c, s, g + 0.05 * s) for c, g in (("uniform", 0.0), ("a", 0.3),
                                                         ("b", 0.3)) for s in range(5)]
    results.append(_result("screen", 0, 0.3))
    levers = {k: [{**_result(f"a@eval.average_draws={k}", s, 0.35 + 0.05 * s + 0.03 * s * s),
                   "trained": "a"} for s in range(5)] for k in (2, 4)}
    agg = aggregate.aggregate(results + levers[2] + levers[4], primary="a")
    assert agg["configs"]["b"]["confidence"] == 0.95  # the only secondary: nothing to correct
    layout = ActionLayout.from_config(LAYOUT)
    trained = [r for r in results if r["config"] == "a"]
    for k in (2, 4):
        lever = agg["configs"][f"a@eval.average_draws={k}"]
        assert lever["comparison"] == "lever" and lever["confidence"] == pytest.approx(0.975)
        # its paired test holds at the lever family's level, wider than an uncorrected 95 %
        paired = lever["vs_trained"]["arm_gain"]
        assert paired == aggregate.lever_comparisons(levers[k], trained, layout, 0.975)["arm_gain"]
        uncorrected = aggregate.lever_comparisons(levers[k], trained, layout)["arm_gain"]
        assert paired[2] - paired[1] > uncorrected[2] - uncorrected[1]


def test_runs_scored_on_different_held_out_chunks_are_refused_naming_them():
    results = [_result(c, s, 0.1) for c in ("uniform", "fix") for s in range(2)]
    for r in results:
        r["episode_replicates"] = {"episodes": 20, "chunks": "a1" if r["config"] == "uniform"
                                   else "b2", **{k: [0.0] * 200 for k in aggregate.COMPARED}}
    with pytest.raises(ValueError, match=r"different held-out chunks \(chunks a1: uniform seed "
                                         r"0, uniform seed 1; chunks b2: fix seed 0, fix seed 1\)"):
        aggregate.aggregate(results)
    for r in results:
        r["episode_replicates"]["chunks"] = "a1"
    assert aggregate.aggregate(results)["episode_resampling"]["episodes"] == 20


def test_reports_are_written_and_name_every_config(tmp_path):
    results = [_result(c, s, 0.1 * s) for c in ("uniform", "arm_focused") for s in range(2)]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    assert "| uniform |" in text and "| arm_focused |" in text and "Welch t" in text
    assert "*persistence (do nothing)*" in text and "anecdotes" in text
    assert json.loads((tmp_path / "study.json").read_text())["baseline"] == "uniform"
    assert (tmp_path / "study.png").stat().st_size > 10_000


def _write_metrics_log(folder, seed, evaluations=(5, 10), timed=False):
    folder.mkdir(parents=True)
    records = [{"step": step, "loss": 2.0 / step + seed, **({"steps_per_sec": 4.0} if timed else {})}
               for step in (2, 4, 6, 8, 10)]
    records += [{"step": step, "skill/left_arm": -1.0 / step, "motion_gain/left_arm": 0.1}
                for step in evaluations]
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_curves_are_drawn_from_the_runs_metrics_logs_only_where_they_are_kept(tmp_path):
    results = [_result(c, s, 0.1 * s) for c in ("uniform", "arm_focused") for s in range(2)]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    assert not (tmp_path / "study_curves.png").exists()  # result.json files only
    for r in results:
        _write_metrics_log(study_run.run_folder(tmp_path, r["config"], r["seed"]), r["seed"])
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    assert (tmp_path / "study_curves.png").stat().st_size > 10_000


def test_curves_are_drawn_from_metrics_logs_with_timings(tmp_path):
    results = [_result(c, s, 0.1 * s) for c in ("uniform", "arm_focused") for s in range(2)]
    for r in results:
        _write_metrics_log(study_run.run_folder(tmp_path, r["config"], r["seed"]), r["seed"],
                           timed=True)
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    assert (tmp_path / "study_curves.png").stat().st_size > 10_000


def test_a_curve_is_taken_at_the_steps_every_seed_logged():
    runs = [[{"step": 5, "skill/left_arm": -1.0}, {"step": 10, "skill/left_arm": 0.5}],
            [{"step": 10, "skill/left_arm": 0.1}, {"step": 15, "skill/left_arm": 0.2}],
            [{"step": 10, "loss": 1.0}]]  # never evaluated: left out
    steps, values = curves_lib._curve_values(runs, "skill/left_arm")
    assert steps == [10]
    np.testing.assert_allclose(values, [[0.5], [0.1]])


def _closed_loop_result(config, seed, manipulation, outcomes=None):
    result = _result(config, seed, 0.1)
    result["metrics"] |= {"closed_loop/episodes": 50, "closed_loop/success/task": manipulation / 2,
                          "closed_loop/success/navigation": 0.9,
                          "closed_loop/success/manipulation": manipulation,
                          "closed_loop/phase_success/navigation": 0.95,
                          "closed_loop/phase_success/manipulation": manipulation,
                          "closed_loop/curve/2x/phase_success/manipulation": manipulation + 0.1,
                          "closed_loop/curve/2x/phase_success/navigation": 1.0}
    if outcomes is not None:
        result["closed_loop_episodes"] = outcomes
    return result


def test_closed_loop_success_gets_its_own_table_with_the_difference_to_the_baseline(tmp_path):
    results = [_closed_loop_result(config, seed, rate)
               for config, rates in (("uniform", (0.1, 0.2)), ("arm_focused", (0.5, 0.6)))
               for seed, rate in enumerate(rates)]
    agg = study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    diff = agg["configs"]["arm_focused"]["vs_baseline"]["closed_loop/phase_success/manipulation"]
    assert diff[0] == pytest.approx(0.4) and diff[1] > 0  # 2 seeds apart, no overlap
    text = (tmp_path / "study.md").read_text()
    assert "## Closed loop in the demo world" in text and "50 episodes per seed" in text
    assert ("| arm_focused | 0.950 ± 0.000 | 0.550 ± 0.071 | 0.900 ± 0.000 | 0.550 ± 0.071 | "
            "0.275 ± 0.035 | n/a | n/a | +0.000 [+0.000, +0.000] | +0.400 [") in text


def test_the_success_curve_is_tabled_per_tolerance_factor(tmp_path):
    results = [_closed_loop_result(c, s, 0.2) for c in ("uniform", "fix") for s in range(2)]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    assert "| config | navigation phases at 2x | manipulation phases at 2x |" in text
    assert "| fix | 1.000 ± 0.000 | 0.300 ± 0.000 |" in text


def test_closed_loop_targets_need_thirty_points_more_manipulation_with_an_interval_above_zero():
    results = [_closed_loop_result("uniform", s, r) for s, r in enumerate((0.1, 0.2))]
    results += [_closed_loop_result("fix", s, r) for s, r in enumerate((0.5, 0.6))]
    results += [_closed_loop_result("small", s, r) for s, r in enumerate((0.3, 0.4))]
    for r in results:
        r["metrics"]["gripper_switch/precision"] = 0.7
    met = {c: e["targets"] for c, e in aggregate.aggregate(results)["configs"].items()}
    assert met["fix"]["closed_loop_manipulation"] and met["fix"]["closed_loop_navigation"]
    assert met["fix"]["switch_precision"]
    assert not met["small"]["closed_loop_manipulation"]  # +0.2: below the 30 points


def test_closed_loop_outcomes_count_each_episodes_phases():
    detail = [{"task": False, "navigation": True, "manipulation": False, "phases": [
        {"kind": "navigation", "success": True}, {"kind": "manipulation", "success": True},
        {"kind": "navigation", "success": True}, {"kind": "manipulation", "success": False}]},
        {"task": True, "navigation": True, "manipulation": True, "phases": [
            {"kind": "navigation", "success": True}, {"kind": "manipulation", "success": True}]}]
    out = aggregate.closed_loop_outcomes(detail)
    assert out["success/task"] == [0, 1] and out["success/manipulation"] == [0, 1]
    assert out["phases/manipulation"] == [2, 1] and out["phase_successes/manipulation"] == [1, 1]


def test_closed_loop_replicates_are_the_rate_on_each_resample_of_the_episodes():
    outcomes = {"success/task": [1, 0, 0, 1], "success/manipulation": [1, 0, 0, 1],
                "phases/manipulation": [2, 2, 1, 1], "phase_successes/manipulation": [2, 1, 0, 1]}
    counts = intervals.episode_counts(4)
    rates = aggregate.closed_loop_replicates(outcomes, "phase_success/manipulation")
    expected = counts @ np.array([2, 1, 0, 1.0]) / (counts @ np.array([2, 2, 1, 1.0]))
    np.testing.assert_allclose(rates, expected)
    task = aggregate.closed_loop_replicates(outcomes, "success/task")
    assert task.mean() == pytest.approx(0.5, abs=0.05)


def _outcomes(rng, episodes=38, factors=("", "curve/2x/", "curve/4x/")):
    """Per-episode closed-loop outcomes at each tolerance, the task's success drawn at random."""
    out = {}
    for at in factors:
        s = rng.integers(0, 2, episodes).tolist()
        out |= {f"{at}success/task": s, f"{at}success/navigation": s,
                f"{at}success/manipulation": s, f"{at}phases/navigation": [2] * episodes,
                f"{at}phase_successes/navigation": [2] * episodes,
                f"{at}phases/manipulation": [2] * episodes, f"{at}phase_successes/manipulation": s}
    return out


def test_a_rate_at_a_looser_tolerance_is_resampled_from_that_tolerances_episodes():
    outcomes = _outcomes(np.random.default_rng(0), episodes=4)
    outcomes["curve/2x/success/task"] = [1, 1, 1, 1]
    outcomes["success/task"] = [0, 0, 0, 0]
    np.testing.assert_allclose(aggregate.closed_loop_replicates(outcomes, "curve/2x/success/task"),
                               1.0)
    np.testing.assert_allclose(aggregate.closed_loop_replicates(outcomes, "success/task"), 0.0)
    counts = intervals.episode_counts(4)
    expected = counts @ np.asarray(outcomes["curve/4x/phase_successes/manipulation"], float) / (
        counts @ np.full(4, 2.0))
    np.testing.assert_allclose(aggregate.closed_loop_replicates(
        outcomes, "curve/4x/phase_success/manipulation"), expected)


def _curve_lever_pair(seed, rng, task_2x, shift):
    """A trained run and its execution-lever variant, both measured in closed loop at 1x, 2x
    and 4x on the same 38 episodes; the variant's task success at 2x `shift` higher."""
    pair = []
    for config, rate in (("arm_focused", task_2x), ("arm_focused@eval.n_exec=8", task_2x + shift)):
        run = _closed_loop_result(config, seed, 0.5, _outcomes(rng))
        run["metrics"] |= {"closed_loop/curve/2x/success/task": rate,
                           "closed_loop/curve/4x/success/task": 0.9}
        pair.append(run)
    pair[1]["trained"] = "arm_focused"
    return pair


def test_a_lever_is_compared_at_every_tolerance_of_the_curve_with_its_interval(tmp_path):
    rng = np.random.default_rng(0)
    runs = [r for seed in range(5) for r in _curve_lever_pair(seed, rng, 0.2 + 0.1 * seed, 0.2)]
    agg = study_main.write_reports(runs, tmp_path, steps=10, command="python -m pi0_armfix.study")
    vs = agg["configs"]["arm_focused@eval.n_exec=8"]["vs_trained"]
    diff, low, high = vs["closed_loop/curve/2x/success/task"]
    assert diff == pytest.approx(0.2)
    assert low < 0.19 and high > 0.21  # every seed +0.2: the width is the episodes' own error
    assert vs["closed_loop/curve/4x/success/task"][0] == pytest.approx(0.0)
    text = (tmp_path / "study.md").read_text()
    assert "| config | navigation at 1x | manipulation at 1x | task at 1x | navigation at 2x |" \
        in text
    row = next(line for line in text.splitlines()
               if line.startswith("| arm_focused@eval.n_exec=8 | +"))
    assert "+0.200 [" in row


def test_a_run_without_its_episodes_at_a_looser_tolerance_gets_no_interval_there():
    rng = np.random.default_rng(1)
    runs = [r for seed in range(3) for r in _curve_lever_pair(seed, rng, 0.3, 0.1)]
    for run in runs:  # measured before the curve's episodes were kept
        run["closed_loop_episodes"] = {k: v for k, v in run["closed_loop_episodes"].items()
                                       if not k.startswith("curve/")}
    vs = aggregate.aggregate(runs)["configs"]["arm_focused@eval.n_exec=8"]["vs_trained"]
    assert "closed_loop/curve/2x/success/task" not in vs
    assert "closed_loop/success/task" in vs


def test_a_run_measured_before_the_curve_kept_its_episodes_is_measured_again():
    run = _closed_loop_result("uniform", 0, 0.5, _outcomes(np.random.default_rng(2)))
    assert study_run.run_has_closed_loop(run, 50)
    run["closed_loop_episodes"] = {k: v for k, v in run["closed_loop_episodes"].items()
                                   if not k.startswith("curve/4x/")}
    assert not study_run.run_has_closed_loop(run, 50)


def test_the_world_episodes_widen_the_closed_loop_interval():
    rng = np.random.default_rng(0)

    def outcomes():
        s = rng.integers(0, 2, 50).tolist()
        return {"success/task": s, "success/navigation": s, "success/manipulation": s,
                "phases/navigation": [2] * 50, "phase_successes/navigation": [2] * 50,
                "phases/manipulation": [2] * 50, "phase_successes/manipulation": s}
    plain = [_closed_loop_result(c, s, r) for c, rates in (("uniform", (0.1, 0.2, 0.15)),
                                                            ("fix", (0.5, 0.6, 0.55)))
             for s, r in enumerate(rates)]
    resampled = [{**r, "closed_loop_episodes": outcomes()} for r in plain]
    key = "closed_loop/phase_success/manipulation"
    narrow = aggregate.aggregate(plain)["configs"]["fix"]["vs_baseline"][key]
    wide = aggregate.aggregate(resampled)["configs"]["fix"]["vs_baseline"][key]
    assert narrow[0] == pytest.approx(wide[0])
    assert wide[2] - wide[1] > narrow[2] - narrow[1]


@pytest.mark.slow  # the slow lane: the study's processes (training, evaluation, closed loop)
def test_study_trains_every_run_once_and_skips_finished_ones(tmp_path, cache_dir, demo_root):
    overrides = {k: v for k, v in tf.tiny_overrides(demo_root).items()
                 if not k.startswith("train.total_steps") and k != "eval.every"}
    command = [sys.executable, "-m", "pi0_armfix.study",
               "--configs=uniform,uniform@eval.average_draws=2,uniform@eval.n_exec=1", "--seeds=2",
               "--steps=2", f"--workdir={tmp_path}", "--closed_loop_episodes=1",
               *[f"--override={k}={v}" for k, v in overrides.items()]]
    first = subprocess.run(command, capture_output=True, text=True, env=tf.env(cache_dir),
                           cwd=tf.REPO_ROOT)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "| uniform |" in first.stdout
    results = json.loads((tmp_path / "study.json").read_text())["runs"]
    assert [r["seed"] for r in results] == [0, 1, 0, 1, 0, 1]
    assert results[0]["metrics"] != results[1]["metrics"]  # the seed reaches the run
    assert all(r["metrics"]["closed_loop/episodes"] == 1 for r in results)
    assert all(r["closed_loop_episodes"]["curve/4x/success/task"] in ([0], [1]) for r in results)
    # the lever variant: its trained config's checkpoints sampled as the mean of 2 draws
    trained = study_run.run_folder(tmp_path, "uniform", 0)
    assert not (study_run.run_folder(tmp_path, "uniform@eval.average_draws=2", 0)
                / "checkpoints").exists()
    assert (trained / "eval" / "step_2" / "metrics_avg2.json").exists()
    assert (trained / "eval" / "step_2" / "closed_loop_1ep_avg2.json").exists()
    assert results[2]["trained"] == "uniform" and "episode_replicates" in results[2]
    assert results[2]["metrics"]["skill/base"] != results[0]["metrics"]["skill/base"]
    # an execution lever samples the trained chunks: their held-out metrics, its own closed loop
    assert not list((trained / "eval" / "step_2").glob("metrics_exec*"))
    assert (trained / "eval" / "step_2" / "closed_loop_1ep_exec1.json").exists()
    assert results[4]["metrics"]["skill/base"] == results[0]["metrics"]["skill/base"]
    assert "## Closed loop in the demo world" in first.stdout
    again = subprocess.run(command, capture_output=True, text=True, env=tf.env(cache_dir),
                           cwd=tf.REPO_ROOT)
    assert again.returncode == 0 and "runs finished; training" not in again.stdout
    assert again.stdout.count("| uniform |") == first.stdout.count("| uniform |")


@pytest.mark.slow  # the slow lane: the study's processes (training, evaluation, closed loop)
def test_the_closed_loop_studys_command_measures_its_variants_on_a_fresh_workdir(
        tmp_path, cache_dir, demo_root):  # noqa: F811
    overrides = {k: v for k, v in tf.tiny_overrides(demo_root).items()
                 if not k.startswith("train.total_steps") and k != "eval.every"}
    variant = "arm_focused@eval.n_exec=1@eval.temporal_ensemble=0.01@eval.deadband=torso=2"
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.study", f"--configs=arm_focused,{variant}",
         "--seeds=1", "--steps=2", "--execution=none", f"--workdir={tmp_path}",
         "--closed_loop_episodes=1", *[f"--override={k}={v}" for k, v in overrides.items()]],
        capture_output=True, text=True, env=tf.env(cache_dir), cwd=tf.REPO_ROOT)
    assert result.returncode == 0, result.stderr[-3000:]
    step = study_run.run_folder(tmp_path, "arm_focused", 0) / "eval" / "step_2"
    assert (step / "metrics_deadband-torso2.json").exists()  # the variant's, not the base's
    assert (step / "closed_loop_1ep_exec1_deadband-torso2_ens0.01.json").exists()
    runs = json.loads((tmp_path / "study.json").read_text())["runs"]
    assert runs[0]["execution"] == "every lever off"
    assert runs[1]["execution"] == ("n_exec 1, temporal_ensemble 0.01, deadband torso=2")
    assert f"- `{variant}`: n_exec 1, temporal_ensemble 0.01, deadband torso=2" in result.stdout


def test_report_only_tables_the_finished_runs_and_trains_nothing(tmp_path):
    for seed in (0, 1):
        folder = study_run.run_folder(tmp_path, "uniform", seed)
        folder.mkdir(parents=True)
        (folder / study_run.RESULT_FILE).write_text(json.dumps(_result("uniform", seed, 0.1)))
    results = study_run.run_study(["uniform", "arm_focused"], [0, 1, 2], 10, tmp_path,
                              closed_loop_episodes=50, train=False)
    assert [(r["config"], r["seed"]) for r in results] == [("uniform", 0), ("uniform", 1)]
    assert not study_run.run_folder(tmp_path, "arm_focused", 0).exists()


def test_finished_runs_without_the_closed_loop_get_it_once_in_the_pool(tmp_path, monkeypatch):
    for seed in (0, 1):
        folder = study_run.run_folder(tmp_path, "uniform", seed)
        folder.mkdir(parents=True)
        (folder / study_run.RESULT_FILE).write_text(json.dumps(_result("uniform", seed, 0.1)))
    measured = []

    outcomes = {f"{at}success/task": [1, 1, 1] for at in ("", "curve/2x/", "curve/4x/")}

    def fake(workdir, config, seed, steps, episodes):
        measured.append(f"seed_{seed}")
        return {"closed_loop/episodes": episodes}, outcomes
    monkeypatch.setattr(study_run, "closed_loop_metrics", fake)
    for _ in range(2):
        results = study_run.run_study(["uniform"], [0, 1], 10, tmp_path, parallel=2,
                                  closed_loop_episodes=3)
    assert sorted(measured) == ["seed_0", "seed_1"]
    assert all(r["closed_loop_episodes"] == outcomes for r in results)
    saved = study_run.load_result(study_run.run_folder(tmp_path, "uniform", 1))
    assert saved["metrics"]["closed_loop/episodes"] == 3


def test_closed_loop_failure_reasons_get_a_table_of_mean_fractions(tmp_path):
    results = []
    for seed, never_reached in enumerate((0.5, 0.7)):
        result = _result("uniform", seed, 0.1)
        result["metrics"] |= {"closed_loop/episodes": 10, "closed_loop/success/task": 0.0,
                              "closed_loop/failure/manipulation/never_reached": never_reached,
                              "closed_loop/failure/navigation/not_stopped": 1.0,
                              "closed_loop/gripper_switches/manipulation": 3.0}
        results.append(result)
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    header = next(line for line in text.splitlines() if "man: never_reached" in line)
    row = next(line for line in text.splitlines() if line.startswith("| uniform | ")
               and line.count("|") == header.count("|"))
    cells = dict(zip(header.split(" | "), row.split(" | ")))
    assert cells["man: never_reached"] == "0.60" and cells["nav: not_stopped"] == "1.00"
    assert cells["nav: heading_off"] == "n/a"


def _with_replicates(result, spread, rng):
    """`result` with episode replicates spread around its own headline numbers."""
    summary = aggregate.run_summary(result["metrics"], ActionLayout.from_config(LAYOUT))
    result["episode_replicates"] = {"episodes": 20, **{
        k: list(summary[k] + spread * rng.standard_normal(200)) for k in aggregate.COMPARED}}
    return result


def test_intervals_widen_by_the_held_out_episodes_sampling_error_when_every_run_has_it():
    rng = np.random.default_rng(0)
    plain = [_result(c, s, g + 0.01 * s) for c, g in (("uniform", 0.0), ("fix", 0.3))
             for s in range(5)]
    resampled = [_with_replicates(dict(r), 0.2, rng) for r in plain]
    narrow = aggregate.aggregate(plain)["configs"]["fix"]["vs_baseline"]["arm_gain"]
    agg = aggregate.aggregate(resampled)
    wide = agg["configs"]["fix"]["vs_baseline"]["arm_gain"]
    assert wide[0] == narrow[0] and wide[2] - wide[1] > 2 * (narrow[2] - narrow[1])
    assert agg["episode_resampling"] == {"episodes": 20, "replicates": 200}
    assert aggregate.aggregate(resampled[:-1] + plain[-1:])["episode_resampling"] is None


def test_the_report_says_which_errors_its_intervals_hold(tmp_path):
    rng = np.random.default_rng(0)
    results = [_with_replicates(_result(c, s, 0.1 * s), 0.1, rng)
               for c in ("uniform", "fix") for s in range(2)]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    assert "held-out episodes' sampling error (20 episodes" in (tmp_path / "study.md").read_text()
    study_main.write_reports(results[:-1] + [_result("fix", 1, 0.1)], tmp_path, steps=10,
                        command="python -m pi0_armfix.study")
    assert "the seeds' spread only" in (tmp_path / "study.md").read_text()


def test_episode_replicates_on_a_resample_of_every_episode_once_are_the_evaluations_numbers(
        monkeypatch):
    layout = ActionLayout.preset("b1k_r1pro")
    rng = np.random.default_rng(1)
    true = rng.normal(size=(6, 5, 23))
    true[..., [14, 22]] = np.sign(rng.normal(size=(6, 5, 2)))
    draws = true + 0.3 * rng.normal(size=(3, *true.shape))
    persistence = np.repeat(true[:, :1], 5, axis=1)
    valid = np.ones((6, 5), bool)
    kwargs = dict(layout=layout, gripper_groups=("left_gripper", "right_gripper"),
                  gripper_threshold=np.zeros(23), switch_tolerance=1)

    def all_sums(chunks, samples):
        return {**eval_metrics.chunk_sums(chunks, true, valid, **kwargs),
                **eval_metrics.energy_sums(samples, true, valid, layout=layout)}

    policy, held = all_sums(draws[0], draws), all_sums(persistence, persistence[None])
    mean = eval_metrics.chunk_sums(draws.mean(0), true, valid, **kwargs)
    sums = {"episode": np.array([0, 0, 1, 1, 2, 2]),
            **{f"policy/{k}": v for k, v in policy.items()},
            **{f"mean_of_draws/{k}": v for k, v in mean.items()},
            **{f"persistence/{k}": v for k, v in held.items()}}
    monkeypatch.setattr(intervals, "episode_counts", lambda e: np.ones((2, e)))
    replicates = aggregate.episode_replicates(sums, layout)

    def measured(s):
        return eval_metrics.metrics_from_sums({k: v.sum() for k, v in s.items()}, layout)

    metrics, reference = measured(policy), measured(held)
    metrics |= eval_metrics.skill_scores(metrics, reference, layout)
    metrics |= {f"mean_of_draws/{k}": v for k, v in eval_metrics.skill_scores(
        measured(mean), reference, layout).items()}
    expected = aggregate.run_summary(metrics, layout)
    assert np.isfinite(expected["arm_energy_skill"])
    assert expected["arm_skill_mean_of_draws"] > expected["arm_skill"]
    assert replicates["episodes"] == 3
    for k in aggregate.COMPARED:
        assert replicates[k] == pytest.approx([expected[k]] * 2)


SLEEPING_STUDY = """
import os, sys
from pathlib import Path
from pi0_armfix.study import main as study_main
from pi0_armfix.study import run as study_run

def sleeper(config, seed, steps, folder, overrides, evaluations):  # a slow training run
    return [sys.executable, "-c", "import os, time; open(%r, 'w').write(str(os.getpid())); "
            "time.sleep(120)" % str(Path(folder) / "pid")]

study_run.train_command = sleeper
sys.argv = ["study", "--configs=uniform,arm_focused", "--seeds=2", "--steps=3",
            "--workdir=" + sys.argv[1], "--closed_loop_episodes=0"]
study_main.cli()
"""


@pytest.mark.slow  # several processes: the slow lane
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_or_kill_stops_the_study_and_its_children_and_says_how_to_resume(tmp_path,
                                                                                 signum,
                                                                                 cache_dir):  # noqa: F811
    script = tmp_path / "sleeping_study.py"
    script.write_text(SLEEPING_STUDY)
    workdir = tmp_path / "study"
    process = subprocess.Popen([sys.executable, str(script), str(workdir)], cwd=tf.REPO_ROOT,
                               env=tf.env(cache_dir), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while (not list(workdir.glob("*/seed_*/pid")) and time.monotonic() < deadline
           and process.poll() is None):
        time.sleep(0.1)
    found = list(workdir.glob("*/seed_*/pid"))
    if not found:
        process.kill()
        pytest.fail(f"the study started no run: {process.communicate()[1][-3000:]}")
    [pid_file] = found
    time.sleep(0.2)  # the pid is written before the child sleeps
    child = int(pid_file.read_text())
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode != 0
    assert stderr.strip().splitlines()[-1] == (
        "pi0_armfix.study: stopped; 0 of 4 runs finished. Rerun the same command to go on: "
        "finished runs are kept, an interrupted one resumes from its last checkpoint")
    assert "Traceback" not in stderr
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)
    assert len(list(workdir.glob("*/seed_*/pid"))) == 1  # no run started after the signal


def test_a_torn_result_json_is_named_with_the_fix(tmp_path):
    folder = study_run.run_folder(tmp_path, "uniform", 0)
    folder.mkdir(parents=True)
    (folder / study_run.RESULT_FILE).write_text('{"config": "uniform", "se')
    with pytest.raises(ValueError, match=r"uniform/seed_0/result.json is not JSON .*delete it"):
        study_run.load_result(folder)


def test_a_config_with_overrides_of_its_own_passes_them_to_its_runs_only(tmp_path):
    assert study_run.parse_config("arm_focused:b1k@data.video_access=random@seed=3") == (
        "arm_focused", "b1k", ["data.video_access=random", "seed=3"])
    command = study_run.train_command("arm_focused@data.video_access=random", 2, 10, tmp_path,
                                  ["data.root=/d"])
    assert "--config=configs/arm_focused.py" in command
    assert command[-2:] == ["--config.data.root=/d", "--config.data.video_access=random"]
    plain = study_run.train_command("arm_focused", 2, 10, tmp_path, ["data.root=/d"])
    assert plain[-1] == "--config.data.root=/d"
    assert (study_run.run_folder(tmp_path, "arm_focused@data.root=/a/b", 0)
            == tmp_path / "arm_focused@data.root=_a_b" / "seed_0")


def test_a_config_naming_its_own_total_steps_is_finished_at_those_steps(tmp_path):
    config = "arm_focused@loss.flow_samples=1@train.total_steps=4000"
    assert study_run.run_steps(config, 2000) == 4000
    assert study_run.run_steps("arm_focused@loss.flow_samples=1", 2000) == 2000
    folder = study_run.run_folder(tmp_path, config, 0)
    folder.mkdir(parents=True)
    (folder / study_run.RESULT_FILE).write_text(json.dumps(
        {"config": config, "seed": 0, "steps": 4000, "layout": {}, "metrics": {}}))
    with pytest.raises(ValueError, match="no finished run"):  # the 4000-step run is finished...
        study_run.run_study(["arm_focused"], [0], 2000, tmp_path, train=False)
    finished = study_run.run_study([config], [0], 2000, tmp_path, train=False)
    assert [r["steps"] for r in finished] == [4000]  # ... and not refused as "not --steps"


def test_the_closed_loop_is_proportionate_to_the_training_budget_and_announced():
    assert study_run.default_closed_loop_episodes(1500) == 12
    assert study_run.default_closed_loop_episodes(6000) == 50
    assert study_run.default_closed_loop_episodes(100) == 10
    line = study_run.closed_loop_plan(runs=20, episodes=50)
    assert "50 episodes x 3 tolerances x 20 runs = 3000 episodes of the demo world" in line


def test_the_learning_curve_table_has_a_row_per_config_and_evaluated_step():
    layout = ActionLayout.preset("b1k_r1pro")
    groups = list(layout.group_names)

    def record(step, value):
        return {"step": step, **{f"skill/{g}": value for g in groups},
                **{f"mean_of_draws/skill/{g}": value + 0.5 for g in groups},
                "gripper_switch/f1": 0.25}

    def timing(step, steps_per_sec):
        return {"step": step, "loss": 1.0, "steps_per_sec": steps_per_sec}

    curves = {"arm_focused": [[timing(500, 5.0), record(500, -0.2), timing(1000, 10.0),
                               record(1000, 0.1)],
                              [timing(500, 2.5), record(500, -0.4), timing(1000, 5.0),
                               record(1000, 0.3)]]}
    table = curves_lib.curve_table(curves, {"groups": groups,
                                              "arm_groups": ["left_arm", "right_arm"]})
    rows = [line for line in table if line.startswith("| arm_focused")]
    assert len(rows) == 2
    # 100 s and 200 s of training to step 500 -> 2.5 min; 150 s and 300 s to step 1000 -> 3.8
    # the sample std (ddof 1) as in every study table: |-0.2 - -0.4| / sqrt(2)
    assert rows[0].startswith("| arm_focused | 500 | 2 | 2.5 | -0.30 ± 0.14")
    assert rows[1].startswith("| arm_focused | 1000 | 2 | 3.8 |")
    assert "+0.70 ± 0.14" in rows[1] and rows[1].endswith("+0.25 ± 0.00 |")


def test_training_seconds_sum_the_logged_windows_and_skip_evaluation_records():
    records = [{"step": 25, "steps_per_sec": 0.5}, {"step": 50, "steps_per_sec": 5.0},
               {"step": 50, "skill/base": 0.1}, {"step": 75, "steps_per_sec": 25.0}]
    assert curves_lib.training_seconds(records) == {25: 50.0, 50: 55.0, 75: 56.0}
    assert curves_lib.training_seconds([{"step": 50, "skill/base": 0.1}]) == {}


def test_minutes_at_an_evaluation_between_log_records_are_interpolated():
    seconds = {25: 60.0, 50: 120.0}
    assert curves_lib.minutes_at(seconds, 40) == pytest.approx(1.6)
    assert curves_lib.minutes_at(seconds, 50) == 2.0
    assert math.isnan(curves_lib.minutes_at({}, 50))


def test_a_lever_variant_is_its_config_less_the_inference_levers():
    config = ("arm_focused@eval.average_draws=4@model.augment.jitter_p=0@eval.temperature=0.5"
              "@eval.n_exec=4@eval.group_draws=base=4+torso=8")
    assert study_run.trained_config(config) == "arm_focused@model.augment.jitter_p=0"
    assert study_run.inference_levers(config) == {"average_draws": "4", "temperature": "0.5",
                                                  "n_exec": "4", "group_draws": "base=4+torso=8"}
    assert study_run.lever_args(config) == ["--average_draws=4", "--temperature=0.5",
                                            "--n_exec=4", "--group_draws=base=4+torso=8"]
    assert study_run.trained_config("arm_focused@eval.every=100") == "arm_focused@eval.every=100"
    assert study_run.lever_args("arm_focused") == []


def test_a_lever_whose_value_is_a_list_stays_one_config_of_the_comma_separated_flag():
    parts = "arm_focused,arm_focused@eval.gripper_hysteresis=0.9,-0.98,uniform,".split(",")
    assert study_run.config_names(parts) == [
        "arm_focused", "arm_focused@eval.gripper_hysteresis=0.9,-0.98", "uniform"]
    assert study_run.trained_config("arm_focused@eval.gripper_hysteresis=0.9,-0.98") == (
        "arm_focused")


def test_a_list_of_names_as_an_overrides_value_stays_one_config():
    from pi0_armfix import console
    parts = ("uniform,arm_focused@eval.gripper_groups=left_gripper,right_gripper,uniform:g1"
             .split(","))
    assert study_run.config_names(parts, console.config_names()) == [
        "uniform", "arm_focused@eval.gripper_groups=left_gripper,right_gripper", "uniform:g1"]


def test_a_lever_variant_finds_its_files_by_the_levers_it_changes_on_its_run(tmp_path):
    config = arm_focused.get_config()
    config.eval.update(dict(n_exec=8, temporal_ensemble=0.01, group_draws="base=4+torso=4"))
    (tmp_path / "config.json").write_text(json.dumps(config.to_dict()))
    assert study_run.lever_tag("arm_focused", tmp_path, closed_loop=True) == ""
    assert study_run.lever_tag("arm_focused@eval.temporal_ensemble=0", tmp_path,
                               closed_loop=True) == "_ens0"
    assert study_run.lever_tag("arm_focused@eval.deadband=base=0.4", tmp_path) == \
        "_deadband-base0.4"


def test_a_lever_variant_of_a_study_without_execution_is_measured_on_a_fresh_workdir(tmp_path):
    config = arm_focused.get_config()  # as the study trains it: --config.eval.execution=none
    config.eval.execution = "none"
    (tmp_path / "config.json").write_text(json.dumps(config.to_dict()))
    adopted = ("arm_focused@eval.n_exec=8@eval.temporal_ensemble=0.01"
               "@eval.group_draws=base=4+torso=8@eval.deadband=torso=2")
    assert study_run.lever_tag(adopted, tmp_path, closed_loop=True) == (
        "_exec8_draws-base4-torso8_deadband-torso2_ens0.01")
    assert study_run.lever_tag("arm_focused@eval.execution=adopted", tmp_path) == (
        "_draws-base4-torso8_deadband-torso2")
    assert study_run.lever_tag("arm_focused", tmp_path, closed_loop=True) == ""


def _finished_run(config, seed, workdir):
    """A run's result as `run_one` leaves it: written into its folder, and returned."""
    result = _result(config, seed, 0.1)
    folder = study_run.run_folder(workdir, config, seed)
    folder.mkdir(parents=True)
    (folder / study_run.RESULT_FILE).write_text(json.dumps(result))
    return result


def test_a_lever_variant_is_measured_after_its_trained_runs_and_trains_nothing(
        tmp_path, monkeypatch):
    variant = "uniform@eval.average_draws=4"
    calls = []

    def fake_run_one(config, seed, steps, workdir, *_):
        trained = study_run.trained_config(config)
        if trained != config:  # the checkpoints it needs exist when it is measured
            assert study_run.load_result(study_run.run_folder(workdir, trained, seed))
        calls.append((config, seed))
        return _finished_run(config, seed, workdir)
    monkeypatch.setattr(study_run, "run_one", fake_run_one)
    results = study_run.run_study([variant, "uniform"], [0, 1], 10, tmp_path, parallel=2)
    assert sorted(calls[:2]) == [("uniform", 0), ("uniform", 1)]
    assert sorted(calls[2:]) == [(variant, 0), (variant, 1)]
    assert [r["config"] for r in results] == [variant, variant, "uniform", "uniform"]


def test_a_lever_variant_takes_a_free_slot_while_another_seed_still_trains(tmp_path, monkeypatch):
    variant, measured = "uniform@eval.average_draws=4", threading.Event()

    def fake_run_one(config, seed, steps, workdir, *_):
        if config == "uniform" and seed == 1:  # the last training waits for seed 0's variant
            assert measured.wait(timeout=30), "seed 0's variant waited for every training"
        if config == variant:
            measured.set()
        return _finished_run(config, seed, workdir)
    monkeypatch.setattr(study_run, "run_one", fake_run_one)
    results = study_run.run_study(["uniform", variant], [0, 1], 10, tmp_path, parallel=2)
    assert [(r["config"], r["seed"]) for r in results] == [
        ("uniform", 0), ("uniform", 1), (variant, 0), (variant, 1)]


def test_a_lever_variant_without_its_trained_config_is_named_before_any_run(tmp_path):
    with pytest.raises(ValueError, match=r"checkpoints of \['arm_focused'\]: add them"):
        study_run.run_study(["uniform", "arm_focused@eval.temperature=0.5"], [0], 10, tmp_path)
    assert not any(tmp_path.iterdir())


def test_the_learning_curves_leave_lever_variants_out(tmp_path):
    for config in ("uniform", "uniform@eval.average_draws=4"):
        folder = study_run.run_folder(tmp_path, config, 0)
        folder.mkdir(parents=True)
        (folder / "metrics.jsonl").write_text(
            json.dumps({"step": 5, "loss": 1.0, "steps_per_sec": 1.0}) + "\n"
            + json.dumps({"step": 5, "skill/base": 0.1}) + "\n"
            + json.dumps({"step": 10, "skill/base": 0.2}) + "\n")
    results = [_result(c, 0, 0.1) for c in ("uniform", "uniform@eval.average_draws=4")]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    rows = [line for line in (tmp_path / "study.md").read_text().splitlines()
            if line.startswith(("| uniform | 5 |", "| uniform@eval.average_draws=4 | 5 |"))]
    assert [row.split(" | ")[0] for row in rows] == ["| uniform"]


def _lever_pair(seed, arm_skill, shift, noise=None):
    """A trained run and its lever variant on the same checkpoint: the variant's arms' skill
    `shift` higher; `noise` `[B]`: held-out replicates' deviations, shared by both."""
    trained = _result("arm_focused", seed, 0.5, arm_skill=arm_skill)
    variant = {**_result("arm_focused@eval.average_draws=4", seed, 0.5,
                         arm_skill=arm_skill + shift), "trained": "arm_focused"}
    if noise is not None:
        for run in (trained, variant):
            summary = aggregate.run_summary(run["metrics"], ActionLayout.from_config(LAYOUT))
            run["episode_replicates"] = {"episodes": 20, **{
                k: list(summary[k] + noise) for k in aggregate.COMPARED}}
    return trained, variant


def test_a_lever_variant_is_compared_with_its_trained_config_seed_for_seed():
    # seeds far apart, the lever +0.1 on every one: Welch cannot tell, the paired interval can
    runs = [run for seed, skill in enumerate((-0.5, 0.0, 0.4, 0.9, 1.3))
            for run in _lever_pair(seed, skill, 0.1)]
    agg = aggregate.aggregate([_result("uniform", s, 0.1) for s in range(5)] + runs)
    variant = agg["configs"]["arm_focused@eval.average_draws=4"]
    assert variant["trained"] == "arm_focused"
    assert variant["vs_trained"]["arm_skill"] == pytest.approx((0.1, 0.1, 0.1))
    assert "vs_trained" not in agg["configs"]["arm_focused"]
    welch = intervals.welch_interval(
        variant["headline"]["arm_skill"], agg["configs"]["arm_focused"]["headline"]["arm_skill"])
    assert welch[1] < 0 < welch[2]


def test_held_out_episode_noise_shared_by_a_lever_pair_cancels_and_its_own_widens():
    rng = np.random.default_rng(0)
    shared = rng.normal(0, 0.2, 200)
    runs = [run for seed in range(5) for run in _lever_pair(seed, 0.1 * seed, 0.1, shared)]
    paired = aggregate.lever_comparisons(runs[1::2], runs[::2], ActionLayout.from_config(LAYOUT))
    assert paired["arm_skill"] == pytest.approx((0.1, 0.1, 0.1))
    for variant in runs[1::2]:  # the variant's replicates now noisy on their own
        variant["episode_replicates"]["arm_skill"] = list(
            np.asarray(variant["episode_replicates"]["arm_skill"]) + rng.normal(0, 0.2, 200))
    wide = aggregate.lever_comparisons(runs[1::2], runs[::2], ActionLayout.from_config(LAYOUT))
    assert wide["arm_skill"][0] == pytest.approx(0.1)
    assert wide["arm_skill"][1] < 0.1 - 0.05 and wide["arm_skill"][2] > 0.1 + 0.05


def test_the_report_tables_lever_variants_against_their_trained_config(tmp_path):
    runs = [run for seed in range(2) for run in _lever_pair(seed, 0.2 * seed, 0.1)]
    study_main.write_reports(runs, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    assert "## Inference levers against the trained config they sample (paired)" in text
    row = next(line for line in text.splitlines()
               if line.startswith("| arm_focused@eval.average_draws=4 | arm_focused |"))
    assert "+0.100 [+0.100, +0.100]" in row


def test_the_report_names_the_configs_with_fewer_seeds_than_a_result_needs(tmp_path):
    results = ([_result("uniform", s, 0.1 * s) for s in range(5)]
               + [_result("arm_focused", 0, 0.5)])
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    assert text.startswith("# Study: 2 configs x 1-5 seeds, 10 steps")
    assert "Fewer than 5 seeds for arm_focused (1): their intervals" in text


def test_a_study_kept_as_its_report_alone_is_reported_again_from_its_study_json(tmp_path):
    results = [_result(c, s, 0.1 * s) for c in ("uniform", "arm_focused") for s in range(2)]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    curves = ["", f"{curves_lib.CURVES_HEADING} (held-out skill)", "", "| config | step |",
              "| uniform | 10 |"]
    with open(tmp_path / "study.md", "a") as study_md:
        study_md.write("\n".join(curves) + "\n")
    again = study_run.run_study(["uniform", "arm_focused"], [0, 1], 10, tmp_path, train=False)
    assert again == results
    study_main.write_reports(again, tmp_path, steps=10, command="again")
    text = (tmp_path / "study.md").read_text()
    assert text.endswith("\n".join(curves) + "\n") and "`again`" in text


def test_a_study_on_other_data_than_the_demo_has_no_closed_loop_by_default():
    assert study_main.on_other_data(["uniform", "arm_focused"], []) == ""
    assert study_main.on_other_data(["uniform"], ["data.root="]) == ""
    assert study_main.on_other_data(["uniform"], ["data.root=/data/g1"]) == (
        "--override=data.root=/data/g1")
    assert "the config arm_focused:g1" in study_main.on_other_data(["uniform:g1", "arm_focused:g1"],
                                                                  [])


@pytest.mark.parametrize("content", ["[]", "{}", '{"steps": 6}', '"text"'])
def test_a_result_json_of_the_wrong_shape_is_one_error_naming_the_file_and_the_fix(
        tmp_path, content):
    folder = tmp_path / "uniform" / "seed_0"
    folder.mkdir(parents=True)
    (folder / "result.json").write_text(content)
    with pytest.raises(ValueError, match=r"result.json (holds|lacks) .*delete it and rerun"):
        study_run.run_study(["uniform"], [0], 6, tmp_path, train=False)


def test_a_lever_out_of_range_is_refused_before_any_run_trains(tmp_path):
    done = subprocess.run([sys.executable, "-m", "pi0_armfix.study",
                           "--configs=uniform,uniform@eval.average_draws=0", "--seeds=1",
                           "--steps=2", f"--workdir={tmp_path / 'study'}"],
                          capture_output=True, text=True, timeout=300, cwd=tf.REPO_ROOT,
                          env=dict(os.environ, PYTHONPATH=str(tf.REPO_ROOT)))
    assert done.returncode != 0
    assert ("--configs uniform@eval.average_draws=0: average_draws = 0 (eval.average_draws or "
            "--average_draws) must be a whole number >= 1" in done.stderr)
    assert not (tmp_path / "study").exists()


def test_an_override_of_a_config_that_names_no_key_is_refused_before_any_run(tmp_path):
    done = subprocess.run([sys.executable, "-m", "pi0_armfix.study", "--configs=uniform@=4",
                           "--seeds=1", "--steps=2", f"--workdir={tmp_path / 'study'}"],
                          capture_output=True, text=True, timeout=300, cwd=tf.REPO_ROOT,
                          env=dict(os.environ, PYTHONPATH=str(tf.REPO_ROOT)))
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert "--configs ['uniform@=4']: what follows a config's '@' must be key=value" in done.stderr
    assert not (tmp_path / "study").exists()


G1 = {"preset": "g1_inspire", "action_dim": 32}
G1_GROUPS = ("left_arm", "right_arm", "left_hand", "right_hand")


def _g1_result(config, seed, skills, noise=None):
    """A G1 run: each group's skill (single draw and mean of draws), no base, no gripper."""
    metrics = {}
    for g, skill in zip(G1_GROUPS, skills):
        metrics |= {f"skill/{g}": skill, f"mean_of_draws/skill/{g}": skill + 0.1,
                    f"motion_gain/{g}": 0.5, f"persistence/skill/{g}": 0.0,
                    f"persistence/motion_gain/{g}": 0.0}
    result = {"config": config, "seed": seed, "steps": 10, "layout": G1, "metrics": metrics}
    if noise is not None:
        keys = aggregate.group_keys(ActionLayout.from_config(G1))
        result["episode_replicates"] = {"episodes": 20, **{k: [0.0] * 200 for k in
                                                          aggregate.COMPARED},
                                        **{k: list(metrics[k] + noise) for k in keys}}
    return result


def test_each_group_is_compared_with_the_baseline_and_targets_of_absent_groups_are_na(tmp_path):
    results = [_g1_result("uniform:g1", s, (-40.0 + s, -0.4, -17.0, -0.4)) for s in range(3)]
    results += [_g1_result("arm_focused:g1", s, (-1.0 - 0.1 * s, -0.3, -0.5, -0.2 + 0.01 * s))
                for s in range(3)]
    agg = aggregate.aggregate(results)
    fix = agg["configs"]["arm_focused:g1"]
    diff, low, high = fix["vs_baseline_groups"]["skill/left_arm"]
    assert diff == pytest.approx(-1.1 - (-39.0)) and low < diff < high
    assert fix["vs_baseline_groups"]["mean_of_draws/skill/right_hand"][0] == pytest.approx(0.21)
    assert fix["targets"]["base_skill"] is None and fix["targets"]["switch_f1"] is None
    study_main.write_reports(results, tmp_path, steps=10, command="study")
    text = (tmp_path / "study.md").read_text()
    assert "## Against `uniform:g1`, per group" in text
    assert "| arm_focused:g1 | single | +37.900 [" in text
    assert "| n/a | n/a |" in text  # base skill and switch F1 targets: no base, no gripper


def test_per_group_intervals_widen_by_the_held_out_episodes_resamples():
    rng = np.random.default_rng(0)

    def runs(resampled):
        noise = (lambda: rng.normal(0, 0.5, 200)) if resampled else (lambda: None)  # noqa: E731
        return ([_g1_result("uniform:g1", s, (-40.0 + s, -0.4 + 0.1 * s, -17.0, -0.4), noise())
                 for s in range(3)]
                + [_g1_result("fix:g1", s, (-1.0 - 0.1 * s, -0.3 + 0.1 * s, -0.5, -0.2), noise())
                   for s in range(3)])

    seeds_only = aggregate.aggregate(runs(False))["configs"]["fix:g1"]
    both = aggregate.aggregate(runs(True))["configs"]["fix:g1"]
    width = lambda c: c["vs_baseline_groups"]["skill/right_arm"][2] - c[  # noqa: E731
        "vs_baseline_groups"]["skill/right_arm"][1]
    assert both["groups_resampled"] and not seeds_only["groups_resampled"]
    assert width(both) > width(seeds_only)


def test_each_groups_skill_gets_its_interval_against_holding(tmp_path):
    rng = np.random.default_rng(0)
    results = [_g1_result("uniform:g1", s, (-40.0, -0.4, -17.0, -0.4), rng.normal(0, 0.1, 200))
               for s in range(5)]
    results += [_g1_result("fix:g1", s, (-1.0, 0.2 + 0.02 * s, -0.5, 0.01 * s - 0.02),
                           rng.normal(0, 0.1, 200)) for s in range(5)]
    fix = aggregate.aggregate(results)["configs"]["fix:g1"]
    mean, low, high = fix["group_intervals"]["skill/right_arm"]
    assert mean == pytest.approx(0.24) and 0 < low < mean < high  # above holding
    mean, low, high = fix["group_intervals"]["skill/right_hand"]
    assert low < 0 < high  # cannot tell from holding
    seeds_only = intervals.mean_interval([0.2 + 0.02 * s for s in range(5)])
    assert high - low > 0 and (fix["group_intervals"]["skill/right_arm"][2]
                               - fix["group_intervals"]["skill/right_arm"][1]
                               > seeds_only[2] - seeds_only[1])  # the episodes widen it
    study_main.write_reports(results, tmp_path, steps=10, command="study")
    text = (tmp_path / "study.md").read_text()
    assert "## Each group against holding the previous action" in text
    assert "| fix:g1 | single | -1.000 [" in text


def test_a_skill_axis_shows_values_far_below_doing_nothing_on_a_symlog_scale():
    fig, (far, near) = report.plt.subplots(1, 2)
    far.plot([1, 2], [-43.7, -0.1])
    near.plot([1, 2], [-0.7, 0.2])
    report.fit_skill_axis(far, top=1.05)
    report.fit_skill_axis(near, top=1.05)
    assert far.get_yscale() == "symlog" and far.get_ylim()[0] <= -43.7
    assert near.get_yscale() == "linear" and near.get_ylim()[0] <= -0.7
    assert far.get_ylim()[1] == near.get_ylim()[1] == 1.05
    report.plt.close(fig)


def _printed_levels(text):
    """`{config: level}` of study.md's comparison table (its `comparison (level%)` column)."""
    start = text.index("## Against `")
    rows = [line.split(" | ") for line in text[start:].splitlines()
            if line.startswith("| ") and "%)" in line]
    return {row[0].removeprefix("| "): float(row[1].rsplit("(", 1)[1].rstrip("%)")) / 100
            for row in rows}


def test_every_printed_interval_level_is_the_level_computed(tmp_path):
    results = [_result(c, s, g + 0.05 * s) for c, g in (("uniform", 0.0), ("a", 0.3),
                                                         ("b", 0.3), ("c", 0.3)) for s in range(5)]
    primary = "a@eval.average_draws=4"  # a lever variant as the study's question
    results += [{**_result(f"a@eval.average_draws={k}", s, 0.35 + 0.05 * s), "trained": "a"}
                for k in (2, 4, 8) for s in range(5)]
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study",
                             primary=primary)
    computed = {name: c["confidence"] for name, c in
                json.loads((tmp_path / "study.json").read_text())["configs"].items()
                if c["comparison"] != "baseline"}
    text = (tmp_path / "study.md").read_text()
    assert _printed_levels(text) == pytest.approx(computed, abs=5e-4)
    assert computed[primary] == 0.95  # the primary at 95 %, though a lever variant
    assert computed["a@eval.average_draws=2"] == pytest.approx(0.975)  # two other levers
    assert computed["b"] == pytest.approx(1 - 0.05 / 3)  # three secondary: a, b, c
    assert f"the primary comparison, `{primary}`, at 95.0%" in text
    assert "95 % interval per cell, uncorrected" in text


def test_with_one_held_out_episode_the_report_says_its_intervals_hold_the_seeds_spread_alone(
        tmp_path):
    rng = np.random.default_rng(0)
    results = [_with_replicates(_result(c, s, 0.1 * s), 0.0, rng)
               for c in ("uniform", "fix") for s in range(2)]
    for result in results:
        result["episode_replicates"]["episodes"] = 1
    study_main.write_reports(results, tmp_path, steps=10, command="python -m pi0_armfix.study")
    text = (tmp_path / "study.md").read_text()
    assert "one held-out episode gives no sampling error" in text
    assert "(1 episodes" not in text
