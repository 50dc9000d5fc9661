"""`data.frame_cache`: video frames decoded once at the model's size are the pixels decoding on
request gives, built once per (data, size, decoder), and read like any table's images."""

import pickle

import jax
import numpy as np
import pytest

import g1_fixture
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.configs import arm_focused
from pi0_armfix.data.formats import image_store
from pi0_armfix.data.formats.image_store import StoredFrameImages
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.pipeline import dataset as dataset_lib
from pi0_armfix.data.pipeline import pipeline, video_stream
from pi0_armfix.data.pipeline.data_spec import DataSpec, Reading
from pi0_armfix.training import fingerprint

LAYOUT = ActionLayout.preset("g1_inspire")
SIZE = (32, 32)


@pytest.fixture(scope="module")
def g1_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("g1") / "G1-policy-train"
    g1_fixture.write_g1_dataset(root, lengths=(12, 10, 14))
    return root


def entries(cache):
    """The cache's entries (not its lock files)."""
    return sorted(p for p in (cache / "images").iterdir() if not p.name.startswith("."))


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("PI0_ARMFIX_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def source(root, frame_cache):
    return LeRobotSource(root, LAYOUT, frame_cache=frame_cache)


def test_cached_frames_are_the_pixels_decoding_on_request_gives(g1_root):
    episodes = [2, 0]
    decoded = source(g1_root, False).load_table(episodes, image_size=SIZE)
    cached = source(g1_root, True).load_table(episodes, image_size=SIZE)
    assert isinstance(cached.images, StoredFrameImages)
    assert cached.images.cameras == decoded.images.cameras
    for frame in range(cached.num_frames):
        for camera, image in decoded.images(frame).items():
            np.testing.assert_array_equal(cached.images(frame)[camera], image)


def test_cached_frames_fit_inside_the_model_size_with_the_aspect_kept(g1_root):
    image = source(g1_root, True).load_table([0], image_size=SIZE).images(0)
    (camera,) = image
    assert image[camera].shape == (24, 32, 3)  # 48x64 fit inside 32x32
    assert image[camera].dtype == np.uint8


def test_the_cache_is_built_once_and_read_by_every_later_table(g1_root, cache, monkeypatch):
    source(g1_root, True).load_table([0], image_size=SIZE)
    (entry,) = entries(cache)

    def refuse(*args, **kwargs):
        raise AssertionError("rebuilt a cache that exists")

    monkeypatch.setattr(image_store, "_build", refuse)
    table = source(g1_root, True).load_table([1, 2], image_size=SIZE)
    assert table.images(table.num_frames - 1)
    assert entries(cache) == [entry]


def test_another_image_size_is_another_cache_entry(g1_root, cache):
    small = source(g1_root, True).load_table([0], image_size=(16, 16)).images(0)
    large = source(g1_root, True).load_table([0], image_size=SIZE).images(0)
    assert len(entries(cache)) == 2
    (camera,) = small
    assert small[camera].shape == (12, 16, 3) and large[camera].shape == (24, 32, 3)


def test_a_changed_video_file_is_another_cache_entry(tmp_path, cache):
    root = tmp_path / "G1"
    g1_fixture.write_g1_dataset(root, lengths=(8, 6))
    source(root, True).load_table(image_size=SIZE)
    video = next((root / "videos").rglob("episode_000001.mp4"))
    video.write_bytes(video.read_bytes())  # a new modification time: a new download
    source(root, True).load_table(image_size=SIZE)
    assert len(entries(cache)) == 2


def test_stored_frames_pickle_as_their_files_for_worker_processes(g1_root):
    images = source(g1_root, True).load_table([1], image_size=SIZE).images
    copy = pickle.loads(pickle.dumps(images))
    assert len(pickle.dumps(images)) < 2000
    for frame in range(10):
        np.testing.assert_array_equal(copy(frame)["base_0_rgb"], images(frame)["base_0_rgb"])


def test_a_cache_the_disk_cannot_hold_is_refused_naming_the_key(g1_root, monkeypatch):
    class Full:
        free = 1000

    monkeypatch.setattr(image_store.shutil, "disk_usage", lambda path: Full)
    with pytest.raises(ValueError, match=r"data\.frame_cache: the decoded frames need .* "
                                         r"set data\.frame_cache=False"):
        source(g1_root, True).load_table(image_size=SIZE)


def test_a_run_reads_cached_frames_at_random_and_says_so(g1_root):
    spec = {"images": True, "frame_cache": True, "video_access": "auto", "stream_episodes": 16,
            "stream_shuffle": 256, "stream_stride": 4}
    mode, why = video_stream.run_access(Reading.from_options(spec), source(g1_root, True))
    assert mode == "random" and "frame cache (data.frame_cache)" in why


def test_streaming_cached_frames_is_refused_naming_both_keys(g1_root):
    spec = {"images": True, "frame_cache": True, "video_access": "stream", "stream_episodes": 16,
            "stream_shuffle": 256, "stream_stride": 4}
    with pytest.raises(ValueError, match="data.video_access='auto' or data.frame_cache=False"):
        video_stream.run_access(Reading.from_options(spec), source(g1_root, True))


def test_a_run_resumes_with_the_frame_cache_switched():
    changed, _ = fingerprint.differences({"data": {"frame_cache": False}},
                                         {"data": {"frame_cache": True}})
    assert changed == []


def test_training_batches_are_the_same_with_the_frame_cache(g1_root, tmp_path):
    """What makes the key an execution key: a run may switch it and resume."""

    def batches(frame_cache):
        config = arm_focused.get_config("g1")
        config.update_from_flattened_dict({"data.root": str(g1_root), "data.num_workers": 0,
                                           "data.frame_cache": frame_cache, "eval.episodes": 1})
        layout = ActionLayout.from_config(config.layout)
        spec = DataSpec.from_config(config, layout)
        stats = dataset_lib.load_or_compute_norm_stats(
            spec, action_horizon=4, cache_path=tmp_path / f"norm_stats_{frame_cache}.json")
        run = pipeline.make_train_iterator(
            spec, norm_stats=stats, action_horizon=4, global_batch_size=4, image_size=SIZE,
            tokenize=lambda prompt: (np.array([len(prompt)], np.int32), np.array([True])),
            sharding=jax.sharding.SingleDeviceSharding(jax.devices()[0]))
        return [jax.tree.map(np.asarray, next(run)) for _ in range(3)]

    for cached, decoded in zip(batches(True), batches(False)):
        assert jax.tree.structure(cached) == jax.tree.structure(decoded)
        for a, b in zip(jax.tree.leaves(cached), jax.tree.leaves(decoded)):
            np.testing.assert_array_equal(a, b)
