"""Data curriculum: validation, phases, the source draw, resumption across a phase switch."""

import json

import jax
import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.pipeline import curriculum as curriculum_lib
from pi0_armfix.data.pipeline import pipeline
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics import stats as stats_lib

LAYOUT = ActionLayout.preset("b1k_r1pro")
BATCH = 6


def episode_table(num_episodes=8, length=10) -> EpisodeTable:
    """Dim 0 of every action is its episode's dataset index (20 + position)."""
    n = num_episodes * length
    actions = np.random.default_rng(0).normal(size=(n, 23)).astype(np.float32)
    actions[:, 0] = np.repeat(np.arange(num_episodes) + 20, length)
    return EpisodeTable(actions=actions, state=np.zeros((n, 23), np.float32),
                        episode_starts=np.arange(0, n + 1, length),
                        episode_index=np.arange(num_episodes) + 20, tasks=["t"] * num_episodes)


def episode_list(tmp_path, episodes):
    path = tmp_path / "arm_heavy.json"
    path.write_text(json.dumps({"episodes": list(episodes)}))
    return str(path)


def iterator(table, data, seed=0):
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), progress=False)
    spec = DataSpec.from_config({"seed": seed, "data": {"norm": "zscore", **data}}, LAYOUT)
    dataset = pipeline.train_batches(table, spec, norm_stats=stats, action_horizon=2,
                                     global_batch_size=BATCH, actions_only=True)
    mesh = jax.make_mesh((1,), ("batch",), axis_types=(jax.sharding.AxisType.Auto,))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
    run = pipeline.TrainIterator(dataset, spec.curriculum, sharding=sharding,
                                 global_batch_size=BATCH, seed=seed)
    normalizer = normalize.Normalizer.from_stats(stats["actions"], "zscore")
    return run, normalizer


def episodes_of(batch, normalizer):
    raw = normalizer.inverse(np.asarray(batch["actions"])[:, 0])
    return set(np.rint(raw[:, 0]).astype(int).tolist())


# ---------------------------------------------------------------------- validation

@pytest.mark.parametrize("curriculum, match", [
    (((10, {"arm": 1.0}),), r"data.curriculum\[0\]: unknown source 'arm'"),
    (((10, {"full": 1.0}), (10, {"arm_heavy": 1.0})),
     r"data.curriculum\[1\]: until_step 10 must be greater than the previous phase's \(10\)"),
    (((0, {"full": 1.0}),), r"data.curriculum\[0\]: until_step 0"),
    (((10, {"full": 1.0}), (20, {"full": -0.5, "arm_heavy": 1.0})),
     r"data.curriculum\[1\]: weight of 'full' is negative"),
    (((10, {"full": 0.0, "arm_heavy": 0.0}),), r"data.curriculum\[0\]: all weights are zero"),
    (((10, {"full": float("nan")}),),
     r"data.curriculum\[0\]: weight of 'full' must be a finite number"),
    (((10.5, {"full": 1.0}),), r"data.curriculum\[0\]: until_step must be an int"),
    ((("full", 1.0),), r"data.curriculum\[0\] .* must be a pair"),
])
def test_bad_curricula_name_the_culprit(curriculum, match):
    with pytest.raises(ValueError, match=match):
        curriculum_lib.parse_curriculum(curriculum)


def test_empty_curriculum_is_full_throughout():
    phases = curriculum_lib.parse_curriculum(())
    assert [p.weights for p in phases] == [{"full": 1.0}]


def test_zero_weights_are_dropped_and_the_rest_normalized():
    phases = curriculum_lib.parse_curriculum(
        ((5, {"arm_heavy": 2.0, "full": 0.0}), (9, {"arm_heavy": 1.0, "full": 3.0})))
    assert phases[0].weights == {"arm_heavy": 1.0}
    assert phases[1].weights == {"full": 0.75, "arm_heavy": 0.25}
    only_full = curriculum_lib.Curriculum(
        curriculum_lib.parse_curriculum(((5, {"full": 1.0, "arm_heavy": 0.0}),)), seed=0)
    assert only_full.sources == ("full",)


