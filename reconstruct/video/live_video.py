"""Video files of the live path: H.264 (T.mp4, R.mp4) fed as ready planes, gray H.264 or raw Y4M, as the user chooses.

The live frames are gray 8-bit images.  ``h264`` (the default) writes what an MP4 player expects, yuv420p H.264,
but sends the encoder its planes ready-made: the luma in the studio range (16-235, by :data:`LIMITED`, the same
value ffmpeg's own gray -> yuv420p conversion gives, checked against it) and constant chroma, so the encoder process
does no colour conversion (the same file as converting in ffmpeg).  ``h264-gray`` encodes 4:0:0 (luma only, full
range; no chroma planes at all; ffmpeg, mpv and VLC play it, browsers and many hardware decoders do not).  ``y4m``
writes the raw 8-bit frames as YUV4MPEG2 (``Cmono``), no encoder process at all: 100 kB per 400 x 250 frame.
The measured encoder CPU and file sizes are in docs/realtime.md.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np

__all__ = ["VIDEO_CODECS", "LIMITED", "open_video"]

VIDEO_CODECS = {"h264": ".mp4", "h264-gray": ".mp4", "y4m": ".y4m"}
"""``LiveConfig.video_codec`` -> file suffix."""

LIMITED = np.round(16 + np.arange(256) * 219 / 255).astype(np.uint8)
"""Full-range gray level -> studio-range luma (16 + 219 v / 255, rounded): ffmpeg's gray -> yuv420p conversion."""


class _H264:
    """x264 in an ffmpeg child process fed with raw planes: yuv420p (studio-range luma given, chroma 128) or gray."""

    def __init__(self, path: Path, height: int, width: int, fps: float, params: list[str], gray: bool):
        import imageio_ffmpeg

        self.h, self.w, self.gray = height // 2 * 2, width // 2 * 2, gray  # 4:2:0 wants even sides; cropped as before
        n = self.h * self.w
        self.buf = np.empty(n, np.uint8) if gray else np.full(n * 3 // 2, 128, np.uint8)
        self.y = self.buf[:n].reshape(self.h, self.w)
        fmt = "gray" if gray else "yuv420p"
        self.gen = imageio_ffmpeg.write_frames(str(path), (self.w, self.h), pix_fmt_in=fmt, pix_fmt_out=fmt, fps=fps, codec="libx264", quality=None,
                                               macro_block_size=1, ffmpeg_log_level="error", output_params=params)
        self.gen.send(None)

    def append(self, img8: np.ndarray, limited: bool) -> None:
        """``img8`` full-range gray levels, or already studio-range luma when ``limited`` (yuv420p only)."""
        src = img8[: self.h, : self.w]
        if self.gray or limited:
            self.y[...] = src
        else:
            np.take(LIMITED, src, out=self.y)
        self.gen.send(self.buf)

    def close(self) -> None:
        self.gen.close()


class _Y4m:
    """Raw 8-bit gray frames in a YUV4MPEG2 stream (``Cmono``)."""

    def __init__(self, path: Path, height: int, width: int, fps: float):
        r = Fraction(fps).limit_denominator(1001)
        self.f = open(path, "wb")  # noqa: SIM115 - closed by close()
        self.f.write(f"YUV4MPEG2 W{width} H{height} F{r.numerator}:{r.denominator} Ip A1:1 Cmono\n".encode())

    def append(self, img8: np.ndarray, limited: bool) -> None:
        self.f.write(b"FRAME\n")
        self.f.write(np.ascontiguousarray(img8).data)

    def close(self) -> None:
        self.f.close()


def open_video(path: Path, codec: str, height: int, width: int, fps: float, x264_params: list[str]):
    """A writer with ``append(img8, limited)`` and ``close()`` for ``codec`` (:data:`VIDEO_CODECS`) at ``path``."""
    if codec == "y4m":
        return _Y4m(path, height, width, fps)
    return _H264(path, height, width, fps, x264_params, gray=codec == "h264-gray")
