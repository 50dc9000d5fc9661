"""The Grain training pipeline: batch contents, determinism, sharding, resumption, held-out data."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from absl import flags

from pi0_armfix.configs import base as base_config
from data_fixtures import B1K_CAMERAS, make_episodes, write_dataset
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.cameras import BATCH_CAMERAS
from pi0_armfix.data.episodes import EpisodeTable
from pi0_armfix.data.formats import sources, video
from pi0_armfix.data.pipeline import batching, pipeline, transforms
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline.data_spec import DataSpec
from pi0_armfix.data.statistics import normalize
from pi0_armfix.data.statistics import stats as stats_lib
from pi0_armfix.model import tokenizer as tokenizer_lib

LAYOUT = ActionLayout.preset("b1k_r1pro")
REPO = Path(__file__).resolve().parents[1]
HORIZON = 4


class ColourImages:
    """Two of the three batch cameras; every pixel of frame f is f % 256 (picklable)."""

    cameras = ("base_0_rgb", "left_wrist_0_rgb")

    def __call__(self, frame):
        return {camera: np.full((4, 5, 3), frame % 256, np.uint8) for camera in self.cameras}


class CountingTokenizer:
    def __init__(self):
        self.calls = []

    def __call__(self, prompt):
        self.calls.append(prompt)
        return np.array([len(prompt), 1, 0], np.int32), np.array([True, True, False])


def frame_table(lengths=(7, 3, 12, 5, 9, 1, 6), seed=0) -> EpisodeTable:
    """Actions whose dim 0 is the global frame index (so a batch tells which frames it holds)."""
    rng = np.random.default_rng(seed)
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    n = int(starts[-1])
    actions = rng.normal(size=(n, 23)).astype(np.float32)
    actions[:, 0] = np.arange(n)
    return EpisodeTable(actions=actions, state=rng.normal(size=(n, 20)).astype(np.float32),
                        episode_starts=starts, episode_index=np.arange(len(lengths)) + 100,
                        tasks=[f"task {e % 2}" for e in range(len(lengths))],
                        images=ColourImages())


def spec_of(data=None, seed=0):
    """The data spec of a run on an in-memory table: z-score, every episode trains."""
    return DataSpec.from_config({"seed": seed, "data": {"norm": "zscore", **(data or {})}},
                                LAYOUT)


def table_stats(table):
    return stats_lib.compute_norm_stats(stats_lib.table_blocks(table), progress=False)


def batches_of(table, *, batch_size=8, steps=6, data=None, seed=0, process_index=0,
               process_count=1, actions_only=True, tokenize=None):
    dataset = pipeline.train_batches(
        table, spec_of(data, seed), norm_stats=table_stats(table), action_horizon=HORIZON,
        global_batch_size=batch_size, process_index=process_index, process_count=process_count,
        tokenize=tokenize, actions_only=actions_only)
    return [dataset[i] for i in range(steps)]


def frames_of(table, batch):
    """The frame index of each sample of a batch (dim 0 of its first action)."""
    normalizer = normalize.Normalizer.from_stats(table_stats(table)["actions"], "zscore")
    return np.rint(normalizer.inverse(batch["actions"][:, 0])[:, 0]).astype(int)


def single_device_sharding():
    mesh = jax.make_mesh((1,), ("batch",), axis_types=(jax.sharding.AxisType.Auto,))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))


def iterator_of(table, *, batch_size=8, seed=0, num_workers=0):
    spec = spec_of(seed=seed)
    dataset = pipeline.train_batches(
        table, spec, norm_stats=table_stats(table), action_horizon=HORIZON,
        global_batch_size=batch_size, actions_only=True)
    return pipeline.TrainIterator(dataset, spec.curriculum, sharding=single_device_sharding(),
                                  global_batch_size=batch_size, seed=seed,
                                  num_workers=num_workers)


# ---------------------------------------------------------------------- batch contents

def test_batch_has_the_contract_keys_shapes_and_dtypes():
    table = frame_table()
    batch = batches_of(table, steps=1, actions_only=False, tokenize=CountingTokenizer())[0]
    assert batch["state"].shape == (8, 32) and batch["state"].dtype == np.float32
    assert batch["actions"].shape == (8, HORIZON, 32) and batch["actions"].dtype == np.float32
    assert batch["action_is_pad"].shape == (8, HORIZON) and batch["action_is_pad"].dtype == bool
    assert batch["tokenized_prompt"].dtype == np.int32
    assert batch["tokenized_prompt"].shape == batch["tokenized_prompt_mask"].shape == (8, 3)
    assert batch["tokenized_prompt_mask"].dtype == bool
    assert set(batch["image"]) == set(batch["image_mask"]) == set(BATCH_CAMERAS)
    for camera in BATCH_CAMERAS:
        assert batch["image"][camera].shape == (8, 4, 5, 3)
        assert batch["image"][camera].dtype == np.uint8
        assert batch["image_mask"][camera].dtype == bool


def test_actions_only_batch_has_no_images_or_prompt():
    batch = batches_of(frame_table(), steps=1)[0]
    assert set(batch) == {"state", "actions", "action_is_pad"}


def test_actions_are_normalized_padded_chunks_of_the_sampled_frame():
    table = frame_table()
    stats = table_stats(table)
    action_norm = normalize.Normalizer.from_stats(stats["actions"], "zscore")
    state_norm = normalize.Normalizer.from_stats(stats["state"], "zscore")
    for batch in batches_of(table, steps=4):
        frames = frames_of(table, batch)
        index, is_pad = transforms.chunk_indices(frames, table.episode_starts, HORIZON)
        np.testing.assert_allclose(batch["actions"][..., :23], action_norm(table.actions[index]),
                                   atol=1e-5)
        np.testing.assert_array_equal(batch["actions"][..., 23:], 0)
        np.testing.assert_array_equal(batch["action_is_pad"], is_pad)
        np.testing.assert_allclose(batch["state"][:, :20], state_norm(table.state[frames]),
                                   atol=1e-5)
        np.testing.assert_array_equal(batch["state"][:, 20:], 0)


def test_missing_camera_is_zeros_and_masked_and_images_follow_the_frame():
    table = frame_table()
    batch = batches_of(table, steps=1, actions_only=False, tokenize=CountingTokenizer())[0]
    frames = frames_of(table, batch)
    assert not batch["image_mask"]["right_wrist_0_rgb"].any()
    assert (batch["image"]["right_wrist_0_rgb"] == 0).all()
    assert batch["image_mask"]["base_0_rgb"].all()
    np.testing.assert_array_equal(batch["image"]["base_0_rgb"][:, 0, 0, 0], frames % 256)


def test_each_prompt_is_tokenized_once_and_matches_its_episode():
    table = frame_table()
    tokenize = CountingTokenizer()
    batch = batches_of(table, steps=3, actions_only=False, tokenize=tokenize)[-1]
    assert sorted(tokenize.calls) == ["task 0", "task 1"]
    episodes = table.episode_of_frame(frames_of(table, batch))
    np.testing.assert_array_equal(batch["tokenized_prompt"][:, 0],
                                  [len(table.tasks[e]) for e in episodes])


def test_training_batches_need_a_tokenizer():
    with pytest.raises(ValueError, match="tokenize"):
        batches_of(frame_table(), actions_only=False)


def test_a_dataset_without_cameras_gives_masked_zero_images_of_the_model_size():
    table = frame_table()
    table.images = None
    transform = batching.BatchTransform(
        table, LAYOUT, norm_stats=table_stats(table), norm_mode="zscore", action_horizon=4,
        tokenize=CountingTokenizer(), image_size=(16, 24))
    batch = transform(np.arange(3))
    for camera in BATCH_CAMERAS:
        assert batch["image"][camera].shape == (3, 16, 24, 3)
        assert not batch["image"][camera].any() and not batch["image_mask"][camera].any()


def test_delta_actions_are_relative_to_the_current_state():
    table = frame_table()
    table.state = np.concatenate([table.actions[:, :20] + 0.5], axis=1)
    data = {"delta_action_mask": list(range(7, 14)),
            "state_groups": {"left_arm": (7, 14)}}
    stats = dataset_lib.block_norm_stats(stats_lib.table_blocks(table), spec_of(data),
                                         action_horizon=HORIZON, progress=False)
    dataset = pipeline.train_batches(table, spec_of(data), norm_stats=stats,
                                     action_horizon=HORIZON, global_batch_size=8,
                                     actions_only=True)
    batch = dataset[0]
    raw = normalize.Normalizer.from_stats(stats["actions"], "zscore").inverse(batch["actions"])
    frames = np.rint(raw[:, 0, 0]).astype(int)
    index, _ = transforms.chunk_indices(frames, table.episode_starts, HORIZON)
    expected = table.actions[index][..., 7:14] - table.state[frames][:, None, 7:14]
    np.testing.assert_allclose(raw[..., 7:14], expected, atol=1e-4)


def arm_table() -> EpisodeTable:
    """B1K-like left arm (dims 7..13): a random walk the state follows closely, so a frame's own
    delta `a[t] - s[t]` is tiny next to a chunk's `a[t + h] - s[t]`."""
    table = frame_table()
    rng = np.random.default_rng(1)
    table.actions[:, 7:14] = np.cumsum(rng.normal(size=(table.num_frames, 7)), axis=0)
    table.state[:, 7:14] = table.actions[:, 7:14] + 0.01 * rng.normal(size=(table.num_frames, 7))
    return table


