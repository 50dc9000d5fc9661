"""Frames by timestamp from mp4 files (pi0_armfix.data.video.VideoDecoder)."""

import numpy as np

from data_fixtures import frame_colour
from pi0_armfix.data import video


def test_every_frame_of_an_open_gop_hevc_file_with_b_frames_is_read_in_any_order(tmp_path):
    # x265's defaults: open GOPs and B-frames; a keyframe every 8 frames decodes before the frames
    # shown just before it, so a seek by time alone lands after them.
    path = tmp_path / "open_gop.mp4"
    frames = np.stack([np.full((16, 16, 3), frame_colour(2, i, 0), np.uint8) for i in range(96)])
    video.write_video(path, frames, 30, "libx265", gop=8,
                      options={"x265-params": "log-level=none"})
    in_order = [image for _, image in video.VideoDecoder(path, 30).frames()]
    assert len(in_order) == 96
    shuffled = np.random.default_rng(0).permutation(96)
    for wanted in shuffled[:40]:  # a fresh decoder: the first read seeks
        fresh = video.VideoDecoder(path, 30)
        np.testing.assert_array_equal(fresh.frame_at(wanted / 30), in_order[wanted])
        fresh.close()
    shared = video.VideoDecoder(path, 30)  # one decoder: reads behind its position seek back
    for wanted in shuffled:
        np.testing.assert_array_equal(shared.frame_at(wanted / 30), in_order[wanted])
