"""Animations from RGB frames: MP4 through an ffmpeg executable when one is available, else an
animated GIF through Pillow. Files are written atomically (temporary file + ``os.replace``), so
an interrupted run leaves no half-written video behind.

ffmpeg is looked up on ``PATH`` and then from the ``imageio-ffmpeg`` package (which bundles a
binary: ``pip install imageio-ffmpeg``); neither is required.
"""

from __future__ import annotations

import logging
import math
import shutil
import subprocess
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

__all__ = ["VIDEO_FORMATS", "decimation", "ffmpeg_executable", "write_gif", "write_mp4",
           "write_video"]

log = logging.getLogger(__name__)

#: accepted values of ``format`` in :func:`write_video`
VIDEO_FORMATS = ("gif", "mp4")


def ffmpeg_executable() -> str | None:
    """Path of an ffmpeg binary (``PATH``, then ``imageio_ffmpeg``), or None."""
    exe = shutil.which("ffmpeg")
    if exe:
        return exe
    try:
        import imageio_ffmpeg  # type: ignore[import-not-found]

        return imageio_ffmpeg.get_ffmpeg_exe()
    except Exception:  # noqa: BLE001 - not installed, or its binary missing
        return None


def decimation(fps: float, max_fps: float | None) -> int:
    """Frame step ``k >= 1`` so that ``fps / k <= max_fps`` (1 when ``max_fps`` is None)."""
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a finite number > 0, got {fps!r}")
    if max_fps is None:
        return 1
    if not (math.isfinite(max_fps) and max_fps > 0):
        raise ValueError(f"max_fps: expected a finite number > 0 or None, got {max_fps!r}")
    return max(1, math.ceil(fps / max_fps - 1e-9))


def _check_frame(frame, shape=None) -> np.ndarray:
    a = np.asarray(frame)
    if a.ndim != 3 or a.shape[-1] != 3 or a.dtype != np.uint8:
        raise ValueError(f"frames: expected (H, W, 3) uint8 RGB frames, got {a.shape} {a.dtype}")
    if shape is not None and a.shape != shape:
        raise ValueError(f"frames: every frame must have the first frame's shape {shape}, "
                         f"got {a.shape}")
    return a


def _check_fps(fps: float) -> float:
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a finite number > 0, got {fps!r}")
    return float(fps)


def write_gif(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Animated GIF (looping) of ``(H, W, 3)`` uint8 frames at ``fps`` (GIF timing is in
    1/100 s; players slow down frames shorter than 20 ms, so keep ``fps <= 50``)."""
    from torchmocap.atomic import atomic_path

    fps = _check_fps(fps)
    images: list[Image.Image] = []
    shape = None
    for f in frames:
        a = _check_frame(f, shape)
        shape = a.shape
        images.append(Image.fromarray(a, "RGB").quantize(colors=256,
                                                         method=Image.Quantize.MEDIANCUT))
    if not images:
        raise ValueError("frames: expected at least one frame, got none")
    path = Path(path)
    with atomic_path(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], loop=0,
                       duration=max(20, round(1000.0 / fps)), optimize=False, disposal=1)
    return path


def write_mp4(path: str | Path, frames: Iterable[np.ndarray], fps: float,
              ffmpeg: str | None = None, crf: int = 23) -> Path:
    """H.264 MP4 (yuv420p, plays in browsers) of ``(H, W, 3)`` uint8 frames, streamed to ffmpeg
    (frames are padded to even sizes with black).

    Raises:
        FileNotFoundError: no ffmpeg executable (``ffmpeg``) was given or found.
        OSError: ffmpeg failed (its last lines of output are in the message).
    """
    from torchmocap.atomic import atomic_path

    fps = _check_fps(fps)
    exe = ffmpeg or ffmpeg_executable()
    if exe is None:
        raise FileNotFoundError("ffmpeg: no ffmpeg executable on PATH or from imageio-ffmpeg")
    it = iter(frames)
    try:
        first = _check_frame(next(it))
    except StopIteration:
        raise ValueError("frames: expected at least one frame, got none") from None
    H, W = first.shape[:2]
    H2, W2 = H + H % 2, W + W % 2
    path = Path(path)
    with atomic_path(path) as tmp:
        cmd = [exe, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
               "-s", f"{W2}x{H2}", "-r", f"{fps:g}", "-i", "-", "-an", "-c:v", "libx264",
               "-pix_fmt", "yuv420p", "-crf", str(int(crf)), "-movflags", "+faststart",
               "-f", "mp4", str(tmp)]
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)
        try:
            for a in _chain(first, it):
                a = _check_frame(a, first.shape)
                if (H2, W2) != (H, W):
                    a = np.pad(a, ((0, H2 - H), (0, W2 - W), (0, 0)))
                proc.stdin.write(np.ascontiguousarray(a).tobytes())
            proc.stdin.close()
        except BrokenPipeError:
            pass
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        err = proc.stderr.read().decode(errors="replace")
        proc.stderr.close()
        if proc.wait() != 0:
            tail = " | ".join(err.strip().splitlines()[-3:])
            raise OSError(f"ffmpeg: failed writing {path} (exit status {proc.returncode}): "
                          f"{tail}")
    return path


def _chain(first, rest):
    yield first
    yield from rest


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float,
                format: str = "mp4") -> Path:
    """Write an animation as ``format`` (``"mp4"`` or ``"gif"``); returns the written path.

    ``"mp4"`` without an ffmpeg executable falls back to a GIF (``path`` with suffix ``.gif``)
    and says so in a log line. ``path``'s suffix is replaced by the format's.
    """
    if format not in VIDEO_FORMATS:
        raise ValueError(f"format: expected one of {VIDEO_FORMATS}, got {format!r}")
    path = Path(path)
    if format == "mp4":
        exe = ffmpeg_executable()
        if exe is not None:
            return write_mp4(path.with_suffix(".mp4"), frames, fps, ffmpeg=exe)
        log.warning("no ffmpeg executable (PATH or imageio-ffmpeg): writing a GIF instead of "
                    "an MP4")
    return write_gif(path.with_suffix(".gif"), frames, fps)