ARM_DELTA = {"delta_action_mask": list(range(7, 14)), "state_groups": {"left_arm": (7, 14)}}


def chunk_targets(table, norm_stats):
    """`[frames * H, 23]` float64: the action targets of every chunk of the table as batched."""
    mask = transforms.delta_action_mask(ARM_DELTA["delta_action_mask"], LAYOUT)
    transform = batching.BatchTransform(table, LAYOUT, norm_stats=norm_stats, norm_mode="zscore",
                                        action_horizon=HORIZON, delta_mask=mask,
                                        actions_only=True)
    return transform(np.arange(table.num_frames))["actions"][..., :23].reshape(-1, 23).astype(
        np.float64)


def passthrough_stats(width):
    """Stats the normalizer leaves values unchanged with: mean 0 and std + eps = 1."""
    return stats_lib.NormStats(mean=np.zeros(width), std=np.full(width, 1.0 - normalize.EPS),
                               q01=-np.ones(width), q99=np.ones(width))


def test_delta_action_stats_are_over_every_chunk_step_the_batches_hold():
    table = arm_table()
    stats = dataset_lib.block_norm_stats(stats_lib.table_blocks(table, block_frames=5),
                                         spec_of(ARM_DELTA), action_horizon=HORIZON,
                                         progress=False)
    targets = chunk_targets(table, {"actions": passthrough_stats(23),
                                    "state": passthrough_stats(20)})
    arm = slice(7, 14)
    np.testing.assert_allclose(stats["actions"].mean[arm], targets[:, arm].mean(0), rtol=1e-9)
    np.testing.assert_allclose(stats["actions"].std[arm], targets[:, arm].std(0), rtol=1e-9)
    data_range = np.ptp(targets[:, arm], axis=0)
    np.testing.assert_array_less(
        np.abs(stats["actions"].q99[arm] - np.quantile(targets[:, arm], 0.99, axis=0)),
        2 * data_range / stats_lib.DEFAULT_BINS)
    absolute = np.r_[0:7, 14:23]  # per frame, each frame once
    np.testing.assert_allclose(stats["actions"].mean[absolute],
                               table.actions[:, absolute].mean(0, dtype=np.float64), rtol=1e-9)


