"""Detections of a video (or image folder) on disk, computed once: :func:`cached_detections`.

An entry is a folder keyed by the **content** of the frame source (SHA-256 of the video file,
or of every image of a folder, by :func:`source_digest`) and the **detector's identity**
(detector, mediapipe release, model digests and settings: a changed setting is another entry),
in a cache folder of the caller's choice (never the recording's folder unless the caller names
it)::

    <cache_dir>/mediapipe_pose-<key>/
        manifest.json            source (path, digest, size, frames), detector identity, format
        keypoints/000012.json    frame 12: OpenPose JSON, format mediapipe_33
        masks/000012.png         frame 12: person probability x 255 (8-bit grey PNG)

The layout is that of a recording's own detections and masks: ``keypoints/`` is read by
:func:`torchmocap.io.openpose.read_openpose_json` (``P = 0`` or 1 people of 33 keypoints;
the file name's number is the frame, :func:`torchmocap.io.frames.numbered_files`) and
``masks/`` by :func:`torchmocap.io.frames.read_mask` (foreground above 127, i.e.
probability > 0.5). Each JSON also holds a ``torchmocap`` block: the frame, the image size, the
region searched (:mod:`torchmocap.detectors.regions`; a detection depends on the crop only)
and the SHA-256 of its mask file.

A frame is cached when its JSON reads, its block matches the request (frame, size, region)
and its mask file has the recorded digest; anything else — a missing, truncated or altered
file, a mask from an interrupted rewrite, another region — is recomputed (with a warning for
damaged entries) and replaced. Files are written atomically (a temporary file renamed into
place), the mask first and the JSON last, so a crash never leaves a frame that reads as
cached.

Example:
    >>> out = cached_detections("videos/cam01.mp4", {}, "outputs/detections",
    ...                         frames=range(0, 100))            # doctest: +SKIP
    >>> out.keypoints(12).shape, out.mask(12).shape, out.computed   # doctest: +SKIP
    (torch.Size([1, 33, 3]), torch.Size([1920, 1080]), (0, 1, ..., 99))
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmocap.atomic import atomic_path
from torchmocap.detectors.mediapipe_pose import (
    MEDIAPIPE_33,
    MEDIAPIPE_VERSION,
    MediaPipePoseDetector,
    MediaPipePoseSettings,
    check_model_files,
)
from torchmocap.detectors.regions import DetectorInputError, Region, box_to_region
from torchmocap.io.frames import IMAGE_SUFFIXES, natural_key, open_frames
from torchmocap.io.openpose import KeypointFormatError, read_openpose_json, write_openpose_json

__all__ = ["CACHE_VERSION", "CachedDetections", "cached_detections", "detection_key",
           "source_digest"]

#: part of every key: bump it when the files an input produces change
CACHE_VERSION = 1
_FORMAT = "torchmocap-detections"
_CHUNK = 1 << 20

#: a box per frame: a mapping ``{frame: box or None}``, or ``(frame, previous keypoints (P, 33,
#: 3) or None) -> box or None``
Boxes = Mapping[int, Any] | Callable[[int, Tensor | None], Any] | None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def source_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a frame source's content: a video file's bytes, or an image folder's images
    (names in natural order and their bytes).

    Raises:
        DetectorInputError: neither a file nor a folder with images.
    """
    p = Path(path)
    if p.is_file():
        return _sha256(p)
    if p.is_dir():
        files = sorted((q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES
                        and q.is_file()), key=lambda q: natural_key(q.name))
        if files:
            h = hashlib.sha256()
            for q in files:
                h.update(f"{q.name}\0{_sha256(q)}\n".encode())
            return h.hexdigest()
    raise DetectorInputError(f"source: {p} is neither a video file nor a folder of images "
                             f"({', '.join(IMAGE_SUFFIXES)})")


def _identity(settings: MediaPipePoseSettings) -> dict[str, Any]:
    return {"detector": MediaPipePoseDetector.name, "mediapipe": MEDIAPIPE_VERSION,
            "models": check_model_files(), "settings": settings.to_dict()}


def detection_key(digest: str, identity: Mapping[str, Any]) -> str:
    """The cache key (32 hex digits, BLAKE2b) of a source digest and a detector identity
    (:meth:`MediaPipePoseDetector.identity`)."""
    blob = json.dumps({"format": _FORMAT, "version": CACHE_VERSION, "source": digest,
                       "detector": identity}, sort_keys=True)
    return hashlib.blake2b(blob.encode(), digest_size=16).hexdigest()


