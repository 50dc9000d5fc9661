"""The closed-loop calibration rows and success curves: reproducible, ordered as they must be."""

import dataclasses
import json

import numpy as np
import pytest

from pi0_armfix.sim import env as env_lib
from pi0_armfix.sim import rollout
from pi0_armfix.sim import world as world_lib
from pi0_armfix.tools import closed_loop_calibration as calibration

QUICK = dataclasses.replace(world_lib.DemoSpec(seed=env_lib.EVAL_SEED), navigation_seconds=12.0,
                            manipulation_seconds=10.0)
PRESS_TASK = 2  # radio: one navigation, one press


def _curves(noise):
    rows = calibration.calibration_rows(np.full(23, noise), hold=8)
    return calibration.calibrate(rows, episodes=[PRESS_TASK], factors=(1, 4), progress=False,
                                 spec=QUICK)


@pytest.fixture(scope="module")
def curves():
    return _curves(0.3)


@pytest.mark.slow  # two calibrations of the demo world
def test_calibration_rows_are_reproducible(curves):
    assert json.dumps(_curves(0.3)) == json.dumps(curves)  # NaN (nothing succeeded) included


def test_the_expert_succeeds_and_doing_nothing_never_does_at_any_tolerance(curves):
    for factor in ("1", "4"):
        assert curves["expert"][factor]["phase_success/manipulation"] == 1.0
        for name in ("hold last action", "zero"):
            assert curves[name][factor]["phase_success/navigation"] == 0.0
            assert curves[name][factor]["failure/navigation/never_within_radius"] == 1.0


def test_looser_tolerances_never_lower_a_noisy_experts_success(curves):
    curve = curves[calibration.NOISY_EXPERT]
    for kind in ("navigation", "manipulation"):
        assert curve["4"][f"phase_success/{kind}"] >= curve["1"][f"phase_success/{kind}"]


def test_the_noisy_expert_holds_each_error_draw_for_hold_steps():
    env = env_lib.DemoWorldEnv(QUICK)
    env.reset(seed=0)
    noisy = rollout.NoisyExpertDriver(np.full(23, 0.1), hold=3)
    clean = rollout.ExpertDriver()
    twin = env_lib.DemoWorldEnv(QUICK)
    twin.reset(seed=0)
    noisy.start([env])
    clean.start([twin])
    errors = []
    for _ in range(6):
        errors.append(noisy([0], [None])[0, 0] - clean([0], [None])[0, 0])
    # The expert's own draws are the same in both: the difference is the held noise.
    np.testing.assert_allclose(errors[0], errors[2])
    np.testing.assert_allclose(errors[3], errors[5])
    assert not np.allclose(errors[0], errors[3])


def test_policy_error_comes_from_a_runs_last_evaluation_in_data_units(tmp_path):
    stats = {"norm_stats": {name: {"mean": [0.0] * 23, "std": [2.0] * 23, "q01": [-1.0] * 23,
                                   "q99": [1.0] * 23}
                            for name in ("actions", "state", "actions_absolute")}}
    (tmp_path / "norm_stats.json").write_text(json.dumps(stats))
    (tmp_path / "config.json").write_text(json.dumps(
        {"layout": {"preset": "b1k_r1pro", "action_dim": 32}}))
    record = {"step": 10, **{f"err/{g}": 0.25 for g in ("base", "torso", "left_arm",
                                                        "left_gripper", "right_arm",
                                                        "right_gripper")}}
    (tmp_path / "metrics.jsonl").write_text(json.dumps(record) + "\n")
    np.testing.assert_allclose(calibration.policy_error_std(tmp_path), np.full(23, 1.0))


def test_a_noise_run_without_an_evaluation_is_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match="--noise_run=.*held-out evaluation"):
        calibration.policy_error_std(tmp_path)


def test_each_tolerance_keeps_the_outcomes_of_its_own_episodes(curves):
    for factor, summary in curves[calibration.NOISY_EXPERT].items():
        detail = summary["episodes_detail"]
        assert [e["episode"] for e in detail] == [PRESS_TASK]
        assert float(np.mean([e["task"] for e in detail])) == summary["success/task"]
        phases = [p for e in detail for p in e["phases"] if p["kind"] == "manipulation"]
        assert np.mean([p["success"] for p in phases]) == summary["phase_success/manipulation"]