def test_normalized_delta_targets_have_unit_std():
    table = arm_table()
    stats = dataset_lib.block_norm_stats(stats_lib.table_blocks(table), spec_of(ARM_DELTA),
                                         action_horizon=HORIZON, progress=False)
    normalized = chunk_targets(table, stats)[:, 7:14]
    np.testing.assert_allclose(normalized.std(0), 1.0, atol=1e-3)
    np.testing.assert_allclose(normalized.mean(0), 0.0, atol=1e-3)


def test_delta_actions_with_a_mismatched_state_layout_fail_before_any_batch():
    data = {"norm": "zscore", "delta_action_mask": list(range(15, 22)),
            "state_groups": {"right_arm": (14, 21)}}
    with pytest.raises(ValueError, match="'right_arm' is at"):
        batches_of(frame_table(), data=data)


# ---------------------------------------------------------------------- order

def test_an_epoch_visits_every_frame_once():
    table = frame_table()
    batches = batches_of(table, batch_size=5, steps=table.num_frames // 5)
    frames = np.concatenate([frames_of(table, b) for b in batches])
    assert len(np.unique(frames)) == len(frames)


def test_same_seed_same_batches_other_seed_other_batches():
    table = frame_table()
    first, again = batches_of(table), batches_of(table)
    other = batches_of(table, seed=1)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a["actions"], b["actions"])
    assert any((a["actions"] != c["actions"]).any() for a, c in zip(first, other))


def test_processes_read_disjoint_halves_of_each_global_batch():
    table = frame_table()
    whole = batches_of(table, batch_size=8)
    halves = [batches_of(table, batch_size=8, process_index=p, process_count=2) for p in (0, 1)]
    for step, batch in enumerate(whole):
        for key in batch:
            np.testing.assert_array_equal(
                np.concatenate([halves[0][step][key], halves[1][step][key]]), batch[key])


