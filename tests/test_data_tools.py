"""Motion measures, balanced normalization, the arm-heavy filter and the four data tools."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pi0_armfix.configs import base as base_config
from data_fixtures import write_dataset
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats import sources
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import sampling
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import motion as motion_lib
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import config as model_config_lib
from pi0_armfix.tools import (analyze_action_magnitudes, compute_norm_stats,
                              filter_arm_heavy_episodes, recompute_balanced_norm_stats)

LAYOUT = ActionLayout.preset("b1k_r1pro")
REPO = Path(__file__).resolve().parents[1]
# The widely copied wrong B1K action layout (the baseline's *state* order).
WRONG_GROUPS = {"base": (0, 3), "torso": (3, 7), "left_arm": (7, 14), "right_arm": (14, 21),
                "grippers": (21, 23)}


def b1k_like_episode(rng, n: int, manipulation: bool) -> np.ndarray:
    """[n, 23]: navigation = base velocity commands, arms still, grippers held; manipulation =
    base still, slow arm joints, grippers switching between -1 and 1. Torso dim 6 is 0."""
    t = np.arange(n)[:, None]
    actions = np.zeros((n, 23))
    actions[:, 3:6] = rng.normal(size=3) * 0.3
    arms = [slice(7, 14), slice(15, 22)]
    for arm in arms:
        speed = 0.02 if manipulation else 0.0
        actions[:, arm] = rng.normal(size=7) + np.cumsum(rng.normal(size=(n, 7)) * speed, 0)
    if manipulation:
        actions[:, 14] = np.where((t[:, 0] // 25) % 2, 1.0, -1.0)
        actions[:, 22] = np.where((t[:, 0] // 40) % 2, -1.0, 1.0)
    else:
        actions[:, 0:3] = 0.3 * np.sin(t / 15 + rng.uniform(0, 6, 3))
        actions[:, [14, 22]] = rng.choice([-1.0, 1.0], 2)
    return actions


def b1k_like_episodes(num_episodes=12, seed=0):
    """Alternating navigation (even) and manipulation (odd) episodes."""
    rng = np.random.default_rng(seed)
    return [b1k_like_episode(rng, int(rng.integers(60, 100)), manipulation=e % 2 == 1)
            for e in range(num_episodes)]


def table_of(episodes) -> EpisodeTable:
    starts = np.concatenate([[0], np.cumsum([len(e) for e in episodes])]).astype(np.int64)
    actions = np.concatenate(episodes).astype(np.float32)
    return EpisodeTable(actions=actions, state=actions.copy(), episode_starts=starts,
                        episode_index=np.arange(len(episodes)), tasks=["t"] * len(episodes))


def summary_of(table, stats=None, block_frames=65536):
    stats = stats or stats_lib.compute_norm_stats(stats_lib.table_blocks(table), ("actions",),
                                                  progress=False)
    unit, active = motion_lib.normalized_units(stats["actions"], "zscore")
    return motion_lib.compute_motion(stats_lib.table_blocks(table, ("actions",), block_frames),
                                     LAYOUT, unit, active, progress=False)


def group_motion_rms(table, normalizer, active):
    """Direct computation: per group, RMS over within-episode pairs and active dims of the
    normalized frame-to-frame change."""
    x = normalizer(table.actions).astype(np.float64)
    same = table.episode_of_frame(np.arange(1, table.num_frames)) == \
        table.episode_of_frame(np.arange(table.num_frames - 1))
    diff = (x[1:] - x[:-1])[same]
    return np.array([np.sqrt((diff[:, d][:, active[d]] ** 2).mean())
                     if active[LAYOUT.group_dims(g)].any() else 0.0
                     for g in LAYOUT.group_names for d in [LAYOUT.group_dims(g)]])


# ---------------------------------------------------------------------- motion

def test_motion_pairs_never_cross_episode_boundaries_also_between_blocks():
    episodes = [np.full((5, 23), 0.0), np.full((4, 23), 7.0), np.full((6, 23), -3.0)]
    table = table_of(episodes)
    for block_frames in (3, 5, 100):
        summary = summary_of(table, block_frames=block_frames)
        assert summary.num_pairs == 4 + 3 + 5
        assert (summary.dim_sq_sum == 0).all()
        np.testing.assert_array_equal(summary.episode_frames, [5, 4, 6])


def test_streaming_motion_equals_one_block():
    table = table_of(b1k_like_episodes(4))
    whole, streamed = summary_of(table), summary_of(table, block_frames=37)
    np.testing.assert_allclose(streamed.dim_sq_sum, whole.dim_sq_sum, rtol=1e-12)
    np.testing.assert_allclose(streamed.episode_motion_sum, whole.episode_motion_sum, rtol=1e-12)
    np.testing.assert_array_equal(streamed.episode_pairs, whole.episode_pairs)
    np.testing.assert_array_equal(streamed.motion.counts, whole.motion.counts)


# ---------------------------------------------------------------------- balanced normalization

@pytest.mark.parametrize("mode", stats_lib.NORM_MODES)
def test_balanced_stats_give_every_group_the_same_motion_rms(mode):
    table = table_of(b1k_like_episodes())
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), ("actions",),
                                         progress=False)["actions"]
    balanced, reports = motion_lib.balanced_norm_stats(stats, summary_of(table), LAYOUT,
                                                       max_scale=100.0)
    report = next(r for r in reports if r.mode == mode)
    _, active = motion_lib.normalized_units(stats, mode)
    before = group_motion_rms(table, normalize.Normalizer.from_stats(stats, mode), active)
    after = group_motion_rms(table, normalize.Normalizer.from_stats(balanced, mode), active)
    moving = before > 0
    assert before[moving].max() / before[moving].min() > 5  # the data is imbalanced
    np.testing.assert_allclose(after[moving], report.target, rtol=1e-3)
    np.testing.assert_allclose(after, list(report.after.values()), rtol=1e-3)
    arms = [LAYOUT.group_names.index(g) for g in ("left_arm", "right_arm")]
    assert all(list(report.scale_change.values())[g] < 1 for g in arms)  # arms amplified


def test_balance_cap_holds():
    table = table_of(b1k_like_episodes())
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), ("actions",),
                                         progress=False)["actions"]
    balanced, reports = motion_lib.balanced_norm_stats(stats, summary_of(table), LAYOUT,
                                                       max_scale=2.0)
    change = balanced.std / np.where(stats.std > 0, stats.std, 1)
    assert change.max() <= 2.0 + 1e-12 and change[stats.std > 0].min() >= 0.5 - 1e-12
    zscore = next(r for r in reports if r.mode == "zscore")
    assert 2.0 in zscore.scale_change.values() or 0.5 in zscore.scale_change.values()
    np.testing.assert_array_equal(balanced.mean, stats.mean)
    np.testing.assert_allclose(balanced.q01 + balanced.q99, stats.q01 + stats.q99)


def test_balance_cap_below_one_is_an_error():
    table = table_of(b1k_like_episodes(2))
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), ("actions",),
                                         progress=False)["actions"]
    with pytest.raises(ValueError, match="balanced_max_scale must be >= 1"):
        motion_lib.balanced_norm_stats(stats, summary_of(table), LAYOUT, max_scale=0.5)


# ---------------------------------------------------------------------- arm-heavy filter

def test_manipulation_episodes_are_arm_heavy_and_navigation_ones_are_not():
    table = table_of(b1k_like_episodes())
    selected, per_episode = motion_lib.arm_heavy_episodes(summary_of(table), LAYOUT)
    np.testing.assert_array_equal(selected, np.arange(1, 12, 2))
    assert [e["selected"] for e in per_episode] == [e % 2 == 1 for e in range(12)]
    assert all(e["base_movement"] == 0 for e in per_episode if e["selected"])


def test_max_base_movement_and_min_arm_movement_filter():
    summary = summary_of(table_of(b1k_like_episodes()))
    none, _ = motion_lib.arm_heavy_episodes(
        summary, LAYOUT, motion_lib.ArmHeavyThresholds(min_arm_movement=1e9))
    loose, _ = motion_lib.arm_heavy_episodes(
        summary, LAYOUT, motion_lib.ArmHeavyThresholds(arm_ratio_threshold=0.0,
                                                       min_arm_movement=0.0,
                                                       max_base_movement=0.0))
    assert none.size == 0
    np.testing.assert_array_equal(loose, np.arange(1, 12, 2))  # only base-still episodes


def _summary(layout):
    table = table_of(b1k_like_episodes(2))
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), ("actions",),
                                         progress=False)["actions"]
    return motion_lib.compute_motion(stats_lib.table_blocks(table, ("actions",)), layout,
                                     *motion_lib.normalized_units(stats, "zscore"),
                                     progress=False)


def test_filter_needs_groups_declared_as_manipulation():
    layout = ActionLayout(groups={"joints": (0, 23)}, real_dim=23)
    with pytest.raises(ValueError, match=r"roles are \{'joints': 'other'\}.*layout.roles"):
        motion_lib.arm_heavy_episodes(_summary(layout), layout)


def test_filter_reads_group_roles_not_names():
    # A base named "wheels" and arms named "links": found by their roles.
    layout = ActionLayout(groups={"wheels": (0, 3), "links": (3, 23)}, real_dim=23,
                          roles={"wheels": "base", "links": "arm"})
    named = ActionLayout(groups={"base": (0, 3), "arm": (3, 23)}, real_dim=23,
                         roles={"base": "base", "arm": "arm"})
    assert motion_lib.arm_heavy_groups(layout) == motion_lib.arm_heavy_groups(named) == ([1], [0])


def test_a_fixed_base_layout_compares_manipulation_with_the_other_groups():
    layout = ActionLayout(groups={"torso": (0, 4), "arm": (4, 22), "gripper": (22, 23)},
                          real_dim=23, roles={"torso": "torso", "arm": "arm", "gripper": "gripper"})
    assert motion_lib.arm_heavy_groups(layout) == ([1, 2], [0])
    selected, per_episode = motion_lib.arm_heavy_episodes(_summary(layout), layout)
    assert len(per_episode) == 2


def test_a_layout_of_manipulation_groups_only_refuses_the_filter_naming_the_fix():
    layout = ActionLayout(groups={"arm": (0, 22), "gripper": (22, 23)}, real_dim=23,
                          roles={"arm": "arm", "gripper": "gripper"})
    with pytest.raises(ValueError, match=r"fixed-base arm.*data.curriculum=\(\)"):
        motion_lib.arm_heavy_groups(layout)


# ---------------------------------------------------------------------- the tools

@pytest.fixture(scope="module")
def config(tmp_path_factory):
    episodes = [{"actions": a, "state": a + 0.01, "task": "tidy up", "images": {}}
                for a in b1k_like_episodes()]
    root = write_dataset(tmp_path_factory.mktemp("b1k_like") / "ds", episodes, "v3.0",
                         episodes_per_file=5, row_group_size=200)
    config = base_config.get_config()
    config.data.root = str(root)
    config.eval.episodes = 2
    return config


def test_compute_norm_stats_writes_openpi_stats_of_the_training_frames(config, tmp_path):
    output = tmp_path / "norm_stats.json"
    compute_norm_stats.run(config, output)
    written = stats_lib.load_norm_stats(output)
    training = np.concatenate(b1k_like_episodes()[:10]).astype(np.float32).astype(np.float64)
    np.testing.assert_allclose(written["actions"].mean, training.mean(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(written["actions"].std, training.std(0), rtol=1e-9, atol=1e-12)
    data_range = training.max(0) - training.min(0)
    for q, field in ((0.01, "q01"), (0.99, "q99")):
        np.testing.assert_array_less(
            np.abs(getattr(written["actions"], field) - np.quantile(training, q, axis=0)),
            1e-3 * data_range + 1e-12)
    assert written["state"].width == 23


def test_every_episode_is_read_whatever_eval_episodes_holds_out(config, tmp_path):
    wide = config.copy_and_resolve_references()
    wide.eval.episodes = 20  # the default, more than this 12-episode set has
    written = compute_norm_stats.run(wide, tmp_path / "norm_stats.json", episodes="all")
    every = np.concatenate(b1k_like_episodes()).astype(np.float32).astype(np.float64)
    np.testing.assert_allclose(written["actions"].mean, every.mean(0), rtol=1e-9, atol=1e-12)


def test_a_hold_out_larger_than_the_dataset_names_a_setting_that_fits(config, tmp_path):
    wide = config.copy_and_resolve_references()
    wide.eval.episodes = 20
    with pytest.raises(ValueError, match=r"eval.episodes = 20: .*12 episodes for training; set "
                                         r"--config.eval.episodes=1 "):
        compute_norm_stats.run(wide, tmp_path / "norm_stats.json")


def test_analysis_reports_groups_and_writes_a_png(config, tmp_path):
    report = analyze_action_magnitudes.run(config, tmp_path / "report.json")
    assert (tmp_path / "report.png").stat().st_size > 0
    assert json.loads((tmp_path / "report.json").read_text()) == report
    groups = report["groups"]
    assert set(groups) == set(LAYOUT.group_names)
    assert sum(g["motion_share"] for g in groups.values()) == pytest.approx(1.0)
    assert groups["base"]["suggested_weight"] == pytest.approx(1.0)
    assert groups["left_arm"]["suggested_weight"] > 1.0
    assert report["num_episodes"] == 10
    assert not any("mixes" in w for w in report["warnings"])
    assert any(w.startswith("dim 6 (group 'torso') is constant") for w in report["warnings"])


def test_analysis_flags_the_classic_wrong_b1k_layout(config, tmp_path):
    wrong = config.copy_and_resolve_references()
    wrong.layout.groups = WRONG_GROUPS
    wrong.layout.real_dim = 23
    report = analyze_action_magnitudes.run(wrong, tmp_path / "wrong.json")
    mixed = sorted(w for w in report["warnings"] if "mixes" in w)
    assert len(mixed) == 2
    assert mixed[0].startswith("group 'grippers' (21, 23) mixes gripper-like dims [22] "
                               "(mass at two ends) with joint-like dims [21]")
    assert mixed[1].startswith("group 'right_arm' (14, 21) mixes gripper-like dims [14] "
                               "(mass at two ends) with joint-like dims [15, 16, 17, 18, 19, 20]")


def test_recompute_balanced_norm_stats_balances_and_reports(config, tmp_path):
    output = tmp_path / "balanced.json"
    stats, reports = recompute_balanced_norm_stats.run(config, output, max_scale=50.0)
    written = stats_lib.load_norm_stats(output)
    np.testing.assert_array_equal(written["actions"].std, stats["actions"].std)
    zscore = next(r for r in reports if r.mode == "zscore")
    moving = [v for v in zscore.after.values() if v > 0]
    np.testing.assert_allclose(moving, zscore.target, rtol=1e-9)
    text = recompute_balanced_norm_stats.format_reports(reports)
    assert "before" in text and "after" in text and "left_arm" in text


def test_filter_writes_the_manipulation_episodes(config, tmp_path):
    output = tmp_path / "arm_heavy.json"
    result = filter_arm_heavy_episodes.run(config, output)
    written = json.loads(output.read_text())
    assert written == result
    assert written["episodes"] == [1, 3, 5, 7, 9]  # 10 and 11 are held out
    assert written["thresholds"] == {"arm_ratio_threshold": 1.5, "min_arm_movement": 0.1,
                                     "max_base_movement": None}
    assert len(written["per_episode"]) == 10


def test_curriculum_on_the_fly_selects_what_the_filter_lists(config, tmp_path):
    layout = ActionLayout.from_config(config.layout)
    horizon = model_config_lib.from_model_config(config.model).action_horizon
    spec = DataSpec.from_config(config, layout)
    stats = dataset_lib.load_or_compute_norm_stats(spec, action_horizon=horizon)
    source = sources.open_source(spec.options, layout)
    table = source.load_table(dataset_lib.training_episodes(spec, source), images=False)
    listed = config.copy_and_resolve_references()
    listed.data.arm_heavy_episodes = str(tmp_path / "arm_heavy.json")
    filter_arm_heavy_episodes.run(config, listed.data.arm_heavy_episodes)
    on_the_fly = sampling.source_frames(table, spec, ("arm_heavy",), stats["actions"])
    from_file = sampling.source_frames(table, DataSpec.from_config(listed, layout),
                                       ("arm_heavy",), stats["actions"])
    np.testing.assert_array_equal(on_the_fly["arm_heavy"], from_file["arm_heavy"])


@pytest.mark.parametrize("tool", ["compute_norm_stats", "analyze_action_magnitudes",
                                  "recompute_balanced_norm_stats", "filter_arm_heavy_episodes"])
def test_command_line(config, tmp_path, tool):
    output = tmp_path / "out.json"
    command = [sys.executable, "-m", f"pi0_armfix.tools.{tool}",
               "--config=configs/uniform.py", f"--config.data.root={config.data.root}",
               "--config.eval.episodes=2", f"--output={output}"]
    result = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert result.returncode == 0, result.stderr[-3000:]
    assert output.is_file()
    assert "wrote" in result.stdout


def test_suggested_weights_are_capped_for_a_group_that_barely_moves():
    from pi0_armfix.tools import analyze_action_magnitudes as analyze

    rms = np.array([1.0, 0.01, 0.5, 0.5, 0.5, 0.5])  # torso barely moves
    weights = analyze.suggested_weights(LAYOUT, rms)
    assert weights["torso"] == analyze.MAX_SUGGESTED_WEIGHT and weights["left_arm"] == 2.0
    groups = {g: {"suggested_weight": w, "motion_normalized": {"rms": r}}
              for (g, w), r in zip(weights.items(), rms)}
    [warning] = analyze.capped_weight_warnings(groups)
    assert warning.startswith("torso barely moves (motion RMS 0.01 normalized units)")
