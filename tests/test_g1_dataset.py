"""A Unitree G1 with Inspire hands as published (layout-exact fixture, `g1_fixture`): the `g1`
scale reads it with its camera, leaves out the episodes whose videos are missing only when told,
trains and evaluates, and the analysis tools run on it."""

import jax
import numpy as np
import pytest

import g1_fixture
from data_fixtures import identify_frame
from pi0_armfix import evaluate as evaluate_command
from pi0_armfix import train
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import arm_focused, arm_focused_previous_action, arm_weights_3x, uniform
from pi0_armfix.data.formats.sources import open_source
from pi0_armfix.data.formats.video import keyframe_interval
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.evaluation import evaluator as evaluator_lib
from pi0_armfix.policies import execution, inference
from pi0_armfix.policies.sampling import Sampling
from pi0_armfix.tools import analyze_action_magnitudes

LAYOUT = ActionLayout.preset("g1_inspire")
MISSING = (1,)


@pytest.fixture(scope="module")
def g1(tmp_path_factory):
    root = tmp_path_factory.mktemp("g1") / "G1-policy-train"
    return root, g1_fixture.write_g1_dataset(root, missing_videos=MISSING)


def g1_config(root, make=arm_focused.get_config, **overrides):
    """A `:g1` config shrunk to the tiny preset on the fixture: two steps of batch 8 and an
    evaluation on the last 2 episodes."""
    config = make("g1")
    config.update_from_flattened_dict({
        "model.preset": "tiny", "data.root": str(root), "data.num_workers": 0,
        "train.total_steps": 2, "train.batch_size": 8, "train.log_every": 1,
        "train.checkpoint_every": 2, "optim.warmup_steps": 1, "eval.every": 2,
        "eval.episodes": 2, "eval.batch_size": 8, "eval.max_chunks": 16, **overrides})
    return config


def test_the_fixture_is_av1_with_a_keyframe_every_two_frames_as_published(g1):
    root, _ = g1
    video = root / "videos/chunk-000" / g1_fixture.CAMERA / "episode_000000.mp4"
    codec, height, width, interval = keyframe_interval(video)
    assert (codec, height, width, interval) == ("libdav1d", 48, 64, 2)


def test_the_g1_scale_reads_both_arms_and_hands_with_the_state_in_the_action_order():
    config = arm_focused.get_config("g1")
    assert config.layout.preset == "g1_inspire"
    assert dict(config.data.state_groups) == dict(LAYOUT.groups)
    assert LAYOUT.roles == {"left_arm": "arm", "right_arm": "arm", "left_hand": "hand",
                            "right_hand": "hand"}
    assert config.data.delta_action_mask == ("left_arm", "right_arm", "left_hand", "right_hand")


def test_the_g1_scale_weights_the_arms_and_hands_in_the_seeds_3x():
    assert dict(arm_weights_3x.get_config("g1").loss.group_weights) == {
        "left_arm": 3.0, "right_arm": 3.0, "left_hand": 3.0, "right_hand": 3.0}
    assert set(dict(uniform.get_config("g1").loss.group_weights)) == set(LAYOUT.group_names)


def test_missing_videos_are_refused_by_default_naming_the_episodes(g1):
    root, _ = g1
    source = open_source(g1_config(root).data, LAYOUT)
    with pytest.raises(ValueError, match=r"episodes 1; .*data.skip_missing_videos=True"):
        source.probe()


def test_the_camera_feeds_the_head_camera_and_decodes_each_rows_frame(g1):
    root, written = g1
    source = open_source(g1_config(root, **{"data.skip_missing_videos": True}).data, LAYOUT)
    assert source.cameras == {"base_0_rgb": g1_fixture.CAMERA}
    assert source.skipped_episodes == MISSING
    table = source.load_table([2])
    np.testing.assert_array_equal(table.actions[:], written[2][1])
    np.testing.assert_array_equal(table.state[:], written[2][0])
    for frame in (0, 9, 17, g1_fixture.LENGTHS[2] - 1):
        image = table.images(frame)["base_0_rgb"]
        # the colour repeats every 16 frames (`data_fixtures.frame_colour`)
        assert identify_frame(image, 2, g1_fixture.LENGTHS[2], 0) == frame % 16


