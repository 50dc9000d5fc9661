"""Episodes streamed front to back (pi0_armfix.data.pipeline.video_stream) on B1K 2025's layout: HEVC with
one keyframe per episode."""

import collections

import numpy as np
import pytest

import b1k_fixture
from data_fixtures import frame_colour, identify_frame
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats import video
from pi0_armfix.data.formats.lerobot import LeRobotSource
from pi0_armfix.data.pipeline import video_stream

LAYOUT = ActionLayout.preset("b1k_r1pro")


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    root = tmp_path_factory.mktemp("b1k") / "b1k"
    b1k_fixture.write_b1k_dataset(root)
    return LeRobotSource(root, LAYOUT, state_preset="b1k_r1pro").load_table()


def _stream(table, **changes):
    options = dict(seed=0, open_episodes=3, shuffle_window=8) | changes
    order = video_stream.episode_order(range(len(table.episode_lengths)), seed=options["seed"])
    return video_stream.stream_frames(table.images, order, **options)


def _identified(table, sample) -> tuple[int, int]:
    """(episode position, offset) of a sample, the offset read from the decoded head image."""
    frame = int(sample["frame"])
    position = int(table.episode_of_frame(np.array([frame]))[0])
    length = int(table.episode_lengths[position])
    decoded = identify_frame(sample["images"]["base_0_rgb"], position, length, 0)
    return position, decoded


def test_one_open_episode_without_a_shuffle_streams_each_episode_in_order_with_its_images(
        table):
    it = iter(_stream(table, open_episodes=1, shuffle_window=1))
    epoch = [next(it) for _ in range(table.num_frames)]
    it.close()
    assert sorted(int(s["frame"]) for s in epoch) == list(range(table.num_frames))
    for previous, sample in zip(epoch, epoch[1:]):
        (p0, o0), (p1, o1) = _identified(table, previous), _identified(table, sample)
        assert (p1, o1) == (p0, o0 + 1) or (o1 == 0 and o0 == table.episode_lengths[p0] - 1)
    for sample in epoch:
        position, decoded = _identified(table, sample)
        assert decoded == int(sample["frame"]) - int(table.episode_starts[position])


def test_every_frame_comes_once_per_epoch_with_episodes_open_and_a_shuffle(table):
    it = iter(_stream(table))
    epochs = 4
    counts = collections.Counter(int(next(it)["frame"]) for _ in range(epochs * table.num_frames))
    it.close()
    # Epochs overlap only where the last episodes of one are still open as the next begins.
    assert set(counts) == set(range(table.num_frames))
    assert min(counts.values()) >= epochs - 1 and max(counts.values()) <= epochs + 1


def test_each_episode_is_decoded_once_front_to_back(table):
    reader = table.images.episode_reader(2)
    for offset in range(reader.length):
        reader.images(offset)
    # One decode per frame and camera: no seek back to the keyframe.
    assert reader.decoded == reader.length * len(table.images.cameras)
    reader.close()


def test_a_stride_streams_every_kth_frame_from_a_first_frame_drawn_per_reading(table):
    it = iter(_stream(table, open_episodes=1, shuffle_window=1, stride=3))
    rows = [next(it) for _ in range(table.num_frames)]  # about three epochs of readings
    it.close()
    samples = [_identified(table, row) for row in rows]
    for row, (position, decoded) in zip(rows, samples):  # the image is the row's frame
        assert decoded == int(row["frame"]) - int(table.episode_starts[position])
    readings = [[samples[0]]]
    for previous, sample in zip(samples, samples[1:]):
        if sample[0] == previous[0] and sample[1] == previous[1] + 3:
            readings[-1].append(sample)
        else:
            readings.append([sample])
    for reading in readings[:-1]:
        position, first = reading[0]
        assert first < 3 and reading[-1][1] + 3 >= table.episode_lengths[position]
    assert len({reading[0][1] for reading in readings}) > 1  # readings start at other frames