def test_global_batch_must_split_over_processes():
    with pytest.raises(ValueError, match="train.batch_size = 9"):
        batches_of(frame_table(), batch_size=9, process_count=2)


def test_resumed_iterator_continues_exactly():
    table = frame_table()
    run = iterator_of(table)
    for _ in range(5):
        next(run)
    state = json.loads(json.dumps(run.get_state()))
    expected = [np.asarray(next(run)["actions"]) for _ in range(3)]
    resumed = iterator_of(table)
    resumed.set_state(state)
    assert resumed.step == 5
    for want in expected:
        np.testing.assert_array_equal(np.asarray(next(resumed)["actions"]), want)


def test_state_of_another_batch_size_is_rejected():
    run = iterator_of(frame_table(), batch_size=8)
    with pytest.raises(ValueError, match="global_batch_size = 4"):
        run.set_state({"step": 3, "global_batch_size": 4, "seed": 0})


def test_worker_processes_give_the_same_batches():
    flags.FLAGS.mark_as_parsed()  # grain's multiprocessing reads absl flags
    table = frame_table()
    in_process, workers = iterator_of(table), iterator_of(table, num_workers=2)
    try:
        for _ in range(4):
            np.testing.assert_array_equal(np.asarray(next(workers)["actions"]),
                                          np.asarray(next(in_process)["actions"]))
    finally:
        workers.close()


def test_global_arrays_are_sharded_over_the_batch_axis():
    script = textwrap.dedent("""
        import numpy as np, jax
        from tests.test_pipeline import frame_table, spec_of, table_stats
        from pi0_armfix.data.pipeline import pipeline
        table = frame_table()
        spec = spec_of()
        dataset = pipeline.train_batches(
            table, spec, norm_stats=table_stats(table), action_horizon=4, global_batch_size=8,
            actions_only=True)
        curriculum = spec.curriculum
        mesh = jax.make_mesh((4,), ("batch",), axis_types=(jax.sharding.AxisType.Auto,))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
        it = pipeline.TrainIterator(dataset, curriculum, sharding=sharding,
                                    global_batch_size=8, seed=0)
        batch = next(it)
        assert batch["actions"].shape == (8, 4, 32), batch["actions"].shape
        assert batch["actions"].sharding == sharding
        assert len(batch["actions"].addressable_shards) == 4
        np.testing.assert_array_equal(np.asarray(batch["actions"]), dataset[0]["actions"])
        print("ok")
    """)
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4",
           "JAX_PLATFORMS": "cpu", "PYTHONPATH": f"{REPO}:{REPO / 'tests'}"}
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("ok")


@pytest.mark.slow
def test_data_workers_closed_with_batches_in_flight_end_without_a_resource_tracker_warning(
        tmp_path):
    script = tmp_path / "workers.py"
    script.write_text(textwrap.dedent("""
        from absl import flags
        from tests.test_pipeline import frame_table, iterator_of

        if __name__ == "__main__":  # the workers are spawned: they import this file
            flags.FLAGS.mark_as_parsed()
            run = iterator_of(frame_table(), num_workers=2)
            for _ in range(2):
                next(run)
            run.close()
            print("ok")
    """))
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": f"{REPO}:{REPO / 'tests'}"}
    result = subprocess.run([sys.executable, str(script)], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-3000:]
    assert "resource_tracker" not in result.stderr, result.stderr[-3000:]


# ---------------------------------------------------------------------- config-level entry points

@pytest.fixture(scope="module")
def lerobot_config(tmp_path_factory):
    episodes = make_episodes(6, min_length=10, max_length=16)
    for e, episode in enumerate(episodes):
        episode["actions"][:, 0] = e  # dim 0 names the episode
    root = write_dataset(tmp_path_factory.mktemp("lerobot") / "ds", episodes, "v2.1")
    config = base_config.get_config()
    config.data.root = str(root)
    config.eval.episodes = 2
    return config


def test_held_out_video_frames_are_decoded_at_the_size_the_training_frames_are(tmp_path):
    cameras = {name: (48, 48) for name in B1K_CAMERAS}
    root = write_dataset(tmp_path / "ds", make_episodes(4, cameras=cameras), "v2.1",
                         image_format="video")
    config = base_config.get_config()
    config.data.root, config.eval.episodes = str(root), 1
    spec = DataSpec.from_config(config, ActionLayout.from_config(config.layout))
    heldout = dataset_lib.heldout_table(spec, image_size=(16, 16))
    full = dataset_lib.heldout_table(spec)
    first = int(heldout.episode_starts[0])
    for camera, image in heldout.images(first).items():
        assert image.shape == (16, 16, 3)
        np.testing.assert_array_equal(image, video.fit_frames(full.images(first)[camera],
                                                              (16, 16)))


