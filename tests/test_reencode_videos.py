"""The re-encode tool: B1K's one-keyframe HEVC -> short-GOP video at the model's size, read like
any LeRobot dataset, the input untouched."""

import json
import subprocess
import sys
from pathlib import Path

import av
import numpy as np
import pytest

import b1k_fixture
from data_fixtures import identify_frame, make_episodes, write_dataset
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.tools.reencode_videos import reencode_dataset

LAYOUT = ActionLayout.preset("b1k_r1pro")
HEAD = "observation.images.rgb.head"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def b1k(tmp_path_factory):
    root = tmp_path_factory.mktemp("b1k") / "dataset"
    b1k_fixture.write_b1k_dataset(root)
    return root


@pytest.fixture(scope="module")
def reencoded(b1k, tmp_path_factory):
    output = tmp_path_factory.mktemp("out") / "b1k_16"
    reencode_dataset(b1k, output, size=16, gop=4, workers=2, progress=False)
    return output


def test_reencoded_frames_are_the_frames_at_the_same_timestamps(b1k, reencoded):
    source = LeRobotSource(reencoded, LAYOUT, state_preset="b1k_r1pro")
    table = source.load_table()
    for frame in range(0, table.num_frames, 5):
        episode = int(table.episode_of_frame(np.array([frame]))[0])
        offset = frame - int(table.episode_starts[episode])
        images = table.images(frame)
        for camera_number, camera in enumerate(source.cameras):
            assert images[camera].shape == (16, 16, 3)
            assert identify_frame(images[camera], episode, int(table.episode_lengths[episode]),
                                  camera_number) == offset


def test_keyframes_come_every_gop_frames(reencoded):
    video = sorted(reencoded.rglob(f"{HEAD}/*.mp4"))[0]
    with av.open(str(video)) as container:
        keyframes = [p.is_keyframe for p in container.demux(video=0) if p.size]
    assert len(keyframes) == 14  # episode 10 has 14 frames
    assert sum(keyframes) >= 14 // 4


def test_unused_video_features_are_left_out_and_info_says_the_new_shape(b1k, reencoded):
    features = json.loads((reencoded / "meta" / "info.json").read_text())["features"]
    videos = {n: f for n, f in features.items() if f["dtype"] == "video"}
    assert sorted(videos) == sorted(f"observation.images.rgb.{c}" for c in b1k_fixture.RGB)
    assert videos[HEAD]["shape"] == [16, 16, 3] and videos[HEAD]["info"]["video.codec"] == "h264"
    assert not list(reencoded.rglob("*depth*/*.mp4"))
    original = json.loads((b1k / "meta" / "info.json").read_text())["features"]
    assert original[HEAD]["shape"] == [24, 24, 3] and "observation.images.depth.head" in original


def test_the_data_files_are_shared_and_read_the_same(b1k, reencoded):
    first = LeRobotSource(b1k, LAYOUT, state_preset="b1k_r1pro").load_table(images=False)
    second = LeRobotSource(reencoded, LAYOUT, state_preset="b1k_r1pro").load_table(images=False)
    np.testing.assert_array_equal(np.asarray(first.actions), np.asarray(second.actions))
    parquet = sorted(reencoded.rglob("*.parquet"))[0]
    assert parquet.stat().st_ino == (b1k / parquet.relative_to(reencoded)).stat().st_ino


def test_refuses_an_existing_output_and_unknown_features(b1k, reencoded, tmp_path):
    with pytest.raises(ValueError, match="already exists"):
        reencode_dataset(b1k, reencoded)
    with pytest.raises(ValueError, match="observation.images.rgb.nose"):
        reencode_dataset(b1k, tmp_path / "x", features="observation.images.rgb.nose")
    no_video = write_dataset(tmp_path / "png", make_episodes(2), "v2.1")
    with pytest.raises(ValueError, match="no video features"):
        reencode_dataset(no_video, tmp_path / "y")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_the_command_line_prints_what_it_did(b1k, tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.tools.reencode_videos", f"--input={b1k}",
         f"--output={tmp_path / 'out'}", "--size=16", "--gop=2", "--workers=1",
         "--features=observation.images.rgb.head"],
        capture_output=True, text=True, check=True, cwd=REPO)
    assert "re-encoded 6 videos" in result.stdout and "--config.data.root=" in result.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "pi0_armfix.tools.reencode_videos", f"--input={tmp_path}",
         f"--output={tmp_path / 'other'}"], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode != 0 and "is not a LeRobot dataset root" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_a_dataset_assembled_from_symlinked_folders_is_carried_over_whole(tmp_path):
    source = write_dataset(tmp_path / "elsewhere", make_episodes(2), "v2.1", image_format="video")
    linked = tmp_path / "linked"
    linked.mkdir()
    for name in ("meta", "data", "videos"):
        (linked / name).symlink_to(source / name, target_is_directory=True)
    out = tmp_path / "out"
    done = reencode_dataset(linked, out, size=16, gop=2, workers=1, progress=False)
    assert done["files"] == 2 * 3  # episodes x cameras, found through the links
    assert sorted(p.name for p in (out / "data").rglob("*.parquet")) == [
        "episode_000000.parquet", "episode_000001.parquet"]


def test_an_input_without_rows_is_refused_before_any_encoding(tmp_path):
    source = write_dataset(tmp_path / "ds", make_episodes(2), "v2.1", image_format="video")
    for path in (source / "data").rglob("*.parquet"):
        path.unlink()
    with pytest.raises(ValueError, match="holds no parquet file to carry over"):
        reencode_dataset(source, tmp_path / "out", size=16, gop=2, workers=1, progress=False)
    assert not (tmp_path / "out").exists()
