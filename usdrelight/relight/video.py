"""Relit frames -> an H.264 MP4 (PyAV, whose wheels bring their own FFmpeg: the ``video`` extra).

Conventions: frames are linear RGB; each is shown as the PNGs are (sRGB), divided by one exposure for the whole
clip, ``max(1, 99.5th percentile of the first frame)`` unless the caller sets :attr:`Mp4Writer.exposure` first
(``relight``: the photo's), so brightness changes between frames stay visible and nothing flickers. Pixel format yuv420p (what every player decodes) when width and height are even, yuv444p
otherwise (4:2:0 needs even sizes; the video keeps the stage's exact size either way), BT.709 matrix, limited range,
tagged BT.709 (matrix, primaries, transfer) so that players do not guess. Quality: x264 CRF 16,
one key frame per second. The file appears complete or not at all (:func:`usdrelight.atomic.atomic_path`).
"""
from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import UsdRelightError
from ..imageio import display_exposure, linear_to_srgb
from ..safe_paths import made_folders, writable_parent

CRF = 16
"""x264 constant rate factor (0 lossless .. 51; 16: visually lossless for relit photos)."""
BT709 = 1
"""FFmpeg's code of ITU-R BT.709 for the matrix, primaries (sRGB's) and transfer tags of the stream."""
LIMITED_RANGE = 1
"""FFmpeg's code of the MPEG (16-235) range the YUV samples use."""


def check_video_path(path) -> Path:
    """``path`` must name an ``.mp4`` file (checked before anything renders)."""
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise UsdRelightError(f"--video writes an H.264 .mp4 file, got {path.name!r}")
    if path.is_dir():
        raise UsdRelightError(f"--video {path} is a folder")
    return writable_parent(path, "--video")


def _av():
    try:
        import av
    except ImportError:
        raise UsdRelightError("--video needs PyAV: pip install 'usdrelight[video]'") from None
    return av


def video_frame(image: np.ndarray, exposure: float) -> np.ndarray:
    """The 8-bit sRGB picture of a linear frame as the video shows it (``image / exposure``, clipped)."""
    return np.round(linear_to_srgb(np.asarray(image, np.float32) / exposure) * 255.0).astype(np.uint8)


class Mp4Writer:
    """Encode frames, in order, into ``path`` at ``fps`` frames per second; use as a context manager (an
    exception leaves no file)."""

    def __init__(self, path, fps: float):
        self.path = check_video_path(path)
        if not (np.isfinite(fps) and 0 < fps <= 1000):
            raise UsdRelightError(f"the video's frame rate must be in (0, 1000], got {fps:g}")
        self.fps = fps
        self.frames = 0
        self.exposure = None
        self._av = _av()
        self._stack = ExitStack()
        self._container = self._stream = None
        interp = self._av.video.reformatter.Interpolation
        self._scaler = interp.BILINEAR | interp.ACCURATE_RND  # rounded, not truncated: no 1-level darkening

    def __enter__(self) -> Mp4Writer:
        self._stack.enter_context(made_folders(self.path.parent))  # removed again, if still empty, on a failure
        tmp = self._stack.enter_context(atomic_path(self.path))
        self._tmp = tmp
        return self

    def add(self, image: np.ndarray) -> None:
        """Append one linear RGB frame (H, W, 3)."""
        from fractions import Fraction

        h, w = image.shape[:2]
        if self._container is None:
            self.exposure = display_exposure(image) if self.exposure is None else self.exposure
            self._container = self._av.open(str(self._tmp), "w", format="mp4")
            rate = Fraction(self.fps).limit_denominator(1001)
            self._stream = self._container.add_stream("libx264", rate=rate)
            self._stream.width, self._stream.height = w, h
            self._stream.pix_fmt = "yuv420p" if w % 2 == 0 and h % 2 == 0 else "yuv444p"
            self._stream.options = {"crf": str(CRF), "g": str(max(1, round(self.fps)))}
            cc = self._stream.codec_context  # tagged as encoded: players assume BT.709 for untagged HD, 601 for SD
            cc.colorspace, cc.color_primaries, cc.color_trc, cc.color_range = BT709, BT709, BT709, LIMITED_RANGE
        elif (h, w) != (self._stream.height, self._stream.width):
            raise UsdRelightError(f"video frames change size ({self._stream.width}x{self._stream.height} -> {w}x{h})")
        frame = self._av.VideoFrame.from_ndarray(video_frame(image, self.exposure), format="rgb24").reformat(
            format=self._stream.pix_fmt, dst_colorspace="ITU709", dst_color_range="MPEG",
            interpolation=self._scaler, dst_color_trc=BT709, dst_color_primaries=BT709)
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self._container is not None:
                if exc_type is None:
                    for packet in self._stream.encode():  # flush the encoder
                        self._container.mux(packet)
                self._container.close()
            elif exc_type is None:
                raise UsdRelightError("no frame to encode")
        except BaseException as err:  # the temporary file goes; nothing appears at the path
            self._stack.__exit__(type(err), err, err.__traceback__)
            raise
        self._stack.__exit__(exc_type, exc, tb)