def test_held_out_episodes_are_the_last_ones_and_never_trained_on(lerobot_config, tmp_path):
    layout = ActionLayout.from_config(lerobot_config.layout)
    heldout = dataset_lib.heldout_table(DataSpec.from_config(lerobot_config, layout))
    np.testing.assert_array_equal(heldout.episode_index, [4, 5])
    stats = dataset_lib.load_or_compute_norm_stats(DataSpec.from_config(lerobot_config, layout), action_horizon=HORIZON,
                                                cache_path=tmp_path / "norm_stats.json")
    run = pipeline.make_train_iterator(DataSpec.from_config(lerobot_config, layout), norm_stats=stats,
                                       action_horizon=HORIZON, global_batch_size=8,
                                       sharding=single_device_sharding(),
                                       tokenize=CountingTokenizer())
    normalizer = normalize.Normalizer.from_stats(
        stats_lib.fit_width(stats["actions"], 23, "actions"), "zscore")
    seen = set()
    for _ in range(12):
        batch = next(run)
        assert batch["image"]["base_0_rgb"].shape == (8, 16, 16, 3)
        seen |= set(np.rint(normalizer.inverse(np.asarray(batch["actions"])[:, 0])[:, 0]).tolist())
    assert seen == {0, 1, 2, 3}


def test_norm_stats_are_computed_once_then_read_from_the_cache(lerobot_config, tmp_path):
    layout = ActionLayout.from_config(lerobot_config.layout)
    cache = tmp_path / "norm_stats.json"
    computed = dataset_lib.load_or_compute_norm_stats(DataSpec.from_config(lerobot_config, layout), action_horizon=HORIZON,
                                                   cache_path=cache, progress=False)
    assert cache.is_file()
    stats_lib.save_norm_stats(cache, {k: v.replace(mean=v.mean + 1) for k, v in computed.items()})
    cached = dataset_lib.load_or_compute_norm_stats(DataSpec.from_config(lerobot_config, layout), action_horizon=HORIZON,
                                                 cache_path=cache)
    np.testing.assert_allclose(cached["actions"].mean, computed["actions"].mean + 1)


def test_norm_stats_cover_the_training_episodes_only(lerobot_config):
    layout = ActionLayout.from_config(lerobot_config.layout)
    stats = dataset_lib.dataset_norm_stats(DataSpec.from_config(lerobot_config, layout), action_horizon=HORIZON,
                                        progress=False)
    source = sources.open_source(lerobot_config.data, layout)
    training = source.load_table(source.episode_index[:4], images=False)
    np.testing.assert_allclose(stats["actions"].mean, np.asarray(training.actions).mean(0, dtype=np.float64),
                               rtol=1e-6, atol=1e-9)
    assert stats["actions"].q99[0] <= 3  # dim 0 is the episode: 4 and 5 are held out


def test_a_padded_norm_stats_file_serves_the_real_width(lerobot_config, tmp_path):
    layout = ActionLayout.from_config(lerobot_config.layout)
    stats = dataset_lib.dataset_norm_stats(DataSpec.from_config(lerobot_config, layout), action_horizon=HORIZON,
                                        progress=False)
    padded = {k: stats_lib.NormStats(*(np.pad(getattr(v, f), (0, 32 - v.width))
                                       for f in stats_lib.FIELDS)) for k, v in stats.items()}
    path = tmp_path / "padded.json"
    stats_lib.save_norm_stats(path, padded)
    config = lerobot_config.copy_and_resolve_references()
    config.data.norm_stats = str(path)
    loaded = dataset_lib.load_or_compute_norm_stats(DataSpec.from_config(config, layout), action_horizon=HORIZON)
    assert loaded["actions"].width == 23 and loaded["state"].width == 32
    run = pipeline.make_train_iterator(DataSpec.from_config(config, layout), norm_stats=loaded, action_horizon=HORIZON,
                                       global_batch_size=4, sharding=single_device_sharding(),
                                       actions_only=True)
    assert next(run)["state"].shape == (4, 32)


def test_too_many_held_out_episodes_is_an_error(lerobot_config):
    config = lerobot_config.copy_and_resolve_references()
    config.eval.episodes = 6
    with pytest.raises(ValueError, match="eval.episodes = 6"):
        dataset_lib.heldout_table(DataSpec.from_config(config, ActionLayout.from_config(config.layout)))