@pytest.mark.slow  # a whole training run: the slow lane
def test_the_g1_scale_trains_and_evaluates_without_the_episodes_missing_their_videos(g1, tmp_path):
    root, _ = g1
    workdir = tmp_path / "run"
    record = train.train_and_evaluate(
        g1_config(root, **{"data.skip_missing_videos": True}), str(workdir))
    assert np.isfinite(record["loss"]) and (workdir / "checkpoints" / "2").is_dir()
    step, metrics, _, _ = evaluate_command.evaluate_checkpoint(workdir)
    assert step == 2
    for group in LAYOUT.group_names:
        assert np.isfinite(metrics[f"skill/{group}"])
    # hands are joints: no switch is counted, and the table has no switch line
    assert sum(metrics[f"gripper_switch/{k}"] for k in ("tp", "fp", "fn")) == 0
    assert "gripper switches" not in evaluator_lib.format_metrics(metrics, LAYOUT)


def test_the_analysis_finds_the_idle_sides_state_copy_and_offset(g1, tmp_path):
    root, _ = g1
    report = analyze_action_magnitudes.run(
        g1_config(root, make=uniform.get_config, **{"eval.episodes": 1}), tmp_path / "r.json")
    groups = report["mechanism"]["groups"]
    assert groups["left_arm"]["state_explained"] > 0.9
    assert groups["left_hand"]["state_explained"] > 0.9
    # the idle side is commanded at a steady offset from where it is: the offset verdict
    assert {"left_arm", "left_hand"} <= set(report["mechanism"]["offset"])
    assert "right_arm" not in report["mechanism"]["offset"]


KEYS = inference.ObservationKeys({"cam_high": "base_0_rgb"}, state="state", prompt="prompt")


@pytest.fixture(scope="module")
def previous_action_run(g1, tmp_path_factory):
    root, _ = g1
    workdir = tmp_path_factory.mktemp("previous") / "run"
    train.train_and_evaluate(g1_config(root, make=arm_focused_previous_action.get_config,
                                       **{"data.skip_missing_videos": True}), str(workdir))
    return workdir


def _observation(written, frame, episode=2):
    state, _ = written[episode]
    return {"cam_high": np.zeros((g1_fixture.HEIGHT, g1_fixture.WIDTH, 3), np.uint8),
            "state": state[frame], "prompt": g1_fixture.TASK}


@pytest.mark.slow  # a trained run of the G1 scale
def test_a_previous_action_policy_is_relative_to_the_command_it_is_given(g1, previous_action_run):
    _, written = g1
    policy = inference.RunPolicy.from_workdir(previous_action_run, keys=KEYS)
    assert policy.metadata()["delta_reference"] == "previous_action"
    state, action = written[2]
    observation = _observation(written, 5)
    inputs, selected = policy.model_inputs([observation])
    # one camera: the wrists are what training fed for them, masked out
    assert inputs["image_mask"]["base_0_rgb"].all()
    assert not inputs["image_mask"]["left_wrist_0_rgb"].any()
    given = {**observation, "previous_action": action[4]}
    np.testing.assert_array_equal(policy.reference([given], selected), action[4][None])
    # no command yet (an episode's first step): the episode's start, as in training: the state,
    # which holds every group's joints as positions in the action order, and the training
    # split's mean offset of the command from it
    stats = policy.run.norm_stats
    offset = stats[stats_lib.ABSOLUTE_ACTIONS].mean - stats["state"].mean
    np.testing.assert_allclose(policy.reference([observation], selected),
                               (state[5] + offset)[None], rtol=1e-5)
    rng = jax.random.key(3)
    np.testing.assert_allclose(policy.infer([observation], rng=rng, previous=action[4][None]),
                               policy.infer([given], rng=rng), atol=1e-6)


@pytest.mark.slow  # a trained run of the G1 scale
def test_a_malformed_previous_action_is_one_error_naming_the_key(g1, previous_action_run):
    _, written = g1
    policy = inference.RunPolicy.from_workdir(previous_action_run, keys=KEYS)
    observation = {**_observation(written, 5), "previous_action": np.zeros(3)}
    with pytest.raises(ValueError, match=r"'previous_action' must be the 26 finite values"):
        policy.infer([observation])


class _Recording:
    """A previous-action policy that records what it was given."""

    delta_reference = "previous_action"
    layout, horizon = LAYOUT, 4

    def __init__(self):
        self.given = []

    def infer(self, observations, follow=None, previous=None):
        self.given.append(previous)
        return np.random.default_rng(len(self.given)).normal(
            size=(len(observations), 4, 26)).astype(np.float32)


def test_the_replanner_gives_the_policy_the_last_action_it_executed():
    policy = _Recording()
    replanning = execution.Replanner(policy, Sampling(n_exec=3))
    replanning.start()
    first = replanning([0, 1], [{}, {}])
    assert np.isnan(policy.given[0]).all()  # an episode's start: none yet
    replanning([1], [{}])
    np.testing.assert_array_equal(policy.given[1], first[1:, 2])
    replanning.start()
    replanning([1], [{}])
    assert np.isnan(policy.given[2]).all()
