"""mp4 video through PyAV: frames by timestamp (`VideoDecoder`) and encoding (`VideoWriter`).

Reading cost is set by the file's GOP: a request that is not a little ahead of the decoder's
position seeks to the keyframe before it and decodes forward from there, so random access into a
file with one keyframe per episode (BEHAVIOR-1K 2025's HEVC) decodes half an episode on average;
on the way it skips the frames no other frame references (`SKIP_MARGIN`).
`python -m pi0_armfix.tools.reencode_videos` rewrites such a dataset with short GOPs at the
model's resolution; `python -m pi0_armfix.bench video` measures both.

Every camera frame reaches the model through one resize, `fit_frames` (libswscale's area filter on
RGB, to fit inside the model's image size with the aspect ratio kept, never up): a decoder asked
for a `size` applies it to each decoded frame (so a 720² frame is not kept at full size), the
batches of stored images apply it (`batching.BatchTransform`), and so does the served policy to
a client's images (`inference.RunPolicy`). Trained, held-out and served frames of one picture are
then the same pixels, and the model's resize-with-pad of a square camera has nothing left to do.
"""

from __future__ import annotations

import collections
import fractions
import itertools
import threading
from pathlib import Path

import numpy as np

from pi0_armfix.data.formats.files import unreadable

# Timestamps are float32: a row one frame late can compute to 1.0000114 frames. Time comparisons
# allow this much (in frames) beyond the tolerance they apply.
TIME_EPSILON_FRAMES = 1e-3
# Decoding towards a frame this many frames or more ahead skips the frames nothing references
# (`skip_frame="NONREF"`) until this close: a seek into a long GOP, a stream's restart. The margin
# covers the frames a decoder keeps (`max_frames`) and those in flight in its threads.
SKIP_MARGIN = 64


def fit_inside(height: int, width: int, size: tuple[int, int] | None) -> tuple[int, int]:
    """(height, width) scaled to fit inside `size` = (H, W) keeping the aspect ratio; never
    enlarged; even sides (what yuv420p needs). `size` None: unchanged."""
    if size is None:
        return height, width
    scale = min(size[0] / height, size[1] / width, 1.0)
    if scale == 1.0:
        return height, width
    return max(2, int(round(height * scale / 2)) * 2), max(2, int(round(width * scale / 2)) * 2)


_SCALERS = threading.local()  # one libswscale context per thread, kept across frames


def fit_frames(images: np.ndarray, size: tuple[int, int] | None) -> np.ndarray:
    """uint8 `[..., h, w, 3]` -> `[..., h', w', 3]` fitting inside `size` (`fit_inside`), by
    libswscale's area filter on RGB; unchanged when it already fits (see the module docstring)."""
    height, width = fit_inside(images.shape[-3], images.shape[-2], size)
    if (height, width) == images.shape[-3:-1]:
        return images
    import av  # PyAV is only needed where a frame is larger than the model's images

    scaler = getattr(_SCALERS, "scaler", None)
    if scaler is None:  # building a scaler per frame costs more CPU than the scaling itself
        scaler = _SCALERS.scaler = av.video.reformatter.VideoReformatter()
    flat = images.reshape(-1, *images.shape[-3:])
    out = np.stack([scaler.reformat(av.VideoFrame.from_ndarray(np.ascontiguousarray(image),
                                                                format="rgb24"),
                                    width=width, height=height, format="rgb24",
                                    interpolation="AREA").to_ndarray() for image in flat])
    return out.reshape(*images.shape[:-3], height, width, 3)