class StateTokenizer:
    """A pi0.5-style tokenizer: called per sample with the normalized state."""
    state_in_prompt = True

    def __init__(self):
        self.states = []

    def __call__(self, prompt, state):
        self.states.append(np.asarray(state))
        return np.array([len(prompt), 1, 0], np.int32), np.array([True, True, False])


def test_a_state_in_prompt_tokenizer_gets_each_samples_normalized_state():
    table = frame_table()
    stats = table_stats(table)
    tokenizer = StateTokenizer()
    transform = batching.BatchTransform(table, LAYOUT, norm_stats=stats, norm_mode="quantile",
                                        action_horizon=4, tokenize=tokenizer)
    batch = transform(np.array([0, 5, 9]))
    assert len(tokenizer.states) == 3
    # The same normalization, in float64 for the tokens (openpi's arithmetic, next test).
    np.testing.assert_allclose(np.stack(tokenizer.states),
                               batch["state"][:, :table.state.shape[1]], atol=1e-6)
    assert tokenizer.states[0].shape == (table.state.shape[1],)  # real dims, not padded


def test_a_state_in_prompt_tokenizer_gets_openpis_float64_normalization_exactly():
    table = frame_table()
    stats = table_stats(table)
    stats["state"] = stats["state"].replace(q99=stats["state"].q01.copy())  # constant dims too
    tokenizer = StateTokenizer()
    transform = batching.BatchTransform(table, LAYOUT, norm_stats=stats, norm_mode="quantile",
                                        action_horizon=4, tokenize=tokenizer)
    frames = np.array([0, 5, 9])
    transform(frames)
    x = np.asarray(table.state[frames], np.float64)
    q01, q99 = stats["state"].q01, stats["state"].q99
    openpi = (x - q01) / (q99 - q01 + 1e-6) * 2.0 - 1.0  # openpi's Normalize, quantile
    got = np.stack(tokenizer.states)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, openpi)
    np.testing.assert_array_equal(tokenizer_lib.state_bins(got), tokenizer_lib.state_bins(openpi))


PREVIOUS = {**ARM_DELTA, "delta_reference": "previous_action"}


def test_previous_action_reference_is_the_command_one_frame_before_and_the_start_at_a_first_frame():
    table = arm_table()
    frames = np.array([0, 1, 6, 7, 8])  # episodes start at 0 and 7
    mean = table.actions.mean(0)
    start = transforms.EpisodeStart.of(_plain_stats(table), LAYOUT, None)  # no state map
    reference = transforms.delta_reference("previous_action", table.actions, table.state,
                                           frames, table.episode_starts, start)
    np.testing.assert_array_equal(reference[[1, 2, 4]], table.actions[[0, 5, 7]])
    np.testing.assert_allclose(reference[[0, 3]], np.stack([mean, mean]), rtol=1e-5)


def _plain_stats(table):
    """A previous-action run's plain stats: the means each episode starts from."""
    stats = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), progress=False)
    return {**stats, stats_lib.ABSOLUTE_ACTIONS: stats["actions"]}


def test_an_episode_starts_from_the_state_and_its_mean_offset_where_it_holds_the_joint_never_for_a_velocity_or_gripper():
    table = arm_table()
    stats = _plain_stats(table)
    mean = stats["actions"].mean
    # the state (20-D) in the action order: the base (a velocity command) and the left gripper (an
    # open/close command) are placed too, but only the joints start from it
    placed = {g: LAYOUT.groups[g] for g in ("base", "torso", "left_arm", "left_gripper")}
    start = transforms.EpisodeStart.of(stats, LAYOUT, placed)
    reference = transforms.delta_reference("previous_action", table.actions, table.state,
                                           np.array([0, 7]), table.episode_starts, start)
    joints = np.r_[LAYOUT.group_dims("torso"), LAYOUT.group_dims("left_arm")]
    others = np.setdiff1d(np.arange(LAYOUT.real_dim), joints)
    offset = mean[joints] - stats["state"].mean[joints]
    np.testing.assert_allclose(reference[:, joints], table.state[[0, 7]][:, joints] + offset,
                               rtol=1e-6)
    np.testing.assert_allclose(reference[:, others], np.stack([mean, mean])[:, others], rtol=1e-6)


def test_an_arm_commanded_at_a_steady_offset_from_its_state_starts_at_its_first_command():
    table = arm_table()  # the left arm idle, its command 0.5 rad from the measured position
    table.actions[:, 7:14] = table.actions[0, 7:14]
    table.state[:, 7:14] = table.actions[:, 7:14] - 0.5
    start = transforms.EpisodeStart.of(_plain_stats(table), LAYOUT,
                                       {"left_arm": LAYOUT.groups["left_arm"]})
    firsts = table.episode_starts[:-1]
    reference = transforms.delta_reference("previous_action", table.actions, table.state,
                                           firsts, table.episode_starts, start)
    np.testing.assert_allclose(reference[:, 7:14], table.actions[firsts, 7:14], atol=1e-5)


