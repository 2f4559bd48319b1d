"""Frame sources: a camera's images from a video file or a folder of images, streamed.

A source knows its frame ``size`` (width, height), frame count and frame rate (``None`` for an
image folder) and yields RGB frames ``(H, W, 3)`` uint8 one at a time, for a frame range
``[start, stop)`` with a ``stride`` and an image ``scale`` applied while streaming — a sequence
of many full-resolution frames is never held in memory.

Videos are decoded by the ffmpeg binary of ``imageio-ffmpeg``: the frame range and stride are
selected by ffmpeg (``select`` on the decoded frame number, so every returned frame is the
exact frame of that index, whatever the stream's timestamps), and only the selected frames
cross the pipe. Image folders hold
``.png``/``.jpg``/``.jpeg``/``.bmp`` files (any case) in natural order (``img2`` before
``img10``); grey images are returned as RGB.

Scaling keeps the pixel-centre convention of
:meth:`~torchmocap.cameras.CameraRig.scaled_images`: output pixel ``u'`` samples the source at
``(u' + 0.5) / scale - 0.5``, the output is ``round(W · scale) × round(H · scale)``, and the
resampling filter is Pillow's antialiased bilinear.

Example:
    >>> src = open_frames("videos/cam01.mp4")           # doctest: +SKIP
    >>> src.size, src.num_frames, src.fps                # doctest: +SKIP
    ((1080, 1920), 100, 60.0)
    >>> [f.shape for f in src.frames(0, 4, stride=2, scale=0.5)]   # doctest: +SKIP
    [(960, 540, 3), (960, 540, 3)]
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

__all__ = [
    "IMAGE_SUFFIXES",
    "VIDEO_SUFFIXES",
    "FrameSourceError",
    "ImageFolderFrames",
    "VideoFrames",
    "check_frame_range",
    "frame_number",
    "natural_key",
    "numbered_files",
    "open_frames",
    "read_mask",
    "resize_image",
    "scaled_size",
]

#: file suffixes of image folders
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
#: file suffixes tried for videos
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")


#: codecs of still images (ffmpeg's names): such a "video" is one picture
_IMAGE_CODECS = {"png", "bmp", "tiff", "webp", "jpeg2000", "jpegls", "qoi", "ppm", "pgm",
                 "pam", "pbm"}


class FrameSourceError(ValueError):
    """A video or image folder cannot be read as frames (names the file)."""


def natural_key(name: str) -> list:
    """Sort key that orders the numbers inside names by value (``img2`` < ``img10``)."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


def frame_number(path: str | os.PathLike) -> int:
    """The frame index in a per-frame file's name: its last number, after dropping an OpenPose
    ``_keypoints`` suffix (``cam01.0012.json`` → 12, ``run_000000000007_keypoints.json`` → 7,
    ``image0003.png`` → 3).

    Raises:
        FrameSourceError: a name without a number.
    """
    name = Path(path).name
    stem = name[: -len(Path(name).suffix)] if Path(name).suffix else name
    nums = re.findall(r"\d+", re.sub(r"_keypoints$", "", stem))
    if not nums:
        raise FrameSourceError(f"{path}: no frame number in the file name")
    return int(nums[-1])