@dataclass(frozen=True)
class CachedDetections:
    """The cached detections of one frame source (module docstring for the layout).

    Attributes:
        path: the entry folder.
        frames: the frames asked for, in order.
        size: ``(W, H)`` of the source's frames.
        computed: the frames the detector ran on in this call (empty: all read from the cache).
        rebuilt: the frames among ``computed`` whose cached files were damaged.
    """

    path: Path
    frames: tuple[int, ...]
    size: tuple[int, int]
    computed: tuple[int, ...] = ()
    rebuilt: tuple[int, ...] = ()

    @property
    def keypoints_dir(self) -> Path:
        """Folder of the OpenPose JSON files (``<frame:06d>.json``)."""
        return self.path / "keypoints"

    @property
    def masks_dir(self) -> Path:
        """Folder of the mask PNGs (``<frame:06d>.png``)."""
        return self.path / "masks"

    def keypoint_file(self, frame: int) -> Path:
        return self.keypoints_dir / f"{frame:06d}.json"

    def mask_file(self, frame: int) -> Path:
        return self.masks_dir / f"{frame:06d}.png"

    def keypoints(self, frame: int) -> Tensor:
        """``(P, 33, 3)`` float64 ``(u, v, confidence)`` of ``frame`` (``P`` = 0 or 1)."""
        return read_openpose_json(self.keypoint_file(frame), len(MEDIAPIPE_33))

    def mask(self, frame: int) -> Tensor:
        """``(H, W)`` float32 person probability of ``frame`` (8-bit: steps of 1/255)."""
        from PIL import Image

        with Image.open(self.mask_file(frame)) as im:
            return torch.from_numpy(np.asarray(im.convert("L"), dtype=np.float32) / 255.0)

    def region(self, frame: int) -> Region | None:
        """The crop ``(x0, y0, x1, y1)`` searched in ``frame`` (None: the whole image, or a
        box that missed it)."""
        r = json.loads(self.keypoint_file(frame).read_text())["torchmocap"]["region"]
        return tuple(r) if isinstance(r, list) else None


def _frame_list(frames, num_frames: int, source: str) -> list[int]:
    if frames is None:
        return list(range(num_frames))
    if isinstance(frames, range):
        from torchmocap.io.frames import check_frame_range

        return list(check_frame_range(num_frames, frames.start, frames.stop, frames.step,
                                      source=source))
    out = []
    for t in frames:
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or \
                not 0 <= int(t) < num_frames:
            raise DetectorInputError(f"frames: expected frame indices in [0, {num_frames}) "
                                     f"({source} has {num_frames} frames), got {t!r}")
        if out and int(t) <= out[-1]:
            raise DetectorInputError(f"frames: expected increasing frame indices, got {t} "
                                     f"after {out[-1]}")
        out.append(int(t))
    if not out:
        raise DetectorInputError("frames: expected at least one frame")
    return out


def _request(boxes: Boxes, t: int, prev: Tensor | None, size: tuple[int, int],
             margin: float) -> tuple[Any, Any]:
    """``(box, region spec)`` of frame ``t``: the spec is None (whole image), the region as a
    list, or ``"outside"`` (a box that misses the image)."""
    if boxes is None:
        box = None
    elif isinstance(boxes, Mapping):
        box = boxes.get(t)
    elif callable(boxes):
        box = boxes(t, prev)
    else:
        raise DetectorInputError(f"boxes: expected None, a mapping {{frame: box}} or a "
                                 f"function (frame, previous keypoints) -> box, got "
                                 f"{type(boxes).__name__}")
    if box is None:
        return None, None
    region = box_to_region(box, size, margin)
    return box, ("outside" if region is None else list(region))


def _cached(entry: CachedDetections, t: int, spec) -> tuple[Tensor | None, bool]:
    """``(keypoints, damaged)``: the cached keypoints of frame ``t`` when its files are whole
    and were made for ``spec``; ``damaged`` when files are there but unreadable."""
    jp, mp = entry.keypoint_file(t), entry.mask_file(t)
    if not jp.exists():
        return None, mp.exists()
    try:
        kp = read_openpose_json(jp, len(MEDIAPIPE_33))
        block = json.loads(jp.read_text())["torchmocap"]
        ok_block = (block["frame"] == t and block["size"] == list(entry.size)
                    and block["mask"] == mp.name)
        if not ok_block or kp.shape[0] > 1:
            return None, True
        if block["region"] != spec:
            return None, False  # made for another region: not damage
        if not mp.is_file() or _sha256(mp) != block["mask_sha256"]:
            return None, True
        return kp, False
    except (KeypointFormatError, OSError, ValueError, KeyError, TypeError):
        return None, True


def _write_frame(entry: CachedDetections, t: int, spec, keypoints: Tensor, mask: Tensor
                 ) -> None:
    from PIL import Image

    mp = entry.mask_file(t)
    grey = (mask.detach().cpu().clamp(0, 1) * 255.0).round().to(torch.uint8).numpy()
    with atomic_path(mp) as tmp:
        Image.fromarray(grey).save(tmp)
    block = {"frame": t, "size": list(entry.size), "region": spec, "mask": mp.name,
             "mask_sha256": _sha256(mp)}
    write_openpose_json(entry.keypoint_file(t), keypoints, {"torchmocap": block})


def _write_manifest(path: Path, manifest: dict) -> None:
    f = path / "manifest.json"
    try:
        if json.loads(f.read_text()) == manifest:
            return
    except (OSError, ValueError):
        pass
    with atomic_path(f) as tmp:
        tmp.write_text(json.dumps(manifest, indent=1))