class VideoDecoder:
    """Frames of one mp4 by timestamp. Not thread-safe: use one per thread.

    Keeps the container open and the last `max_frames` decoded frames. A request a little ahead
    of the decoder's position (within `max_gap` frames) continues decoding forward; any other miss
    seeks to the keyframe before the requested time and decodes from there. A request is served
    by the frame nearest to it when that lies within `tolerance` frames (0.5: the nearest frame);
    otherwise it is an error naming the file, the time and the video's last frame.

    Args:
      path: the mp4 file.
      fps: the dataset's frame rate (frame numbers are `round(time * fps)`).
      tolerance: see above.
      size: (height, width) to fit frames inside (`fit_frames`, see the module docstring);
        None = as stored.
      max_frames, max_gap: see above.
      threads: decode with FFmpeg's frame and slice threads (a random reader: several times
        faster per frame); False for a reader of one of many streams decoded at once, where
        threads only add CPU per frame.
    """

    def __init__(self, path: Path, fps: float, tolerance: float = 0.5,
                 size: tuple[int, int] | None = None, max_frames: int = 32, max_gap: int = 32,
                 threads: bool = True):
        import av  # PyAV is only needed for video features

        self.path, self.fps, self.tolerance = Path(path), fps, tolerance
        self.max_frames, self.max_gap = max_frames, max_gap
        try:
            self._container = av.open(str(path))
            self._stream = self._container.streams.video[0]
        except (av.FFmpegError, IndexError) as err:
            raise unreadable(self.path, "video file", err) from err
        # Frame threads decode HEVC several times faster than one; slices as well for h264.
        if threads:
            self._stream.thread_type = "AUTO"
        context = self._stream.codec_context
        self.height, self.width = fit_inside(context.height, context.width, size)
        self._size = size
        self._frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._decoder = None
        self._position = -1  # number of the last frame the decoder returned
        self.decoded = 0  # frames decoded so far (what a request cost, for benchmarks)

    def close(self) -> None:
        self._container.close()

    def _seek(self, seconds: float) -> None:
        offset = int(max(seconds, 0.0) / self._stream.time_base)
        self._container.seek(offset, stream=self._stream, backward=True, any_frame=False)
        self._decoder = self._container.decode(self._stream)
        self._position = -1

    def _redecoding_frames(self, wanted: int, seek_from: float | None):
        """The decoder's frames; after a seek, seeks further back while its first frame comes
        after `wanted`. A container indexes keyframes by decoding time, and with B-frames an
        open-GOP keyframe (HEVC's CRA, x265's default) decodes before the frames shown just
        before it, which the decoder drops when it starts there: a seek to such a frame lands
        after it. Each retry goes twice as far back (from one GOP's worth of frames)."""
        back = 0.0
        while True:
            first = seek_from is not None
            for frame in self._decoder:
                if first:
                    first = False
                    number = (int(round(frame.time * self.fps)) if frame.time is not None
                              else 0)
                    if number > wanted and seek_from > 0:
                        self.decoded += 1
                        back = max(2 * back, self.max_gap / self.fps)
                        seek_from = max(wanted / self.fps - back, 0.0)
                        self._seek(seek_from)
                        break
                yield frame
            else:
                return

    def _array(self, frame) -> np.ndarray:
        return fit_frames(frame.to_ndarray(format="rgb24"), self._size)

    def frame_at(self, seconds: float) -> np.ndarray:
        """uint8 [h, w, 3], the frame nearest to `seconds` (within `tolerance` frames)."""
        import av

        wanted = int(round(seconds * self.fps))
        if wanted in self._frames:
            self._frames.move_to_end(wanted)
            return self._frames[wanted]
        seek_from = None  # seconds the decoder last sought to, while its first frame is due
        if self._decoder is None or not (self._position < wanted <= self._position + self.max_gap):
            seek_from = seconds
            self._seek(seek_from)
        context = self._stream.codec_context
        try:
            for frame in self._redecoding_frames(wanted, seek_from):
                self.decoded += 1
                # A stream without timestamps is numbered by decoding order from its start.
                number = (int(round(frame.time * self.fps)) if frame.time is not None
                          else self._position + 1)
                self._position = number
                # Far before the wanted frame, frames no other frame references are skipped
                # (decoding them would only draw them); the rest decode as always, so every
                # frame from `wanted - SKIP_MARGIN` on is decoded, identical to a full decode.
                # Only with timestamps: skipped frames would break numbering by order.
                far = frame.time is not None and wanted - number > SKIP_MARGIN
                if (context.skip_frame == "NONREF") != far:
                    context.skip_frame = "NONREF" if far else "DEFAULT"
                # Frames before the wanted one are kept only when a later request may want them.
                if number >= wanted - self.max_frames:
                    self._frames[number] = self._array(frame)
                    while len(self._frames) > self.max_frames:
                        self._frames.popitem(last=False)
                if number >= wanted:
                    break
        except av.FFmpegError as err:
            self._decoder = None
            raise unreadable(self.path, "video file", err) from err
        finally:
            context.skip_frame = "DEFAULT"
        if wanted in self._frames:
            return self._frames[wanted]
        nearest = min(self._frames, key=lambda n: abs(n - seconds * self.fps), default=None)
        if (nearest is not None
                and abs(nearest - seconds * self.fps) <= self.tolerance + TIME_EPSILON_FRAMES):
            return self._frames[nearest]
        self._decoder = None
        ended = self._position  # the last frame decoded: the video's end when it ran out
        last = ("no frame" if ended < 0 else f"its frame {ended} at {ended / self.fps:.4f} s")
        short = wanted - ended if ended >= 0 else None
        if short is not None and self.tolerance < short <= 2:
            advice = (f"If the data's timestamps run past the video by up to {short} frame(s), "
                      f"set data.video_tolerance_frames={short} to read the nearest frame")
        elif short is not None and short > 0:
            advice = (f"The video ends {short} frames before this row: it is shorter than its "
                      "rows (a cut or partial file): fetch or re-encode it, or leave the episode "
                      "out")
        else:
            advice = ("The data's timestamps and the video disagree by more than a frame or "
                      "two: check the dataset's fps and its videos")
        raise ValueError(
            f"{self.path} has no frame at {seconds:.4f} s (frame {seconds * self.fps:.2f} at "
            f"{self.fps:g} fps; decoding ended at {last}). {advice}")

    def frames(self):
        """Every frame in order from the start: yields (time in seconds or None, uint8 [h, w, 3])
        (the sequential read a re-encode needs; no seeking)."""
        import av

        self._container.seek(0, stream=self._stream, backward=True, any_frame=False)
        try:
            for frame in self._container.decode(self._stream):
                self.decoded += 1
                yield frame.time, self._array(frame)
        except av.FFmpegError as err:
            raise unreadable(self.path, "video file", err) from err
        finally:
            self._decoder = None

    def rate(self) -> float | None:
        """The stream's frame rate from the container (None if it does not say)."""
        rate = self._stream.average_rate or self._stream.guessed_rate
        return float(rate) if rate else None

    def last_frame_time(self) -> float | None:
        """Time of the video's last frame from the container's metadata (None if unknown)."""
        stream = self._stream
        if stream.frames:
            start = float(stream.start_time * stream.time_base) if stream.start_time else 0.0
            return start + (stream.frames - 1) / self.fps
        return None


