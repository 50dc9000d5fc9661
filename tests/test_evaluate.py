"""Held-out stagnation metrics, the do-nothing baselines and the offline evaluation of a
checkpoint (docs/evaluation.md)."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

import train_fixtures as tf
from train_fixtures import cache_dir, demo_root  # noqa: F401  (pytest fixtures)
from pi0_armfix import evaluate as evaluate_command
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.evaluation import baselines, ceiling
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.evaluation import heldout
from pi0_armfix.evaluation import chunk_sums as chunk_sums_lib
from pi0_armfix.evaluation import metrics as eval_metrics
from pi0_armfix.data.pipeline import transforms
from pi0_armfix.policies import restore

LAYOUT = ActionLayout(groups={"base": (0, 2), "arm": (2, 5), "gripper": (5, 6)}, real_dim=6,
                      action_dim=8, velocity_groups=("base",))
H = 6


def _metrics(predicted, true, valid=None):
    valid = np.ones(true.shape[:2], bool) if valid is None else valid
    return eval_metrics.chunk_metrics(predicted, true, valid, layout=LAYOUT,
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


def _switches(metrics):
    return [metrics[f"gripper_switch/{k}"] for k in ("precision", "recall", "f1")]


def test_a_perfect_policy_has_gain_one_zero_error_and_switch_f1_one():
    true = _moving_chunks()
    metrics = _metrics(true.copy(), true)
    for g in LAYOUT.group_names:
        assert metrics[f"err/{g}"] == 0
    for g in ("base", "arm"):
        assert metrics[f"motion_gain/{g}"] == pytest.approx(1.0)
        assert metrics[f"motion_ratio/{g}"] == pytest.approx(1.0)
    assert _switches(metrics) == [1.0, 1.0, 1.0]


def test_a_policy_that_holds_the_current_action_has_arm_gain_zero():
    true = _moving_chunks()
    still = np.repeat(true[:, :1], H, axis=1)
    metrics = _metrics(still, true)
    assert metrics["motion_gain/arm"] == 0.0
    assert metrics["motion_ratio/arm"] == 0.0


def test_a_standing_base_has_gain_zero():
    true = _moving_chunks()
    standing = true.copy()
    standing[..., 0:2] = 0.0  # the zero velocity command
    assert _metrics(standing, true)["motion_gain/base"] == 0.0


def test_a_never_switching_gripper_has_recall_and_f1_zero_and_no_precision():
    true = _moving_chunks()
    never = true.copy()
    never[..., 5] = 1.0
    precision, recall, f1 = _switches(_metrics(never, true))
    assert np.isnan(precision) and recall == 0.0 and f1 == 0.0


def test_an_inverted_gripper_scores_zero():
    true = _moving_chunks()
    inverted = true.copy()
    inverted[..., 5] = -true[..., 5]  # every close becomes an open
    assert _switches(_metrics(inverted, true)) == [0.0, 0.0, 0.0]


def test_a_flickering_gripper_has_full_recall_but_low_precision():
    true = _moving_chunks()
    flicker = true.copy()
    flicker[..., 5] = np.where(np.arange(H) % 2, -1.0, 1.0)  # switches at every step
    precision, recall, f1 = _switches(_metrics(flicker, true))
    assert recall == 1.0 and precision < 0.25 and f1 < 0.4


def test_a_switch_within_the_tolerance_matches_and_one_outside_does_not():
    true = np.zeros((1, 12, LAYOUT.action_dim))
    true[0, :, 5] = 1.0
    true[0, 4:, 5] = -1.0  # closes at step 4
    late = true.copy()
    late[0, :, 5] = 1.0
    late[0, 6:, 5] = -1.0  # closes at step 6
    valid = np.ones((1, 12), bool)
    kwargs = dict(layout=LAYOUT, gripper_groups=("gripper",),
                  gripper_threshold=np.zeros(LAYOUT.action_dim))
    within = eval_metrics.chunk_metrics(late, true, valid, switch_tolerance=2, **kwargs)
    outside = eval_metrics.chunk_metrics(late, true, valid, switch_tolerance=1, **kwargs)
    assert within["gripper_switch/f1"] == 1.0 and outside["gripper_switch/f1"] == 0.0


def test_evaluation_units_scale_by_the_std_and_measure_a_near_constant_dim_in_data_units():
    std = np.array([2.0, 0.0, 1e-9])  # a moving dim, a constant one, an idle gripper
    scale, threshold = eval_metrics.evaluation_units(std, np.array([-1.0, 5.0, 0.0]),
                                                     np.array([3.0, 5.0, 0.0]))
    assert scale.tolist() == [2.0, 1.0, 1.0]
    assert threshold.tolist() == [0.5, 5.0, 0.0]


def test_the_error_in_the_datas_units_undoes_each_dims_scale():
    true = _moving_chunks()
    scale = np.array([0.5, 2.0, 0.01, 0.02, 0.03, 1.0, 1.0, 1.0])  # [A]: a base, rad, a gripper
    offset = np.array([0.0, 0.0, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0])  # the arm off, in data units
    sums = eval_metrics.chunk_sums(true + offset / scale, true, np.ones(true.shape[:2], bool),
                                   layout=LAYOUT, gripper_groups=("gripper",),
                                   gripper_threshold=np.zeros(8), scale=scale)
    metrics = eval_metrics.metrics_from_sums({k: v.sum() for k, v in sums.items()}, LAYOUT)
    assert metrics["rms_units/arm"] == pytest.approx(np.sqrt(np.mean([0.01, 0.04, 0.09])))
    assert metrics["rms_units/base"] == 0.0
    assert metrics["err/arm"] == pytest.approx(100.0)  # each dim off by 10 of its scale


def test_evaluation_scale_without_absolute_stats_falls_back_to_the_held_out_chunks():
    rng = np.random.default_rng(0)
    true = rng.normal(3.0, 2.0, size=(200, H, 2))
    true[..., 1] = 5.0
    scale, threshold = heldout.evaluation_scale({}, true, np.ones((200, H), bool))
    assert scale[0] == pytest.approx(true[..., 0].std()) and scale[1] == 1.0
    assert threshold[1] == pytest.approx(5.0)


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


def test_metrics_are_nan_where_the_data_gives_nothing_to_measure():
    still = np.zeros((4, H, LAYOUT.action_dim))
    metrics = _metrics(still, still)
    assert np.isnan(metrics["motion_gain/arm"]) and all(np.isnan(_switches(metrics)))


def test_the_energy_score_equals_the_hand_computed_value():
    layout = ActionLayout(groups={"g": (0, 2)}, real_dim=2, action_dim=2)
    draws = np.array([[0.0, 0.0], [3.0, 4.0]]).reshape(2, 1, 1, 2)  # [M, N, H, D]
    true = np.array([0.0, 1.0]).reshape(1, 1, 2)
    sums = eval_metrics.energy_sums(draws, true, np.ones((1, 1), bool), layout=layout)
    # E|X - y| = (1 + sqrt(18)) / 2; E|X - X'| / 2 = (5 + 5) / (2 * 2 * 1)
    assert sums["energy/g"][0] == pytest.approx((1 + np.sqrt(18)) / 2 - 2.5)


def test_a_point_predictions_energy_score_is_its_error_norm_over_valid_steps():
    true = _moving_chunks()
    predicted = true + 0.5
    valid = np.ones(true.shape[:2], bool)
    valid[0, -2:] = False
    sums = eval_metrics.energy_sums(predicted[None], true, valid, layout=LAYOUT)
    expected = np.sqrt(valid.sum(axis=1) * 3 * 0.25)  # arm: 3 dims off by 0.5 per valid step
    np.testing.assert_allclose(sums["energy/arm"], expected)


def test_spread_around_the_truth_scores_better_than_the_same_spread_beside_it():
    rng = np.random.default_rng(0)
    true = _moving_chunks()
    spread = rng.normal(size=(8, *true.shape))
    centred = eval_metrics.energy_sums(true + spread, true, np.ones(true.shape[:2], bool),
                                       layout=LAYOUT)
    biased = eval_metrics.energy_sums(true + 1.0 + spread, true, np.ones(true.shape[:2], bool),
                                      layout=LAYOUT)
    assert centred["energy/arm"].sum() < biased["energy/arm"].sum()


def _kept(predicted, true, episodes):
    valid = np.ones(true.shape[:2], bool)
    kwargs = dict(layout=LAYOUT, gripper_groups=("gripper",),
                  gripper_threshold=np.zeros(LAYOUT.action_dim))
    persistence = np.repeat(true[:, :1], true.shape[1], axis=1)
    return {"episode": episodes,
            **{f"policy/{k}": v for k, v in eval_metrics.chunk_sums(predicted, true, valid,
                                                                   **kwargs).items()},
            **{f"mean_of_draws/{k}": v for k, v in eval_metrics.chunk_sums(
                predicted, true, valid, **kwargs).items()},
            **{f"persistence/{k}": v for k, v in eval_metrics.chunk_sums(
                persistence, true, valid, **kwargs).items()}}


def test_skill_intervals_over_held_out_episodes_bracket_the_skill_and_pin_a_perfect_policy():
    rng = np.random.default_rng(0)
    true = np.cumsum(rng.normal(size=(40, H, LAYOUT.action_dim)), axis=1)
    episodes = np.repeat(np.arange(8), 5)
    held = _metrics(np.repeat(true[:, :1], H, axis=1), true)["err/arm"]
    perfect = chunk_sums_lib.episode_intervals(_kept(true, true, episodes), LAYOUT,
                                        {"skill/arm": 1.0, "mean_of_draws/skill/arm": 1.0})
    assert perfect["interval_low/skill/arm"] == perfect["interval_high/skill/arm"] == 1.0
    noisy = true + rng.normal(size=true.shape)
    skill = 1 - _metrics(noisy, true)["err/arm"] / held
    intervals = chunk_sums_lib.episode_intervals(_kept(noisy, true, episodes), LAYOUT,
                                          {"skill/arm": skill, "mean_of_draws/skill/arm": skill})
    low, high = intervals["interval_low/skill/arm"], intervals["interval_high/skill/arm"]
    assert low < skill < high
    np.testing.assert_allclose((low + high) / 2, skill)  # the t rule: centred on the estimate
    assert intervals["interval_low/mean_of_draws/skill/arm"] == low


def test_unknown_group_in_eval_config_is_an_error_naming_the_key():
    eval_cfg = dict(gripper_groups=("claw",), plot_groups=(), batch_size=8, max_chunks=16,
                    num_steps=10)
    with pytest.raises(ValueError, match=r"eval.gripper_groups names \['claw'\]"):
        evaluator_lib.check_eval_config(eval_cfg, LAYOUT, num_devices=1)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, demo_root):  # noqa: F811
    """A tiny run of configs/arm_focused.py with an EMA that moves (checkpoint at step 2); its
    tests are in the slow lane (the fast lane's one training is test_serve.py's run)."""
    return tf.trained_tiny_run("configs/arm_focused.py", tmp_path_factory.mktemp("run"),
                               demo_root, optim__ema_decay=0.5)


@pytest.mark.slow
def test_offline_evaluation_of_a_checkpoint_prints_metrics_and_writes_figures(
        trained, cache_dir):  # noqa: F811
    workdir = trained
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={workdir}"],
                            env=tf.env(cache_dir), cwd=tf.REPO_ROOT, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "step 2" in result.stdout
    for column in ("err", "skill", "gain", "ratio", "persistence err", "state copy err",
                   "precision", "TP/FP/FN", "left_arm"):
        assert column in result.stdout
    for figure in ("trajectories.png", "group_losses.png"):
        assert (workdir / "eval" / "step_2" / figure).stat().st_size > 10_000
    saved = json.loads((workdir / "eval" / "step_2" / "metrics.json").read_text())
    assert saved["step"] == 2 and saved["params"] == "ema_params"
    assert f"{saved['motion_gain/left_arm']:.3f}" in result.stdout
    assert saved["persistence/motion_gain/left_arm"] == 0.0  # holding never moves an arm
    assert saved["persistence/skill/left_arm"] == 0.0 and "skill/left_arm" in saved
    assert saved["draws"] == 8  # eval.num_draws: single draw, mean of 8, energy score
    for key in ("mean_of_draws/skill/left_arm", "energy/left_arm", "energy_skill/left_arm"):
        assert key in saved
    assert saved["persistence/energy_skill/left_arm"] == 0.0
    assert (workdir / "eval" / "stagnation.png").stat().st_size > 10_000  # over the evaluations


@pytest.mark.slow  # a second process of the evaluate command
def test_offline_evaluation_is_quiet_by_default(trained, cache_dir):  # noqa: F811
    result = subprocess.run([sys.executable, "-m", "pi0_armfix.evaluate", f"--workdir={trained}"],
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


# ---------------------------------------------------------------------- baselines


def _tiny_table():
    """Two episodes of 4 frames; actions [base vx, arm q, gripper] and a state whose arm is at
    index 0 and whose base velocity is at index 1 (another order than the actions)."""
    actions = np.array([[0.1, 1.0, 1.0], [0.2, 1.5, 1.0], [0.3, 2.0, -1.0], [0.3, 2.5, -1.0],
                        [0.0, -1.0, 1.0], [0.0, -0.5, 1.0], [0.5, 0.0, 1.0], [0.5, 0.5, -1.0]])
    state = np.array([[0.9, 0.05], [1.2, 0.1], [1.7, 0.2], [2.2, 0.3],
                      [-1.1, 0.0], [-0.8, 0.0], [-0.3, 0.4], [0.2, 0.5]])
    return EpisodeTable(actions=actions, state=state, episode_starts=np.array([0, 4, 8]),
                        episode_index=np.array([0, 1]), tasks=["a", "b"])


TINY = ActionLayout(groups={"base": (0, 1), "arm": (1, 2), "gripper": (2, 3)}, real_dim=3,
                    action_dim=4, velocity_groups=("base",),
                    roles={"base": "base", "arm": "arm", "gripper": "gripper"})


def test_persistence_holds_the_previous_action_and_the_first_action_at_an_episode_start():
    chunks = baselines.persistence(_tiny_table(), np.array([0, 2, 4, 7]), horizon=3)
    assert chunks.shape == (4, 3, 3)
    # frame 0: no previous action (its own); frame 2: frame 1's; frame 4: a new episode's first
    assert chunks[:, 0].tolist() == [[0.1, 1.0, 1.0], [0.2, 1.5, 1.0], [0.0, -1.0, 1.0],
                                     [0.5, 0.0, 1.0]]
    assert (chunks == chunks[:, :1]).all()


def test_state_copy_maps_groups_by_name_and_holds_the_gripper():
    state_groups = {"arm": (0, 1), "base": (1, 2), "gripper": (1, 2)}
    chunks = baselines.state_copy(_tiny_table(), np.array([2, 5]), 2, TINY, state_groups)
    # base <- state[1], arm <- state[0]; the gripper (a width in the state) holds the command
    assert chunks[:, 0].tolist() == [[0.2, 1.7, 1.0], [0.0, -0.8, 1.0]]


def test_state_copy_without_state_groups_is_persistence():
    table, frames = _tiny_table(), np.array([1, 6])
    assert np.array_equal(baselines.state_copy(table, frames, 2, TINY, None),
                          baselines.persistence(table, frames, 2))


def test_persistence_metrics_equal_the_hand_computed_values():
    """Chunks of H = 2 at frames 1 and 5 of the tiny table, scored in data units."""
    table, frames = _tiny_table(), np.array([1, 5])
    true = table.actions[np.array([[1, 2], [5, 6]])]
    held = baselines.persistence(table, frames, 2)  # [[0.1, 1, 1] x2], [[0, -1, 1] x2]
    metrics = eval_metrics.chunk_metrics(held, true, np.ones((2, 2), bool), layout=TINY,
                                         gripper_groups=("gripper",),
                                         gripper_threshold=np.zeros(3))
    # base errors (0.1, 0.2; 0, 0.5)^2 / 4; arm (0.5, 1.0; 0.5, 1.0)^2 / 4
    assert metrics["err/base"] == pytest.approx((0.01 + 0.04 + 0 + 0.25) / 4)
    assert metrics["err/arm"] == pytest.approx((0.25 + 1.0 + 0.25 + 1.0) / 4)
    assert metrics["err/gripper"] == pytest.approx((0 + 4.0 + 0 + 0) / 4)
    # base gain: held means (0.1, 0) on true means (0.25, 0.25) -> 0.025 / 0.125
    assert metrics["motion_gain/base"] == pytest.approx(0.2)
    assert metrics["motion_gain/arm"] == 0.0
    # the true gripper closes once (frame 1 -> 2); persistence never switches
    assert [metrics[f"gripper_switch/{k}"] for k in ("tp", "fp", "fn")] == [0, 0, 1]
    assert eval_metrics.skill_scores(metrics, metrics, TINY) == {
        "skill/base": 0.0, "skill/arm": 0.0, "skill/gripper": 0.0}


def test_skill_is_one_for_a_perfect_policy_and_negative_for_one_worse_than_doing_nothing():
    persistence = {"err/base": 0.5, "err/arm": 0.1, "err/gripper": 0.0}
    policy = {"err/base": 0.0, "err/arm": 0.3, "err/gripper": 0.2}
    skill = eval_metrics.skill_scores(policy, persistence, TINY)
    assert skill["skill/base"] == 1.0 and skill["skill/arm"] == pytest.approx(-2.0)
    assert np.isnan(skill["skill/gripper"])


def test_held_out_chunks_tile_each_episode_so_every_transition_is_in_one_chunk():
    starts = np.array([0, 100, 130, 400])
    frames = heldout.tiled_chunk_starts(starts, horizon=10, max_chunks=1000)
    covered = np.zeros(400, int)  # transitions f -> f + 1 inside each chunk's 10 steps
    for f in frames:
        episode_end = starts[np.searchsorted(starts, f, side="right")]
        covered[f:min(f + 9, episode_end - 1)] += 1
    ends = starts[1:] - 1  # the last frame of an episode has no transition inside it
    assert (np.delete(covered, ends) == 1).all() and (covered[ends] == 0).all()


def test_held_out_chunks_beyond_max_chunks_are_an_even_subset_without_overlap():
    frames = heldout.tiled_chunk_starts(np.array([0, 1000]), horizon=10, max_chunks=40)
    assert len(frames) == 40 and (np.diff(frames) >= 9).all()
    assert frames[0] == 0 and frames[-1] > 900


def _evaluate_in_process(workdir, **eval_changes):
    import jax
    from pi0_armfix.policies import restore
    from pi0_armfix.data.formats import sources
    from pi0_armfix.data.pipeline.data_spec import DataSpec
    from pi0_armfix.model import tokenizer as tokenizer_lib
    from pi0_armfix import sharding as sharding_lib
    run = restore.restore_run(workdir)
    config = run.config
    config.eval.update(eval_changes)
    mesh = sharding_lib.make_mesh(1)
    spec = DataSpec.from_config(config, run.layout)
    source = sources.open_source(spec.options, run.layout)
    tokenize = tokenizer_lib.make_tokenizer(config.model, prompts=source.tasks)
    with jax.set_mesh(mesh):
        evaluator = evaluator_lib.Evaluator.for_policy(
            spec, config.eval, run.model_config, run.norm_stats, tokenize, mesh=mesh,
            params_sharding=sharding_lib.tree_shardings(run.params, mesh), source=source,
            sampling=run.sampling)
        return evaluator(run.params)


@pytest.mark.slow
def test_the_held_out_truth_is_the_stored_actions_on_every_dim_never_the_normalizers(trained):
    from pi0_armfix.policies import restore
    from pi0_armfix.data.pipeline import dataset as dataset_lib
    from pi0_armfix.data.pipeline import transforms
    from pi0_armfix.data.pipeline.data_spec import DataSpec
    run = restore.restore_run(trained)  # delta torso: its constant dim 6 relative to the state
    spec = DataSpec.from_config(run.config, run.layout)
    chunks = evaluator_lib.heldout_chunks(spec, run.config.eval, run.model_config,
                                          run.norm_stats, tokenize=None)
    table = dataset_lib.heldout_table(spec, images=False)
    index, is_pad = transforms.chunk_indices(chunks.frames, table.episode_starts,
                                             run.model_config.action_horizon)
    np.testing.assert_array_equal(chunks.valid, ~is_pad)
    np.testing.assert_array_equal(chunks.true,
                                  np.asarray(table.actions[index], np.float64) / chunks.scale)


@pytest.mark.slow
def test_a_held_out_set_smaller_than_a_batch_is_padded_and_scores_as_unpadded(trained):
    padded = _evaluate_in_process(trained, max_chunks=5, batch_size=32, num_draws=2)
    unpadded = _evaluate_in_process(trained, max_chunks=5, batch_size=5, num_draws=2)
    assert padded.metrics["chunks"] == 5
    np.testing.assert_allclose(padded.predicted, unpadded.predicted, rtol=1e-5, atol=1e-6)
    for key, value in unpadded.metrics.items():
        assert padded.metrics[key] == pytest.approx(value, rel=1e-4, abs=1e-6, nan_ok=True), key


@pytest.mark.slow
def test_a_trained_runs_output_on_a_constant_dim_is_the_constant(trained):
    from pi0_armfix.policies import inference
    policy = inference.RunPolicy.from_workdir(trained)
    rng = np.random.default_rng(0)
    observations = [{**{key: rng.integers(0, 255, (32, 32, 3), np.uint8)
                        for key in policy.keys.cameras},
                     policy.keys.state: np.r_[rng.normal(size=6), 0.0, rng.normal(size=16)],
                     policy.keys.prompt: ""} for _ in range(3)]
    actions = policy.infer(observations)
    assert np.all(actions[..., 6] == 0.0)  # the demo's torso dim 6 never moves
    assert np.ptp(actions[..., 5]) > 0  # its neighbour does


@pytest.mark.slow
def test_the_switch_timing_tool_times_the_evaluations_own_draws(trained):
    from pi0_armfix.tools import switch_timing
    _, metrics, _, _ = evaluate_command.evaluate_checkpoint(trained)
    step, result = switch_timing.run_switch_timing(str(trained), None, tolerances=(0, 2))
    single = result["single_draw"]
    assert (single["predicted"], single["true"]) == (
        metrics["gripper_switch/tp"] + metrics["gripper_switch/fp"],
        metrics["gripper_switch/tp"] + metrics["gripper_switch/fn"])
    assert single["by_tolerance"][2]["f1"] == pytest.approx(metrics["gripper_switch/f1"],
                                                            nan_ok=True)
    saved = json.loads((trained / "eval" / f"step_{step}" / switch_timing.RESULT_FILE).read_text())
    assert set(saved["mean_of_draws"]["recall"]) == {"executed", "ahead", "opens", "closes"}


# ---------------------------------------------------------------------- the ceiling (demo)


def test_the_expert_redraw_is_deterministic_and_differs_only_by_its_own_draws():
    from pi0_armfix.sim.expert import demonstration
    from pi0_armfix.sim.world import DemoSpec, World
    spec = DemoSpec(num_episodes=3)
    recorded = np.asarray(list(demonstration(World(spec, 1))))
    first = ceiling.redraw_chunk(spec, 1, 60, 16)
    assert np.array_equal(first, ceiling.redraw_chunk(spec, 1, 60, 16))
    other = ceiling.redraw_chunk(spec, 1, 60, 16, draw=1)
    assert not np.array_equal(first, other)
    # the same world state: the arms differ by the teleoperator's tremor, not by a posture
    arm = slice(7, 14)
    assert np.abs(first[:, arm] - recorded[60:76, arm]).max() < 10 * spec.arm_jitter


@pytest.mark.slow
def test_the_raw_params_of_a_run_with_an_ema_never_replace_the_ema_results(trained):
    _, ema_metrics, _, ema_path = evaluate_command.evaluate_checkpoint(trained)
    _, raw_metrics, _, raw_path = evaluate_command.evaluate_checkpoint(trained,
                                                                       params_name="params")
    assert ema_path.name == "metrics.json" and raw_path.name == "metrics_params.json"
    assert json.loads(ema_path.read_text())["params"] == "ema_params"
    assert json.loads(raw_path.read_text())["params"] == "params"
    assert (raw_path.parent / "chunk_sums_params.npz").is_file()


@pytest.mark.slow
def test_an_evaluation_names_the_chunks_it_scored(trained):
    _, metrics, _, path = evaluate_command.evaluate_checkpoint(trained)
    sums = chunk_sums_lib.load_chunk_sums(path.parent / chunk_sums_lib.CHUNK_SUMS_FILE)
    chunks = sums[chunk_sums_lib.CHUNKS]  # episode id, first frame in it, horizon
    assert chunks.shape == (metrics["chunks"], 3) and (chunks[:, 2] == chunks[0, 2]).all()
    assert chunk_sums_lib.chunks_fingerprint(sums) == chunk_sums_lib.chunks_fingerprint(dict(sums))
    other = {**sums, chunk_sums_lib.CHUNKS: chunks + np.array([0, 0, 1])}  # another horizon
    assert chunk_sums_lib.chunks_fingerprint(other) != chunk_sums_lib.chunks_fingerprint(sums)


def test_the_printed_table_says_n_a_and_why_for_a_constant_group_and_an_unmapped_state():
    layout = ActionLayout(groups={"arm": (0, 2), "still": (2, 3)}, real_dim=3, action_dim=4)
    metrics = {}
    for g, skill in (("arm", 0.5), ("still", math.nan)):
        metrics |= {f"err/{g}": 0.1 if skill == skill else 0.0, f"skill/{g}": skill,
                    f"interval_low/skill/{g}": skill - 0.1, f"interval_high/skill/{g}": skill + 0.1,
                    f"motion_gain/{g}": 0.5, f"motion_ratio/{g}": 1.0,
                    **{f"{name}/err/{g}": 0.2 for name in ("persistence", "state_copy")},
                    **{f"{name}/motion_gain/{g}": 0.0 for name in ("persistence", "state_copy")}}
    text = evaluator_lib.format_metrics(metrics, layout)
    assert "nan" not in text
    assert "n/a: still never move(s)" in text
    assert "state copy = persistence: the state maps to no action group" in text


@pytest.mark.slow
def test_the_evaluator_scores_any_prediction_function_chunk_for_chunk(trained):
    from pi0_armfix.policies import restore
    from pi0_armfix.data.pipeline.data_spec import DataSpec
    run = restore.restore_run(trained)
    spec = DataSpec.from_config(run.config, run.layout)
    eval_cfg = {**run.config.eval.to_dict(), "batch_size": 2}  # several batches, the last padded
    chunks = evaluator_lib.heldout_chunks(spec, eval_cfg, run.model_config, run.norm_stats,
                                          tokenize=None)
    horizon, dim = run.model_config.action_horizon, run.model_config.action_dim
    assert len(chunks.batches) > 1

    def predict(params, observation, rows):  # each chunk predicted as its own index
        out = np.full((2, len(observation["state"]), horizon, dim), -1.0)
        out[:, :rows.stop - rows.start] = np.arange(rows.start, rows.stop)[None, :, None, None]
        return out

    evaluator = evaluator_lib.Evaluator(chunks, predict, plot_groups=())
    sampled = evaluator.sample(params=None)
    np.testing.assert_array_equal(
        sampled, np.broadcast_to(np.arange(len(chunks.frames))[None, :, None, None],
                                 (2, len(chunks.frames), horizon, dim)))
    absolute = np.stack([chunks.transform.absolute_actions(d, chunks.frames) for d in sampled])
    np.testing.assert_equal(evaluator(None).metrics, chunks.score(absolute / chunks.scale)[0])


@pytest.mark.parametrize("key, said", [
    ({"data.delta_reference": "previous_action"}, "an earlier rule; its norm_stats.key.json"),
    ({"data.delta_reference": "previous_action", "episode_start": "the state"}, "to the state;"),
    ({"data.delta_reference": "previous_action", "episode_start": transforms.EPISODE_START},
     None),
    ({}, None),
])
def test_a_run_trained_under_another_episode_start_rule_is_named_when_it_is_restored(
        tmp_path, key, said):
    (tmp_path / "norm_stats.key.json").write_text(json.dumps(key))
    warning = restore.episode_start_warning(tmp_path)
    if said is None:
        assert warning is None
    else:
        assert said in warning and f"today's rule ({transforms.EPISODE_START})" in warning