def numbered_files(folder: str | os.PathLike, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """The files of ``folder`` with one of ``suffixes`` (any case), by :func:`frame_number`.

    Raises:
        FrameSourceError: a missing folder, one without such files, or two files of one frame
            (both named).
    """
    from torchmocap.inputs import note_input

    folder = Path(folder)
    if not folder.is_dir():
        raise FrameSourceError(f"{folder}: no such folder")
    note_input(folder)  # which files are there decides what is read
    out: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in suffixes or not p.is_file():
            continue
        i = frame_number(p)
        if i in out:
            raise FrameSourceError(f"{folder}: {out[i].name} and {p.name} are both frame {i}")
        out[i] = p
    if not out:
        raise FrameSourceError(f"{folder}: no {'/'.join(suffixes)} files")
    return out


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """``(round(W · scale), round(H · scale))``, the size of a scaled image (at least 1 px);
    the size :meth:`~torchmocap.cameras.CameraRig.scaled_images` gives the camera."""
    return max(1, round(size[0] * scale)), max(1, round(size[1] * scale))


def resize_image(image: Image.Image, scale: float, resample: int = Image.BILINEAR
                 ) -> Image.Image:
    """``image`` scaled by ``scale`` so that output pixel ``u'`` samples the source at
    ``(u' + 0.5) / scale - 0.5`` (the camera intrinsics' convention); size
    :func:`scaled_size`. When the rounded size reaches past the source's edge by a fraction of
    a pixel, the edge is repeated."""
    if scale == 1.0:
        return image
    w, h = scaled_size(image.size, scale)
    box_w, box_h = w / scale, h / scale
    if box_w > image.width + 1e-6 or box_h > image.height + 1e-6:
        a = np.asarray(image)
        pad = ((0, max(0, math.ceil(box_h) - image.height)),
               (0, max(0, math.ceil(box_w) - image.width))) + ((0, 0),) * (a.ndim - 2)
        image = Image.fromarray(np.pad(a, pad, mode="edge"))
    box = (0.0, 0.0, min(box_w, image.width), min(box_h, image.height))
    return image.resize((w, h), resample, box=box)


def check_frame_range(num_frames: int, start: int = 0, stop: int | None = None,
                      stride: int = 1, scale: float = 1.0, source: str = "frames"
                      ) -> range:
    """The frame indices ``range(start, stop, stride)`` after checking them against a source of
    ``num_frames`` frames, and ``0 < scale <= 1``.

    Raises:
        ValueError: naming ``start``, ``stop``, ``stride`` or ``scale`` and the valid bounds.
    """
    def is_int(v) -> bool:
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    if not is_int(start) or not 0 <= start < num_frames:
        raise ValueError(f"start: expected an integer frame index in [0, {num_frames}) "
                         f"({source} has {num_frames} frames), got {start!r}")
    stop = num_frames if stop is None else stop
    if not is_int(stop) or not start < stop <= num_frames:
        raise ValueError(f"stop: expected an integer in ({start}, {num_frames}] ({source} has "
                         f"{num_frames} frames), got {stop!r}")
    if not is_int(stride) or stride < 1:
        raise ValueError(f"stride: expected an integer >= 1, got {stride!r}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or \
            not (math.isfinite(scale) and 0 < scale <= 1):
        raise ValueError(f"scale: expected an image scale in (0, 1], got {scale!r}")
    return range(int(start), int(stop), int(stride))


class VideoFrames:
    """Frames of a video file, decoded by ffmpeg (``imageio-ffmpeg``'s binary).

    Attributes:
        path: the file.
        size: ``(width, height)`` of the decoded frames (after the codec's cropping: an H.264
            stream coded at 1088 rows with a 1080-row crop decodes to 1080).
        fps: frame rate.
        num_frames: number of frames (counted from the stream's packets, without decoding).
        codec: the video codec's name.

    Raises:
        FrameSourceError: naming the file when it is missing or ffmpeg cannot read a video
            stream from it.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        import imageio_ffmpeg

        from torchmocap.inputs import note_input

        self.path = Path(path)
        if not self.path.is_file():
            raise FrameSourceError(f"{self.path}: no such video file")
        note_input(self.path)
        self._exe = imageio_ffmpeg.get_ffmpeg_exe()
        try:
            gen = imageio_ffmpeg.read_frames(str(self.path))
            meta = next(gen)
            gen.close()
        except (OSError, RuntimeError, StopIteration) as e:
            raise FrameSourceError(f"{self.path}: not a readable video ({_last_line(e)})"
                                   ) from None
        fps = float(meta.get("fps") or 0)
        if not (math.isfinite(fps) and fps > 0):
            raise FrameSourceError(f"{self.path}: the video states no frame rate")
        self.size: tuple[int, int] = (int(meta["size"][0]), int(meta["size"][1]))
        self.fps = fps
        self.codec = str(meta.get("codec", "?"))
        self.num_frames = self._count_frames()
        codec = self.codec.split(",")[0].strip().lower()
        if codec in _IMAGE_CODECS or (self.num_frames == 1 and not meta.get("duration")):
            raise FrameSourceError(
                f"{self.path}: a single {codec.upper()} image, not a video (one frame, no "
                "duration); a camera's frames are a video, or a folder of images "
                "(images/<cam>/000000.png, ...)")

    def _count_frames(self) -> int:
        cmd = [self._exe, "-hide_banner", "-nostdin", "-i", str(self.path), "-map", "0:v:0",
               "-c", "copy", "-f", "null", "-"]
        r = subprocess.run(cmd, capture_output=True)
        counts = re.findall(rb"frame=\s*(\d+)", r.stderr)
        if r.returncode != 0 or not counts or int(counts[-1]) < 1:
            raise FrameSourceError(f"{self.path}: cannot count the video's frames "
                                   f"({r.stderr.decode(errors='replace').strip()[-200:]})")
        return int(counts[-1])

    def frames(self, start: int = 0, stop: int | None = None, stride: int = 1,
               scale: float = 1.0) -> Iterator[np.ndarray]:
        """Yield the frames ``start, start + stride, … < stop`` as ``(H', W', 3)`` uint8 RGB,
        scaled by ``scale`` (:func:`resize_image`).

        Raises:
            ValueError: a range, stride or scale out of bounds (:func:`check_frame_range`).
            FrameSourceError: the video ends early or its frames do not decode (file named,
                with ffmpeg's last error line).
        """
        idx = check_frame_range(self.num_frames, start, stop, stride, scale, str(self.path))
        s, e, k = idx.start, idx.stop, idx.step
        # select by decoded frame number, then renumber the timestamps at the output rate so
        # that ffmpeg's constant-rate output neither repeats nor drops a selected frame
        # (works with ffmpeg versions before and after -vsync became -fps_mode)
        rate = repr(self.fps)
        vf = f"select='gte(n\\,{s})*lt(n\\,{e})*not(mod(n-{s}\\,{k}))',setpts=N/({rate}*TB)"
        cmd = [self._exe, "-hide_banner", "-nostdin", "-loglevel", "error", "-i",
               str(self.path), "-map", "0:v:0", "-vf", vf, "-r", rate, "-frames:v",
               str(len(idx)), "-f", "rawvideo", "-pix_fmt", "rgb24", "-"]
        w, h = self.size
        size = w * h * 3
        count = 0
        with tempfile.TemporaryFile() as log, subprocess.Popen(
                cmd, stdout=subprocess.PIPE, stderr=log) as proc:
            try:
                while count < len(idx):
                    buf = proc.stdout.read(size)
                    if len(buf) < size:
                        break
                    frame = np.frombuffer(buf, np.uint8).reshape(h, w, 3)
                    if scale != 1.0:
                        frame = np.asarray(resize_image(Image.fromarray(frame), scale))
                    yield frame
                    count += 1
            finally:
                if proc.poll() is None:
                    proc.kill()
                proc.stdout.close()
                proc.wait()
            if count != len(idx):
                log.seek(0)
                why = log.read().decode(errors="replace").strip().splitlines()
                raise FrameSourceError(
                    f"{self.path}: decoded {count} of the {len(idx)} frames {s}..{e - 1} "
                    f"(stride {k}) of a video of {self.num_frames} packets"
                    + (f" ({why[-1]})" if why else ""))

    def __repr__(self) -> str:
        return (f"VideoFrames({str(self.path)!r}, size={self.size}, fps={self.fps:g}, "
                f"num_frames={self.num_frames}, codec={self.codec!r})")


class ImageFolderFrames:
    """Frames of a folder of images (``.png``/``.jpg``/``.jpeg``/``.bmp``).

    Numbered images (every name holds a number, :func:`frame_number`) are frames by number:
    frame ``t`` is the image numbered ``first + t``, so that the frames of several cameras and
    their per-frame keypoint files stay paired. A number missing between the first and the
    last is a gap: :meth:`missing` names it, and reading it is refused (the later images are
    never shifted into its place). Images without numbers are frames in natural order.

    Attributes:
        path: the folder; files: the image files in frame order (None at a gap).
        size: ``(width, height)`` of the first image (every frame must have it).
        fps: None (images carry no frame rate).
        num_frames: number of frames (from the first number to the last).

    Raises:
        FrameSourceError: a missing folder, a folder without images, an unreadable first image,
            two images of one frame number.
    """

    fps: float | None = None

    def __init__(self, path: str | os.PathLike) -> None:
        from torchmocap.inputs import note_input

        self.path = Path(path)
        if not self.path.is_dir():
            raise FrameSourceError(f"{self.path}: no such image folder")
        note_input(self.path)
        self.files = sorted((p for p in self.path.iterdir()
                             if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                            key=lambda p: natural_key(p.name))
        if not self.files:
            raise FrameSourceError(f"{self.path}: no images ({', '.join(IMAGE_SUFFIXES)})")
        self.size = _image_size(self.files[0])
        numbered: dict[int, Path] = {}
        for f in self.files:
            if not re.search(r"\d", f.stem):
                break
            n = frame_number(f)
            if n in numbered:
                raise FrameSourceError(f"{self.path}: {numbered[n].name} and {f.name} are both "
                                       f"frame {n}")
            numbered[n] = f
        else:
            first = min(numbered)
            self.first_number = first
            self.files = [numbered.get(n) for n in range(first, max(numbered) + 1)]
        self.num_frames = len(self.files)

    #: the number of frame 0 (numbered images), else None
    first_number: int | None = None

    def missing(self, start: int = 0, stop: int | None = None, stride: int = 1) -> list[int]:
        """Frames ``start, start + stride, ... < stop`` without an image (a gap in the
        numbers)."""
        stop = self.num_frames if stop is None else min(stop, self.num_frames)
        return [t for t in range(start, stop, stride) if self.files[t] is None]

    def check_complete(self, start: int = 0, stop: int | None = None, stride: int = 1) -> None:
        """Refuse a gap among frames ``start, start + stride, ... < stop``.

        Raises:
            FrameSourceError: naming the folder, the first missing frame and the numbers.
        """
        gaps = self.missing(start, stop, stride)
        if gaps:
            raise self._gap_error(gaps[0])

    def _gap_error(self, t: int) -> FrameSourceError:
        gaps = self.missing()
        named = ", ".join(str(self.first_number + g) for g in gaps[:5]) + \
            (", ..." if len(gaps) > 5 else "")
        return FrameSourceError(
            f"{self.path}: no image for frame {t} (the images are numbered "
            f"{self.first_number}..{self.first_number + self.num_frames - 1}; number(s) "
            f"{named} missing): frames pair by number with the other cameras and the keypoint "
            f"files, so a gap is not skipped; fill it (e.g. with a copy of its neighbour) or "
            f"load only the frames before it (data.stop={gaps[0]})")

    def frames(self, start: int = 0, stop: int | None = None, stride: int = 1,
               scale: float = 1.0) -> Iterator[np.ndarray]:
        """Yield the images ``start, start + stride, … < stop`` as ``(H', W', 3)`` uint8 RGB
        (grey images expanded), scaled by ``scale``.

        Raises:
            ValueError: a range, stride or scale out of bounds.
            FrameSourceError: an unreadable image or one of another size (file named).
        """
        from torchmocap.inputs import note_input

        idx = check_frame_range(self.num_frames, start, stop, stride, scale, str(self.path))
        for i in idx:
            p = self.files[i]
            if p is None:
                raise self._gap_error(i)
            note_input(p)
            try:
                with Image.open(p) as im:
                    im = im.convert("RGB")
            except (UnidentifiedImageError, OSError) as e:
                raise FrameSourceError(f"{p}: cannot read image ({e})") from None
            if im.size != self.size:
                raise FrameSourceError(f"{p}: image size {im.size} differs from the folder's "
                                       f"first image {self.files[0].name} {self.size}")
            yield np.asarray(resize_image(im, scale))

    def __repr__(self) -> str:
        return (f"ImageFolderFrames({str(self.path)!r}, size={self.size}, "
                f"num_frames={self.num_frames})")


def read_mask(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """A foreground mask image as ``(H, W)`` bool, noted as an input
    (:func:`torchmocap.inputs.note_input`).

    A mask with at most two grey levels, one of them 0, is binary whatever its foreground value
    (0/255, 0/1 as written by numpy, 0/2, 0/100): every non-zero pixel is foreground. A mask
    with more levels (antialiased edges, JPEG noise) is foreground above 127. Colour masks are
    read as their grey level.

    Args:
        path: the image file.
        size: the ``(width, height)`` it must have (the camera's frames), or None.

    Raises:
        FrameSourceError: an unreadable image, or one of another size (both named).
    """
    from torchmocap.inputs import note_input

    path = Path(path)
    note_input(path)
    try:
        with Image.open(path) as im:
            grey = np.asarray(im.convert("L"))
    except (UnidentifiedImageError, OSError) as e:
        raise FrameSourceError(f"{path}: cannot read mask ({e})") from None
    if size is not None and (grey.shape[1], grey.shape[0]) != tuple(size):
        raise FrameSourceError(f"{path}: mask is {grey.shape[1]}x{grey.shape[0]}, the camera's "
                               f"frames are {size[0]}x{size[1]}")
    levels = np.flatnonzero(np.bincount(grey.ravel(), minlength=256))
    binary = len(levels) == 1 or (len(levels) == 2 and levels[0] == 0)
    return grey > (0 if binary else 127)


def _image_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError) as e:
        raise FrameSourceError(f"{path}: cannot read image ({e})") from None


def _last_line(e: BaseException) -> str:
    lines = [ln for ln in str(e).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else type(e).__name__


def open_frames(path: str | os.PathLike) -> VideoFrames | ImageFolderFrames:
    """The frame source of ``path``: an image folder for a directory, else a video file.

    Raises:
        FrameSourceError: naming ``path`` when it is neither.
    """
    p = Path(path)
    if p.is_dir():
        return ImageFolderFrames(p)
    if p.is_file():
        return VideoFrames(p)
    raise FrameSourceError(f"{p}: no such video file or image folder")
