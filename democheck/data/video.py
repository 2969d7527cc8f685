"""Video files: H.264 in MP4 through PyAV, with cheap random access.

Episodes are packed back to back in one file (LeRobot v3).  Every episode
starts on a keyframe and keyframes recur every ``GOP`` frames, so reading the
first and last frame of an episode decodes at most ``GOP`` frames, never the
whole episode.

Default pixel format is yuv444p: at 64x64 the chroma subsampling of yuv420p
alone caps PSNR near 35 dB on our scenes, while yuv444p at CRF 20 keeps
~43 dB (tests/test_data.py checks the bound) and allows odd frame sizes
such as 125x125.  yuv420p stays available for players that need it.
"""

from __future__ import annotations

import tempfile
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from democheck.errors import DatasetError

GOP = 10
DEFAULT_CODEC = "libx264"
# Frames decoded by this process so far (benchmarks and tests read it to check random access stays cheap).
frames_decoded = 0
DEFAULT_PIX_FMT = "yuv444p"
DEFAULT_CRF = 20
# ultrafast: ~35% less encoding time than veryfast and, at CRF 20, higher PSNR (~43 dB)
# for ~1.7x the bytes; encoding is the largest cost of generation after rendering.
PRESET = "ultrafast"


# Lossless: H.264 coding the RGB planes themselves at quantiser 0, so decoding gives back the very bytes written
# (YUV, even 4:4:4, rounds in the colour conversion).  democheck's reader (PyAV) plays it; not every player does.
LOSSLESS_CODEC = "libx264rgb"


def frame_size(size: int | tuple[int, int]) -> tuple[int, int]:
    """A camera's (height, width) from its side (square) or from (height, width)."""
    return (int(size), int(size)) if isinstance(size, (int, np.integer)) else (int(size[0]), int(size[1]))