def keyframe_interval(path: Path, packets: int = 256) -> tuple[str, int, int, int | None]:
    """`(codec, height, width, frames between keyframes)` of an mp4's video stream, from its
    first `packets` packets (demuxed, not decoded); the interval is None when they hold one
    keyframe only (a long GOP: a random read decodes from far back)."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        codec = stream.codec_context.name
        height, width = stream.codec_context.height, stream.codec_context.width
        keys = [i for i, packet in enumerate(itertools.islice(container.demux(stream), packets))
                if packet.is_keyframe]
    interval = int(np.median(np.diff(keys))) if len(keys) > 1 else None
    return codec, height, width, interval


class VideoWriter:
    """Encodes uint8 [h, w, 3] frames into an mp4, frame i at time i / fps (or a given time).

    Args:
      path: the mp4 to write (its folder is created).
      fps: frame rate.
      height, width: frame size.
      codec: PyAV encoder ("libx264", "libx265", "libsvtav1", ...).
      gop: frames between keyframes (2 as LeRobot writes; B1K 2025's files have one per episode).
      crf: constant rate factor (quality; lower is better).
      options: further encoder options. x265 writes closed GOPs (`no-open-gop=1`) unless its
        `x265-params` name `open-gop`: other readers (LeRobot's decoders among them) cannot seek
        into x265's default open GOPs, whose keyframes decode before frames shown ahead of them.
    """

    def __init__(self, path: Path, *, fps: float, height: int, width: int,
                 codec: str = "libx264", gop: int = 2, crf: int = 10,
                 options: dict[str, str] | None = None):
        import av

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fps = fractions.Fraction(fps).limit_denominator(1001)
        self._container = av.open(str(path), "w")
        self._stream = self._container.add_stream(codec, rate=self._fps)
        self._stream.height, self._stream.width = height, width
        self._stream.pix_fmt = "yuv420p"
        options = {"g": str(int(gop)), "crf": str(int(crf)), **(options or {})}
        if codec == "libx265" and "open-gop" not in options.get("x265-params", ""):
            options["x265-params"] = ":".join(
                p for p in ("no-open-gop=1", options.get("x265-params")) if p)
        self._stream.options = options
        self._count = 0

    def write(self, image: np.ndarray, seconds: float | None = None) -> None:
        """Appends a frame, at `seconds` (default: count / fps)."""
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        time_base = 1 / self._fps
        frame.pts = self._count if seconds is None else int(round(seconds * self._fps))
        frame.time_base = time_base
        self._container.mux(self._stream.encode(frame))
        self._count += 1

    def close(self) -> None:
        self._container.mux(self._stream.encode())
        self._container.close()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_video(path: Path, frames: np.ndarray, fps: float, codec: str = "libx264", *,
                gop: int = 2, crf: int = 10, options: dict[str, str] | None = None) -> None:
    """uint8 [n, h, w, 3] -> mp4 (see `VideoWriter`)."""
    with VideoWriter(path, fps=fps, height=frames.shape[1], width=frames.shape[2], codec=codec,
                     gop=gop, crf=crf, options=options) as writer:
        for image in frames:
            writer.write(image)