@pytest.mark.parametrize("stride", [1, 3])
def test_a_restored_iterator_goes_on_exactly_where_its_state_was_taken(table, stride):
    it = iter(_stream(table, stride=stride))
    for _ in range(23):  # mid-way through open episodes and a shuffle window
        next(it)
    state = it.get_state()
    expected = [next(it) for _ in range(40)]
    it.close()
    restored = iter(_stream(table, stride=stride))
    restored.set_state(state)
    again = [next(restored) for _ in range(40)]
    restored.close()
    assert [int(s["frame"]) for s in again] == [int(s["frame"]) for s in expected]
    for a, b in zip(again, expected):
        for camera in a["images"]:
            np.testing.assert_array_equal(a["images"][camera], b["images"][camera])


def test_the_seed_sets_the_order_and_processes_open_disjoint_episodes(table):
    def first_episodes(**changes):
        order = video_stream.episode_order(range(6), **{"seed": 0} | changes)
        return [order[i] for i in range(6 // changes.get("process_count", 1))]

    assert sorted(first_episodes()) == list(range(6))
    assert first_episodes() != first_episodes(seed=1)
    halves = [first_episodes(process_index=p, process_count=2) for p in (0, 1)]
    assert sorted(halves[0] + halves[1]) == list(range(6))
    order = video_stream.episode_order(range(6), seed=0)
    assert [order[i] for i in range(6)] != [order[i] for i in range(6, 12)]  # a new epoch


def test_open_episodes_bound_how_many_episodes_a_window_mixes(table):
    it = iter(_stream(table, open_episodes=2, shuffle_window=4))
    samples = [next(it) for _ in range(40)]
    it.close()
    positions = [_identified(table, s)[0] for s in samples]
    # Two episodes open, one replaced when it ends: a window of 4 sees at most 3 episodes.
    assert max(len(set(positions[i:i + 4])) for i in range(0, 40, 4)) <= 3
    assert len(collections.Counter(positions)) >= 3  # episodes are replaced as they end


def test_stream_options_below_one_are_an_error_naming_them(table):
    with pytest.raises(ValueError, match="open_episodes \\(0\\)"):
        _stream(table, open_episodes=0)


def _access(requested, keyframes):
    return video_stream.choose_access(requested, keyframes, open_episodes=16,
                                      shuffle_window=256)


def test_auto_streams_long_gop_video_and_reads_short_gop_video_on_request():
    mode, why = _access("auto", ("hevc 720x720 (head)", None))  # B1K 2025: one per episode
    assert mode == "stream" and "a long GOP" in why and "16 episodes" in why
    mode, why = _access("auto", ("hevc 720x720 (head)", 8))  # B1K 2026
    assert mode == "random" and "a keyframe every 8 frames" in why
    assert _access("auto", None)[0] == "random"  # no video camera


def test_random_reads_of_long_gop_video_say_they_are_slow_and_name_the_stream():
    mode, why = _access("random", ("hevc 720x720 (head)", None))
    assert mode == "random" and "slow" in why and "data.video_access='stream'" in why


def test_a_stream_the_data_or_config_cannot_have_is_an_error_naming_the_key_and_the_fix():
    with pytest.raises(ValueError, match="no camera of the dataset is a video"):
        _access("stream", None)
    with pytest.raises(ValueError, match="data.video_access = 'fast' must be one of"):
        _access("fast", None)
    with pytest.raises(ValueError, match="data.stream_stride = 0 must be >= 1"):
        video_stream.choose_access("stream", ("hevc 720x720 (head)", None), open_episodes=16,
                                   shuffle_window=256, stride=0)


def test_a_seek_into_a_long_gop_skips_unreferenced_frames_and_returns_the_same_frames(tmp_path):
    path = tmp_path / "long_gop.mp4"
    frames = np.stack([np.full((16, 16, 3), frame_colour(1, i, 0), np.uint8) for i in range(300)])
    video.write_video(path, frames, 30, "libx265", gop=1000,
                      options={"x265-params": "log-level=none"})
    every = video.VideoDecoder(path, 30)
    full = {i: every.frame_at(i / 30) for i in range(300)}  # front to back: nothing skipped
    assert every.decoded == 300
    for wanted in (250, 120, 299, 70):
        fresh = video.VideoDecoder(path, 30)
        np.testing.assert_array_equal(fresh.frame_at(wanted / 30), full[wanted])
        if wanted > video.SKIP_MARGIN:
            assert fresh.decoded < wanted  # unreferenced frames before the margin were skipped
        fresh.close()


def test_a_stream_draws_from_its_open_episodes_where_random_access_draws_from_all():
    from pi0_armfix.bench.video import sample_diversity

    diversity = sample_diversity(200, 300, open_episodes=4, window=16, stride=1, samples=2000,
                                 lags=(1,))
    # 2000 samples of episodes of ~300 frames, 4 open: about 4 + 2000 / 300 episodes.
    assert 4 <= diversity["stream"]["distinct"] <= 20
    assert diversity["stream"]["same@1"] > 0.1
    assert diversity["random access"]["distinct"] > 150
    assert diversity["random access"]["same@1"] < 0.02


@pytest.mark.slow  # a whole streamed pass per stride
def test_a_stride_reads_k_times_the_episodes_for_the_same_samples():
    from pi0_armfix.bench.video import sample_diversity

    read = {k: sample_diversity(400, 300, open_episodes=4, window=16, stride=k, samples=6000,
                                lags=(1,))["stream"]["distinct"] for k in (1, 4)}
    # 6000 samples of episodes of ~300 frames: ~4 + 20 episodes read, ~4 + 80 with a stride of 4.
    assert 15 <= read[1] <= 35 and 3 * read[1] <= read[4] <= 5 * read[1]


# Ten episodes: the first two long (1000 frames), the others 100; `arm_heavy` draws the first two.
_LENGTHS = np.array([1000, 1000] + [100] * 8)
_SOURCES = {"full": np.arange(10), "arm_heavy": np.array([0, 1])}


def _curriculum_order(phases, **options):
    from pi0_armfix.data.pipeline.curriculum import Curriculum, parse_curriculum

    curriculum = Curriculum(parse_curriculum(phases), seed=0)
    return video_stream.curriculum_episode_order(
        curriculum, [_SOURCES[name] for name in curriculum.sources], _LENGTHS,
        **dict(seed=0, global_batch_size=10, open_episodes=2) | options)


@pytest.mark.slow  # a long stream: the slow lane
def test_a_mix_opens_episodes_so_that_each_source_gets_its_weight_of_the_frames():
    order = _curriculum_order([(10, {"full": 0.5, "arm_heavy": 0.5})])
    opened = np.array([order[i] for i in range(2_000)])
    frames = _LENGTHS[opened]
    long_share = frames[opened < 2].sum() / frames.sum()
    # Half the frames from arm_heavy (all long), half from full (long in 2000 of its 2800); over
    # 2000 openings the share's sampling sd is ~0.003.
    assert abs(long_share - (0.5 + 0.5 * 2000 / 2800)) < 0.02
    assert set(opened.tolist()) == set(range(10))


def test_a_phase_switch_changes_the_episodes_opened_from_when_they_are_read():
    # Episodes average 280 frames; 2 open; batches of 10: phase 0 (steps < 56) covers the
    # openings read before sample 560, i.e. openings 0 .. 3.
    order = _curriculum_order([(56, {"arm_heavy": 1.0}), (100, {"full": 1.0})])
    opened = [order[i] for i in range(200)]
    assert set(opened[:4]) <= {0, 1}
    assert set(opened[4:]) - {0, 1}  # the full dataset from then on


def test_processes_open_alternate_openings_of_the_same_draw():
    mix = [(10, {"full": 1.0, "arm_heavy": 1.0})]
    single = _curriculum_order(mix)
    halves = [_curriculum_order(mix, process_index=p, process_count=2) for p in (0, 1)]
    assert [halves[i % 2][i // 2] for i in range(100)] == [single[i] for i in range(100)]