class VideoWriter:
    """Append frames to an MP4; frame ``k`` of the file has timestamp ``k / fps``; ``lossless``: bit-exact."""

    def __init__(self, path: str | Path, fps: int, size: int | tuple[int, int], pix_fmt: str = DEFAULT_PIX_FMT,
                 crf: int = DEFAULT_CRF, lossless: bool = False):
        """``size``: the frames' side (square) or (height, width)."""
        height, width = frame_size(size)
        if pix_fmt == "yuv420p" and (height % 2 or width % 2) and not lossless:
            raise ValueError(f"yuv420p needs an even frame size, got {height}x{width}; use yuv444p")
        self.path = Path(path)
        self._container = av.open(str(self.path), "w", format="mp4")
        self._stream = self._container.add_stream(LOSSLESS_CODEC if lossless else DEFAULT_CODEC, rate=fps)
        self._stream.width, self._stream.height = width, height
        self._stream.pix_fmt = "rgb24" if lossless else pix_fmt
        self._stream.time_base = Fraction(1, fps)
        # One thread: x264's output then depends only on its input (determinism).
        quality = {"qp": "0"} if lossless else {"crf": str(crf)}
        self._stream.options = {**quality, "g": str(GOP), "preset": PRESET, "threads": "1"}
        self.frames = 0

    def write(self, frames: np.ndarray, new_episode: bool = True) -> tuple[int, int]:
        """Append uint8 [T, H, W, 3] frames; returns their (first, end) frame numbers in the file."""
        start = self.frames
        for i, img in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            frame.pts = self.frames
            if new_episode and i == 0:
                frame.pict_type = av.video.frame.PictureType.I
            for packet in self._stream.encode(frame):
                self._container.mux(packet)
            self.frames += 1
        return start, self.frames

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def through_codec(frames: np.ndarray, fps: int, pix_fmt: str = DEFAULT_PIX_FMT, crf: int = DEFAULT_CRF
                  ) -> np.ndarray:
    """``frames`` [T, H, W, 3] as a recording with these settings stores them: encoded by ``VideoWriter`` (a
    keyframe first and every ``GOP`` frames) and decoded again, uint8 [T, H, W, 3] -- for frames rendered now that
    must look like frames recorded before (a probe beside its lossy source)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "episode.mp4"
        with VideoWriter(path, fps, frames.shape[1:3], pix_fmt, crf) as writer:
            writer.write(frames)
        return read_frames(path, np.arange(len(frames)), fps)


class FrameArena:
    """One block of memory that successive reads decode into (``read_frames``'s ``arena``): writing a hub camera's
    frames into fresh memory costs five times writing them into memory written before (the pages are mapped on
    first touch), so a pass that reads one demo after another reuses it.  What a read returns is valid until the
    next read into the same arena."""

    def __init__(self) -> None:
        self._block = np.zeros(0, np.uint8)

    def take(self, n: int, h: int, w: int) -> np.ndarray:
        """An uninitialised uint8 [n, h, w, 3] view of the block, grown when it is too small."""
        size = n * h * w * 3
        if self._block.size < size:
            self._block = np.empty(max(size, int(self._block.size * 1.25)), np.uint8)
        return self._block[:size].reshape(n, h, w, 3)


def read_frames(path: str | Path, indices: list[int] | np.ndarray, fps: float, arena: FrameArena | None = None
                ) -> np.ndarray:
    """Decode the given frame numbers (ascending) of a file; uint8 [N, H, W, 3] (in ``arena`` where given: valid
    until its next read).

    Seeks to the keyframe before each wanted frame that is far from the last
    decoded one, so sparse reads cost O(GOP) decoded frames each.
    """
    global frames_decoded
    indices = np.asarray(indices, np.int64)
    want = sorted(set(indices.tolist()))
    if not want:
        return np.zeros((0, 0, 0, 3), np.uint8)
    path = Path(path)
    # Each frame is converted straight into one array, in the order ``want`` asks for them: a hub camera's frames
    # (0.9 MB each) are written once, not converted, held and stacked again.
    slot = {k: n for n, k in enumerate(want)}
    out: np.ndarray | None = None
    got = np.zeros(len(want), bool)
    try:
        with av.open(str(path)) as container:
            if not container.streams.video or container.streams.video[0].codec_context is None:
                raise DatasetError(f"{path}: unreadable video (no video stream in it that a codec reads)")
            stream = container.streams.video[0]
            # Frame threading restarts its threads at every seek: 8x slower for sparse reads of small frames.
            stream.thread_type = "NONE"
            stream.codec_context.thread_count = 1
            tb = stream.time_base
            pos = -1  # frame number of the last decoded frame
            it = None
            for k in want:
                if it is None or k <= pos or k - pos > GOP:
                    # Seek (backward) to the keyframe at or before frame k.
                    container.seek(int(round(k / fps / tb)), stream=stream, backward=True, any_frame=False)
                    it = container.decode(stream)
                for frame in it:
                    frames_decoded += 1
                    pos = int(round(float(frame.pts * tb) * fps))
                    if pos == k:
                        if out is None:
                            out = (arena.take(len(want), frame.height, frame.width) if arena is not None else
                                   np.empty((len(want), frame.height, frame.width, 3), np.uint8))
                        if (frame.height, frame.width) != out.shape[1:3]:
                            raise DatasetError(f"{path}: frame {k} is {frame.width}x{frame.height}, the frames "
                                               f"before it {out.shape[2]}x{out.shape[1]}")
                        _to_rgb(frame, out[slot[k]])
                        got[slot[k]] = True
                        break
                    if pos > k:
                        break
                if not got[slot[k]]:
                    raise DatasetError(f"{path}: frame {k} is missing (video truncated or corrupt?)")
    except av.FFmpegError as exc:
        raise DatasetError(f"{path}: unreadable video ({exc})") from None
    except OverflowError:  # a frame number no video holds (from damaged metadata): no position to seek to
        raise DatasetError(f"{path}: frame {want[-1]} is missing (video truncated or its metadata corrupt?)") from None
    except UnicodeDecodeError:  # PyAV decodes the container's metadata as UTF-8 when it opens it
        raise DatasetError(f"{path}: unreadable video (its metadata is not valid UTF-8)") from None
    if len(indices) == len(want) and (np.diff(indices) > 0).all():
        return out
    return out[[slot[int(i)] for i in indices]]


def _to_rgb(frame: av.VideoFrame, into: np.ndarray) -> None:
    """``frame`` as RGB, written into ``into`` [H, W, 3] (what ``frame.to_ndarray(format="rgb24")`` gives)."""
    # swscale's default threading costs ~7 ms a 64x64 frame (thread start-up); one thread, 0.3 ms.
    # 4:4:4 needs no chroma resampling, so point sampling is exact there and 4x cheaper again.
    interp = "POINT" if frame.format.name == "yuv444p" else None
    rgb = frame if frame.format.name == "rgb24" else frame.reformat(format="rgb24", interpolation=interp, threads=1)
    plane = rgb.planes[0]
    h, w = into.shape[:2]
    into[:] = np.frombuffer(plane, np.uint8).reshape(h, plane.line_size)[:, :3 * w].reshape(h, w, 3)


def read_range(path: str | Path, start: int, stop: int, fps: float, arena: FrameArena | None = None) -> np.ndarray:
    """Decode frames ``start..stop-1`` of a file in one sequential pass (into ``arena`` where given)."""
    return read_frames(path, np.arange(start, stop), fps, arena)