def cached_detections(source: str | os.PathLike,
                      detector: MediaPipePoseDetector | MediaPipePoseSettings | Mapping | None,
                      cache_dir: str | os.PathLike, frames: range | Iterable[int] | None = None,
                      boxes: Boxes = None, progress: bool = True) -> CachedDetections:
    """Detect the person in the frames of ``source``, reading every frame that is cached and
    running the detector (and storing its output) only on the others.

    Args:
        source: a video file or a folder of images (:func:`torchmocap.io.frames.open_frames`).
        detector: a :class:`MediaPipePoseDetector`, or its settings (an object or a mapping;
            None: defaults) — then the detector is built only when a frame is not cached.
        cache_dir: the folder of cache entries (created when missing).
        frames: the frame indices (a ``range`` or increasing integers; None: every frame).
        boxes: where to look per frame: None (the whole image), a mapping ``{frame: box}``
            (a frame not in it: the whole image), or a function ``(frame, previous) -> box``
            where ``previous`` is the ``(P, 33, 3)`` keypoints of the previous frame asked for
            (None for the first) — e.g. :func:`~torchmocap.detectors.regions.keypoint_box`
            of them. Boxes are ``(u_min, v_min, u_max, v_max)`` in the frame's pixels,
            widened by the detector's ``margin``; None is the whole image.
        progress: show a tqdm progress bar.

    Returns:
        :class:`CachedDetections` (paths and readers of the frames' files).

    Raises:
        DetectorInputError: a missing or unreadable source, frames out of range, a malformed
            box.
        DetectorSettingsError: invalid settings.
        DetectorUnavailableError: mediapipe or its model files are missing (checked first,
            even when every frame is cached: the key holds the model files' digests).
    """
    from tqdm import tqdm

    from torchmocap.io.frames import FrameSourceError

    if isinstance(detector, MediaPipePoseDetector):
        settings, model = detector.settings, detector
    elif isinstance(detector, MediaPipePoseSettings):
        settings, model = detector, None
    elif detector is None or isinstance(detector, Mapping):
        settings, model = MediaPipePoseSettings.from_dict(detector), None
    else:
        raise DetectorInputError(f"detector: expected a MediaPipePoseDetector or its settings, "
                                 f"got {type(detector).__name__}")
    identity = model.identity() if model is not None else _identity(settings)
    src_path = Path(source).expanduser().absolute()
    try:
        src = open_frames(src_path)
    except FrameSourceError as e:
        raise DetectorInputError(f"source: {e}") from None
    digest = source_digest(src_path)
    key = detection_key(digest, identity)
    size = (int(src.size[0]), int(src.size[1]))
    ts = _frame_list(frames, src.num_frames, str(src_path))
    root = Path(cache_dir).expanduser() / f"{MediaPipePoseDetector.name}-{key}"
    entry = CachedDetections(root, tuple(ts), size)
    root.mkdir(parents=True, exist_ok=True)
    _write_manifest(root, {
        "format": _FORMAT, "version": CACHE_VERSION, "key": key,
        "source": {"path": str(src_path), "sha256": digest, "size": list(size),
                   "num_frames": int(src.num_frames)},
        "detector": identity, "keypoint_format": MediaPipePoseDetector.keypoint_format,
        "keypoint_names": list(MEDIAPIPE_33)})

    computed: list[int] = []
    rebuilt: list[int] = []
    decoder = None
    at = step = 0
    prev: Tensor | None = None
    bar = tqdm(ts, desc=f"detect {src_path.name}", unit="frame", disable=not progress,
               dynamic_ncols=True)
    try:
        for i, t in enumerate(bar):
            box, spec = _request(boxes, t, prev, size, settings.margin)
            kp, damaged = _cached(entry, t, spec)
            if kp is None:
                if decoder is None:  # decode from the first frame to compute, in its steps
                    rest = ts[i:]
                    step = rest[1] - rest[0] if len(rest) > 1 else 1
                    if any(b - a != step for a, b in zip(rest, rest[1:])):
                        step = 1
                    decoder = src.frames(rest[0], rest[-1] + 1, step)
                    at = rest[0] - step
                image = None
                while at < t:
                    image = next(decoder)
                    at += step
                if model is None:
                    model = MediaPipePoseDetector(settings)
                out = model.detect(image, box)
                _write_frame(entry, t, spec, out.keypoints, out.mask)
                kp = out.keypoints
                computed.append(t)
                if damaged:
                    rebuilt.append(t)
                bar.set_postfix(computed=len(computed), refresh=False)
            prev = kp
    finally:
        bar.close()
        if decoder is not None:
            decoder.close()  # ends the ffmpeg process
    if rebuilt:
        warnings.warn(f"{root}: the cached files of {len(rebuilt)} frame(s) (first: "
                      f"{rebuilt[0]}) were damaged or incomplete; recomputed them",
                      stacklevel=2)
    return CachedDetections(root, tuple(ts), size, tuple(computed), tuple(rebuilt))
