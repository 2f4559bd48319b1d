"""Foreground masks of a loaded recording (``data.masks``): the recording's mask files, or masks
computed from its frames with :func:`torchmocap.data.recordings.masks.compute_masks`.

``data.masks``:

* ``files``: the mask folders (``masks/<cam>/``, ``FG<i>/``), required for every camera;
* ``compute``: computed from the frames at the working scale (``data.scale``: the masks line
  up with the sequence's images, :func:`~torchmocap.data.recordings.masks.working_images` is the
   identity
  there), with the background plates (``background/``) and the subject's keypoints when the
  recording has them; it needs one of the two (the keypoints place the multi-view check and
  gate the components; a plate tells the background where the subject stands still);
* ``detector``: the person masks of the keypoint source's own detector run
  (``data.keypoints.source=mediapipe``: the segmentation of each kept detection, inside its
  region; :func:`detector_masks`) — no plates needed, the same cached run as the keypoints;
* ``auto``: ``files`` when every camera has a mask folder, else ``compute`` when the recording
  has keypoints or plates, else ``none``;
* ``none``.

Computed masks are cached (:func:`~torchmocap.data.recordings.masks.cached_masks`) in
``data.mask_cache``
under a content hash of the frames, the rig, the plates, the keypoints and the settings; a
preview PNG of the middle frame (kept in green, removed by the multi-view check in magenta, the
keypoints yellow) is written beside the entry (``masks-<hash>.png``) on a miss.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchmocap.data.recordings.files import RecordingCamera, RecordingLayoutError
from torchmocap.data.recordings.masks import MaskSettings, cached_masks, compute_masks, content_key

__all__ = ["MASK_MODES", "check_mask_settings", "detector_masks", "mask_mode", "read_plates",
           "recording_masks"]

MASK_MODES = ("auto", "files", "compute", "detector", "none")


def mask_mode(masks: str, cams: Sequence[RecordingCamera], keypoints: bool, root: Path,
              source: Any = None) -> str:
    """``files``, ``compute``, ``detector`` or ``none`` for the ``data.masks`` setting
    ``masks``.

    Args:
        source: the keypoint source (``detector`` needs one with ``person_masks``).

    Raises:
        ValueError: an unknown mode, ``compute`` without keypoints or plates, ``detector``
            with a keypoint source that computes no masks.
        RecordingLayoutError: ``files`` with a camera lacking its mask folder.
    """
    if masks not in MASK_MODES:
        raise ValueError(f"data.masks: expected one of {list(MASK_MODES)}, got {masks!r}")
    if masks == "detector" and not callable(getattr(source, "person_masks", None)):
        what = ("no keypoint source is loaded" if source is None else
                f"the keypoint source {getattr(source, 'name', type(source).__name__)!r} "
                "reads files and computes no masks")
        raise ValueError(f"data.masks: detector takes the person masks of a detector run on "
                         f"the frames (data.keypoints.source=mediapipe), but {what}; set "
                         "data.masks: compute (background subtraction), files or none")
    plates = any(c.background for c in cams)
    if masks == "auto":
        if all(c.masks for c in cams):
            return "files"
        return "compute" if keypoints or plates else "none"
    if masks == "files":
        lacking = [c.name for c in cams if c.masks is None]
        if lacking:
            raise RecordingLayoutError(f"{root}: no mask folder (masks/<cam>/ or FG<i>/) for "
                                       f"camera(s) {lacking} (data.masks: files)")
    if masks == "compute" and not (keypoints or plates):
        raise ValueError(f"data.masks: compute needs the subject's keypoints or background "
                         f"plates (background/<cam>*.png), and {root} loads neither; set "
                         "data.masks: none (or files with mask folders)")
    return masks


def check_mask_settings(settings: Mapping[str, Any] | None) -> MaskSettings:
    """``data.mask_settings`` as
    :class:`~torchmocap.data.recordings.masks.MaskSettings` at the working
    scale (``scale`` is the loader's ``data.scale``, not a mask setting).

    Raises:
        MaskError: an unknown key or a bad value (named ``data.mask_settings.<key>``).
    """
    given = {} if settings is None else dict(settings)
    if "scale" in given:
        from torchmocap.data.recordings.masks import MaskError

        raise MaskError("data.mask_settings.scale: the masks are computed at the images' "
                        "working scale; set data.scale instead")
    return MaskSettings.from_dict({**given, "scale": 1.0}, prefix="data.mask_settings")


def read_plates(cams: Sequence[RecordingCamera], scale: float) -> list[torch.Tensor | None]:
    """Each camera's first background plate (``(H, W, 3)`` uint8 RGB at ``scale``, resampled
    like the frames), None for a camera without one.

    Raises:
        FrameSourceError: an unreadable plate (named).
    """
    from PIL import Image, UnidentifiedImageError

    from torchmocap.io.frames import FrameSourceError, resize_image

    out: list[torch.Tensor | None] = []
    for cam in cams:
        if not cam.background:
            out.append(None)
            continue
        path = cam.background[0]
        try:
            with Image.open(path) as im:
                plate = resize_image(im.convert("RGB"), scale)
        except (UnidentifiedImageError, OSError) as e:
            raise FrameSourceError(f"{path}: cannot read background plate ({e})") from None
        out.append(torch.from_numpy(np.array(plate)))
    return out


def recording_masks(images: torch.Tensor, rig, plates: list[torch.Tensor | None],
                    keypoints: torch.Tensor | None, settings: MaskSettings,
                    cache: str | os.PathLike | None) -> tuple[torch.Tensor, dict]:
    """Masks ``(T, C, H, W)`` bool of the working-scale ``images (T, C, H, W, 3)`` and the
    report (:func:`~torchmocap.data.recordings.masks.compute_masks`'s, with ``cache`` and
    ``preview``
    when cached).

    Args:
        images: the sequence's images (views smaller than the array in its top-left corner).
        rig: the cameras at the working scale.
        plates: per camera a plate ``(H', W', 3)`` at the working scale or None.
        keypoints: ``(T, C, K, 3)`` the subject's detections in the images' pixels, or None.
        settings: from :func:`check_mask_settings`.
        cache: folder of the cache entries, or None (computed every time, no preview).
    """
    have = None if all(p is None for p in plates) else plates
    if cache is None:
        masks, report = compute_masks(images, rig, have, keypoints, settings)
        return masks, report
    root = Path(cache).expanduser()
    key = content_key(("recording-masks", images, rig, have, keypoints, settings))
    preview = root / f"masks-{content_key(key)}.png"  # beside the entry cached_masks names

    def compute():
        return compute_masks(images, rig, have, keypoints, settings, preview=preview)

    masks, report = cached_masks(root, key, compute)
    if preview.is_file():
        report["preview"] = str(preview)
    return masks, report


def detector_masks(source, request, report: Mapping[str, Any], scale: float,
                   canvas: tuple[int, int]) -> tuple[torch.Tensor, dict]:
    """Masks ``(T, C, H, W)`` bool of the request's cameras from the keypoint source's detector
    run (``data.masks=detector``): ``source.person_masks(request, report, scale)`` — per
    camera ``(T, h, w)`` — placed in the top-left corner of the ``canvas (W, H)`` (views
    smaller than it by a codec's crop), and a report (``source``, ``mask_fraction`` per
    camera, ``empty_frames`` per camera: frames without a mask, a view dropped or nobody
    found)."""
    per_cam = source.person_masks(request, report, scale)
    T, C = len(request.frames), len(request.cameras)
    out = torch.zeros(T, C, canvas[1], canvas[0], dtype=torch.bool)
    fractions, empty = {}, {}
    for c, (cam, m) in enumerate(zip(request.cameras, per_cam)):
        out[:, c, :m.shape[1], :m.shape[2]] = m
        fractions[cam.name] = round(float(m.float().mean()), 5)
        empty[cam.name] = [t for t, x in zip(request.frames, m) if not bool(x.any())]
    return out, {"source": getattr(source, "name", None), "mask_fraction": fractions,
                 "empty_frames": empty}