def _previous_action_stats(table, block_frames=5):
    """The norm stats of a previous-action run on `table`, as `dataset_norm_stats` makes them:
    the plain stats first (where each episode starts), then the chunk deltas."""
    absolute = stats_lib.compute_norm_stats(stats_lib.table_blocks(table), progress=False)
    return dataset_lib.block_norm_stats(stats_lib.table_blocks(table, block_frames=block_frames),
                                        spec_of(PREVIOUS), action_horizon=HORIZON,
                                        progress=False, absolute=absolute)


def test_delta_actions_relative_to_the_previous_action_round_trip_to_the_true_chunks():
    table = arm_table()
    spec = spec_of(PREVIOUS)
    stats = _previous_action_stats(table)
    transform = batching.BatchTransform(table, LAYOUT, norm_stats=stats, norm_mode="zscore",
                                        action_horizon=HORIZON, delta_mask=spec.delta_mask,
                                        delta_reference=spec.delta_reference,
                                        actions_only=True)
    frames = np.arange(table.num_frames)
    index, _ = transforms.chunk_indices(frames, table.episode_starts, HORIZON)
    np.testing.assert_allclose(transform.absolute_actions(transform(frames)["actions"], frames),
                               table.actions[index], atol=1e-4)


def test_previous_action_delta_stats_are_over_the_chunk_steps_the_batches_hold():
    table = arm_table()
    stats = _previous_action_stats(table)
    frames = np.arange(table.num_frames)
    index, _ = transforms.chunk_indices(frames, table.episode_starts, HORIZON)
    previous = transforms.previous_frames(frames, table.episode_starts)
    first = previous == frames
    # the state places the left arm: an episode starts from its state and mean offset there
    offset = table.actions[:, 7:14].mean(0, dtype=np.float64) - table.state[:, 7:14].mean(
        0, dtype=np.float64)
    reference = np.where(first[:, None], table.state[:, 7:14] + offset,
                         table.actions[previous, 7:14])
    targets = (table.actions[index][..., 7:14] - reference[:, None]).reshape(-1, 7)
    np.testing.assert_allclose(stats["actions"].mean[7:14], targets.mean(0, dtype=np.float64),
                               atol=1e-5)
    np.testing.assert_allclose(stats["actions"].std[7:14], targets.std(0, dtype=np.float64),
                               atol=1e-5)


def _velocity_arm_table() -> EpisodeTable:
    """A single arm commanded by joint velocities (dims 7..13, ~0.01) whose state holds its joint
    positions (~1.5 rad, dims 7..13 too): subtracting the state from a velocity mixes units."""
    table = frame_table()
    rng = np.random.default_rng(2)
    velocity = 0.01 * rng.normal(size=(table.num_frames, 7))
    table.actions[:, 7:14] = velocity
    table.state[:, 7:14] = 1.5 + np.cumsum(velocity, axis=0)
    return table


def test_an_episodes_start_never_mixes_a_velocity_command_with_the_position_state():
    table = _velocity_arm_table()
    stats = _previous_action_stats(table)
    transform = batching.BatchTransform(
        table, LAYOUT, norm_stats=stats, norm_mode="zscore", action_horizon=HORIZON,
        delta_mask=spec_of(PREVIOUS).delta_mask, delta_reference="previous_action",
        actions_only=True)
    firsts = table.episode_starts[:-1]
    reference = transform.reference(firsts)[:, 7:14]
    np.testing.assert_allclose(reference, np.broadcast_to(table.actions[:, 7:14].mean(0),
                                                          reference.shape), atol=1e-6)
    assert np.abs(reference).max() < 0.1  # a velocity, never the ~1.5 rad of the state
    deltas = transform(firsts)["actions"][..., 7:14]  # normalized: no chunk sits far off
    assert np.abs(deltas).max() < 10


def test_the_previous_action_reference_needs_no_state_map():
    # another set than the demo (whose state preset would place the groups)
    data = {"root": "/data/velocity_arm", "delta_action_mask": list(range(7, 14))}
    spec, table = spec_of({**data, "delta_reference": "previous_action"}), _velocity_arm_table()
    pipeline._batch_transform(table, spec, norm_stats=_previous_action_stats(table),
                                  action_horizon=HORIZON, tokenize=None, actions_only=True)
    with pytest.raises(ValueError, match="data.delta_action_mask needs data.state_groups"):
        pipeline._batch_transform(table, spec_of(data),
                                      norm_stats=table_stats(table), action_horizon=HORIZON,
                                      tokenize=None, actions_only=True)