def test_phase_boundaries_and_the_last_phase_continues():
    curriculum = curriculum_lib.Curriculum(curriculum_lib.parse_curriculum(
        ((3, {"arm_heavy": 1.0}), (6, {"full": 1.0}))), seed=0)
    assert [curriculum.phase_at(s) for s in (0, 2, 3, 5, 6, 1000)] == [0, 0, 1, 1, 1, 1]


def test_source_draw_follows_the_weights_and_is_a_function_of_the_index():
    curriculum = curriculum_lib.Curriculum(curriculum_lib.parse_curriculum(
        ((10**9, {"arm_heavy": 0.3, "full": 0.7}),)), seed=5)
    draws = np.array([curriculum.choose(g, 64) for g in range(20_000)])
    share_full = (np.array(curriculum.sources)[draws] == "full").mean()
    assert abs(share_full - 0.7) < 0.02
    assert [curriculum.choose(g, 64) for g in range(100)] == draws[:100].tolist()


# ---------------------------------------------------------------------- in the pipeline

def test_arm_heavy_phase_draws_only_the_listed_episodes(tmp_path):
    listed = [21, 24, 99]  # 99 is not in the table: ignored
    data = {"curriculum": ((4, {"arm_heavy": 1.0}), (8, {"full": 1.0})),
            "arm_heavy_episodes": episode_list(tmp_path, listed)}
    run, normalizer = iterator(episode_table(), data)
    seen_early, seen_late = set(), set()
    for step in range(8):
        seen = episodes_of(next(run), normalizer)
        assert run.phase == (0 if step < 4 else 1)
        (seen_early if step < 4 else seen_late).update(seen)
    assert seen_early == {21, 24}
    assert len(seen_late - {21, 24}) > 0


def test_resuming_just_before_a_phase_switch_gives_the_same_sequence(tmp_path):
    data = {"curriculum": ((3, {"arm_heavy": 1.0}), (5, {"arm_heavy": 0.5, "full": 0.5}),
                           (9, {"full": 1.0})),
            "arm_heavy_episodes": episode_list(tmp_path, [20, 23, 26])}
    table = episode_table()
    run, _ = iterator(table, data)
    for _ in range(2):
        next(run)
    state = json.loads(json.dumps(run.get_state()))
    expected = [(np.asarray(next(run)["actions"]), run.phase) for _ in range(5)]
    assert [phase for _, phase in expected] == [0, 1, 1, 2, 2]
    resumed, _ = iterator(table, data)
    resumed.set_state(state)
    for actions, phase in expected:
        np.testing.assert_array_equal(np.asarray(next(resumed)["actions"]), actions)
        assert resumed.phase == phase


def test_an_episode_list_without_training_episodes_is_an_error(tmp_path):
    data = {"curriculum": ((4, {"arm_heavy": 1.0}),),
            "arm_heavy_episodes": episode_list(tmp_path, [7, 8])}
    with pytest.raises(ValueError, match="selects none of the 8 training episodes"):
        iterator(episode_table(), data)


@pytest.mark.parametrize("content, match", [
    ("[1, 2]", "needs an 'episodes' list"),
    ('{"episodes": ["a"]}', "needs an 'episodes' list"),
    ("{oops", "not valid JSON"),
])
def test_bad_episode_lists_name_the_file(tmp_path, content, match):
    path = tmp_path / "list.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=match) as error:
        curriculum_lib.load_episode_list(path)
    assert "list.json" in str(error.value)


def test_missing_episode_list_is_named(tmp_path):
    with pytest.raises(ValueError, match="gone.json does not exist"):
        curriculum_lib.load_episode_list(tmp_path / "gone.json")
