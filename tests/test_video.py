"""Frames by timestamp from mp4 files (pi0_armfix.data.formats.video.VideoDecoder)."""

import numpy as np

from data_fixtures import frame_colour
from pi0_armfix.data.formats import video


def test_every_frame_of_an_open_gop_hevc_file_with_b_frames_is_read_in_any_order(tmp_path):
    # x265's defaults: open GOPs and B-frames; a keyframe every 8 frames decodes before the frames
    # shown just before it, so a seek by time alone lands after them.
    path = tmp_path / "open_gop.mp4"
    frames = np.stack([np.full((16, 16, 3), frame_colour(2, i, 0), np.uint8) for i in range(96)])
    video.write_video(path, frames, 30, "libx265", gop=8,
                      options={"x265-params": "log-level=none:open-gop=1"})
    assert 21 in _keyframe_nal_types(path)  # CRA: an open GOP
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


def _keyframe_nal_types(path):
    """The HEVC NAL unit types in the keyframe packets of an mp4 (19/20: IDR, 21: CRA)."""
    import av
    types = set()
    with av.open(str(path)) as container:
        for packet in container.demux(video=0):
            data = bytes(packet)
            if not packet.is_keyframe:
                continue
            offset = 0
            while offset + 5 <= len(data):  # length-prefixed NAL units
                size = int.from_bytes(data[offset:offset + 4], "big")
                types.add((data[offset + 4] >> 1) & 0x3F)
                offset += 4 + size
    return types


def test_hevc_written_by_the_project_has_closed_gops_that_any_reader_can_seek(tmp_path):
    path = tmp_path / "closed_gop.mp4"
    frames = np.stack([np.full((16, 16, 3), frame_colour(2, i, 0), np.uint8) for i in range(48)])
    video.write_video(path, frames, 30, "libx265", gop=8,
                      options={"x265-params": "log-level=none"})
    types = _keyframe_nal_types(path)
    assert types & {19, 20} and 21 not in types  # IDR keyframes only


def _textured_frames(count: int, size: int) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size] / size
    rng = np.random.default_rng(0)
    frames = [np.stack([128 + 100 * np.sin(6 * xx + t + 3 * yy), 128 + 100 * np.cos(9 * yy - t),
                        128 + 60 * np.sin(13 * (xx + yy))], -1) + rng.normal(0, 20, (size, size, 3))
              for t in range(count)]
    return np.clip(np.stack(frames), 0, 255).astype(np.uint8)


def test_a_decoder_asked_for_a_size_returns_the_one_resize_a_served_image_gets(tmp_path):
    path = tmp_path / "cam.mp4"
    video.write_video(path, _textured_frames(6, 96), 30)
    fitted, full = video.VideoDecoder(path, 30, size=(32, 32)), video.VideoDecoder(path, 30)
    for i in range(6):
        frame = fitted.frame_at(i / 30)
        assert frame.shape == (32, 32, 3)
        np.testing.assert_array_equal(frame, video.fit_frames(full.frame_at(i / 30), (32, 32)))


def test_fitting_keeps_the_aspect_ratio_never_enlarges_and_works_on_batches():
    images = _textured_frames(4, 64)[:, :, :48]  # [4, 64, 48, 3]
    fitted = video.fit_frames(images, (32, 32))
    assert fitted.shape == (4, 32, 24, 3)
    np.testing.assert_array_equal(fitted[2], video.fit_frames(images[2], (32, 32)))
    assert video.fit_frames(images, (128, 128)) is images
    # the area filter: a flat colour stays that colour
    flat = np.full((2, 90, 90, 3), 77, np.uint8)
    assert (video.fit_frames(flat, (30, 30)) == 77).all()