def test_the_statistics_of_previous_action_runs_have_their_own_cache_key():
    table = arm_table()
    source = type("S", (), {"episode_index": np.arange(table.num_episodes),
                            "episode_lengths": np.diff(table.episode_starts), "root": ""})()
    keys = [dataset_lib.norm_stats_key(spec_of(data), source, action_horizon=HORIZON)
            for data in (ARM_DELTA, PREVIOUS)]
    assert "data.delta_reference" not in keys[0] and "episode_start" not in keys[0]
    assert keys[1]["data.delta_reference"] == "previous_action"
    assert keys[1]["episode_start"] == transforms.EPISODE_START


def _keyed_cache(folder, key_changes):
    """A run folder's norm stats beside a key of the previous-action statistics, changed."""
    table = arm_table()
    source = type("S", (), {"episode_index": np.arange(table.num_episodes),
                            "episode_lengths": np.diff(table.episode_starts), "root": ""})()
    key = dataset_lib.norm_stats_key(spec_of(PREVIOUS), source, action_horizon=HORIZON)
    for entry, value in key_changes.items():
        if value is None:
            del key[entry]
        else:
            key[entry] = value
    cache = folder / dataset_lib.NORM_STATS_FILE
    stats_lib.save_norm_stats(cache, table_stats(table))
    cache.with_name("norm_stats.key.json").write_text(json.dumps(key))
    return cache, source


def test_resuming_a_run_whose_statistics_predate_the_episode_start_rule_names_the_rule_and_fix(
        tmp_path):
    cache, source = _keyed_cache(tmp_path, {"episode_start": None})
    with pytest.raises(ValueError, match=r"started from the state \(an earlier rule\); today it "
                                         r"starts from .*--config.train.resume=force"):
        dataset_lib.load_or_compute_norm_stats(spec_of(PREVIOUS), action_horizon=HORIZON,
                                               cache_path=cache, source=source, resuming=True)


@pytest.mark.parametrize("changes, rule", [
    ({"episode_start": None}, ""),
    ({}, transforms.EPISODE_START),
    ({"data.delta_reference": None, "episode_start": None}, None),
])
def test_a_run_folder_names_the_episode_start_rule_its_statistics_were_computed_under(
        tmp_path, changes, rule):
    _keyed_cache(tmp_path, changes)
    assert dataset_lib.run_episode_start(tmp_path) == rule
    assert dataset_lib.run_episode_start(tmp_path / "elsewhere") is None


def test_an_unknown_delta_reference_is_an_error_naming_the_choices():
    with pytest.raises(ValueError, match=r"data.delta_reference = 'goal' is not one of"):
        spec_of({**ARM_DELTA, "delta_reference": "goal"})


def test_a_previous_action_reference_without_relative_dims_is_refused():
    with pytest.raises(ValueError, match=r"data.delta_reference = 'previous_action' makes no "
                                         r"dim relative: data.delta_action_mask is empty"):
        spec_of({"delta_reference": "previous_action"})


@pytest.mark.parametrize("groups, message", [
    ("left_arm", r"data.state_groups = 'left_arm' must map each group"),
    ({"base": (0, 3), "left_arm": (2, 9)}, r"places 'base' \(0, 3\) and 'left_arm' \(2, 9\) "
                                           r"over the same state dims"),
    ({"base": (3, 3)}, r"data.state_groups\['base'\] = \(3, 3\) must have 0 <= start < stop"),
])
def test_malformed_or_overlapping_state_groups_are_refused_naming_them(groups, message):
    with pytest.raises(ValueError, match=message):
        spec_of({"root": "/data/x", "state_groups": groups})


def test_state_groups_past_the_states_width_are_refused_before_any_pass(tmp_path):
    root = write_dataset(tmp_path / "ds", make_episodes(3), "v2.1")
    config = base_config.get_config()
    config.data.root = str(root)
    config.data.state_groups = {"base": (21, 24)}
    config.eval.episodes = 1
    spec = DataSpec.from_config(config, LAYOUT)
    source = sources.open_source(config.data, LAYOUT)
    with pytest.raises(ValueError, match=r"data.state_groups\['base'\] = \(21, 24\) reaches past "
                                         r"the state's 23 dims"):
        dataset_lib.check_data(spec, source, images=False)
