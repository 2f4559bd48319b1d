"""Regions of interest: detect inside a box of an image and map the result back.

A pose landmarker follows one person per image; to detect the subject and not a bystander, the
caller passes the subject's box (from the other views' triangulation, or the previous frame's
detection). The image is cropped to the box, the detector runs on the crop, and its keypoints
and mask are mapped back to the full image.

Conventions: pixel coordinates ``(u, v)`` have pixel centres at integers (pixel ``(i, j)``
covers ``[i - 0.5, i + 0.5) × [j - 0.5, j + 0.5)``), the convention of the cameras and of
OpenPose JSON. A **box** is ``(u_min, v_min, u_max, v_max)`` in those coordinates (floats, may
reach outside the image); a **region** is the crop it becomes: integer pixel ranges
``(x0, y0, x1, y1)`` = columns ``x0 … x1 - 1`` and rows ``y0 … y1 - 1``, inside the image.
A point ``(u, v)`` of the crop is ``(u + x0, v + y0)`` in the image.

Example:
    >>> import numpy as np
    >>> region = box_to_region((100.2, 40.0, 180.7, 300.0), (640, 480), margin=0.1)
    >>> region
    (92, 14, 190, 327)
    >>> crop_image(np.zeros((480, 640, 3), np.uint8), region).shape
    (313, 98, 3)
    >>> region_to_image(torch.tensor([[[10.0, 20.0, 0.5]]]), region).tolist()
    [[[102.0, 34.0, 0.5]]]
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "Box",
    "DetectorInputError",
    "Region",
    "box_to_region",
    "check_box",
    "crop_image",
    "keypoint_box",
    "paste_region",
    "region_to_image",
]

#: ``(u_min, v_min, u_max, v_max)`` in pixels (pixel centres at integers)
Box = tuple[float, float, float, float]
#: ``(x0, y0, x1, y1)``: the columns ``x0 … x1 - 1`` and rows ``y0 … y1 - 1`` of an image
Region = tuple[int, int, int, int]


class DetectorInputError(ValueError):
    """An image, box or region a detector was given is malformed (names the argument and what
    was expected)."""


def check_box(box, what: str = "box") -> Box:
    """``box`` as four finite floats with ``u_min < u_max`` and ``v_min < v_max``.

    Raises:
        DetectorInputError: naming ``what`` for another length, non-numbers, non-finite
            values or an empty box.
    """
    if isinstance(box, Tensor):
        box = box.detach().cpu().tolist()
    elif isinstance(box, np.ndarray):
        box = box.tolist()
    try:
        b = tuple(float(v) for v in box)
    except (TypeError, ValueError):
        raise DetectorInputError(f"{what}: expected (u_min, v_min, u_max, v_max) in pixels, "
                                 f"got {box!r}") from None
    if len(b) != 4 or not all(math.isfinite(v) for v in b):
        raise DetectorInputError(f"{what}: expected 4 finite numbers (u_min, v_min, u_max, "
                                 f"v_max) in pixels, got {box!r}")
    if not (b[0] < b[2] and b[1] < b[3]):
        raise DetectorInputError(f"{what}: expected u_min < u_max and v_min < v_max, got "
                                 f"{b}")
    return b  # type: ignore[return-value]


def _check_size(size, what: str = "size") -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise DetectorInputError(f"{what}: expected the image's (width, height), got {size!r}"
                                 ) from None
    if w < 1 or h < 1:
        raise DetectorInputError(f"{what}: expected a positive (width, height), got {size!r}")
    return w, h


def box_to_region(box, size: Sequence[int], margin: float = 0.0) -> Region | None:
    """The crop of ``box`` in an image of ``size``: the box widened by ``margin`` times its
    width and height on each side, as whole pixels, clipped to the image.

    Args:
        box: ``(u_min, v_min, u_max, v_max)`` in pixels.
        size: the image's ``(width, height)``.
        margin: the fraction of the box's width (height) added left and right (top and
            bottom), ``>= 0``.

    Returns:
        the region ``(x0, y0, x1, y1)``, every pixel any part of which the widened box
        covers; None when the widened box misses the image.

    Raises:
        DetectorInputError: a malformed box or size, or a negative margin.
    """
    u0, v0, u1, v1 = check_box(box)
    W, H = _check_size(size)
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or \
            not (math.isfinite(margin) and margin >= 0):
        raise DetectorInputError(f"margin: expected a fraction of the box's size >= 0, got "
                                 f"{margin!r}")
    mu, mv = margin * (u1 - u0), margin * (v1 - v0)
    u0, v0, u1, v1 = u0 - mu, v0 - mv, u1 + mu, v1 + mv
    # pixel i covers [i - 0.5, i + 0.5): the first and last pixel the box reaches
    x0, y0 = max(0, math.floor(u0 + 0.5)), max(0, math.floor(v0 + 0.5))
    x1, y1 = min(W, math.ceil(u1 + 0.5)), min(H, math.ceil(v1 + 0.5))
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _check_region(region, size: tuple[int, int] | None = None, what: str = "region") -> Region:
    try:
        r = tuple(int(v) for v in region)
        ok = len(r) == 4 and all(float(v) == int(v) for v in region)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DetectorInputError(f"{what}: expected integer pixel ranges (x0, y0, x1, y1), got "
                                 f"{region!r}")
    x0, y0, x1, y1 = r
    W, H = size if size is not None else (x1, y1)
    if not (0 <= x0 < x1 <= W and 0 <= y0 < y1 <= H):
        raise DetectorInputError(f"{what}: expected 0 <= x0 < x1 <= {W} and 0 <= y0 < y1 <= "
                                 f"{H} (the image's width and height), got {r}")
    return r  # type: ignore[return-value]


def crop_image(image, region: Region):
    """The pixels of ``region`` of an ``(H, W, ...)`` image (a view, not a copy).

    Raises:
        DetectorInputError: a region outside the image or not of integers.
    """
    x0, y0, x1, y1 = _check_region(region, (image.shape[1], image.shape[0]))
    return image[y0:y1, x0:x1]


def region_to_image(keypoints: Tensor, region: Region | None) -> Tensor:
    """Keypoints ``(..., K, 2 or 3)`` in the pixels of a crop, moved to the full image's
    pixels (``u + x0``, ``v + y0``; a third column, the confidence, is kept). None: unchanged.

    Raises:
        DetectorInputError: a last dimension other than 2 or 3, or a malformed region.
    """
    if keypoints.dim() < 1 or keypoints.shape[-1] not in (2, 3):
        raise DetectorInputError(f"keypoints: expected shape (..., 2) or (..., 3) (u, v[, "
                                 f"confidence]), got {tuple(keypoints.shape)}")
    if region is None:
        return keypoints
    x0, y0, _, _ = _check_region(region)
    shift = torch.zeros(keypoints.shape[-1], dtype=keypoints.dtype, device=keypoints.device)
    shift[0], shift[1] = x0, y0
    return keypoints + shift


def paste_region(crop: Tensor, region: Region | None, size: Sequence[int]) -> Tensor:
    """An ``(h, w)`` map of a crop (a mask) placed into a zero ``(H, W)`` map of the image of
    ``size`` at ``region`` (None: the crop is the whole image and is returned as it is).

    Raises:
        DetectorInputError: a crop whose shape is not the region's, or a region outside the
            image.
    """
    W, H = _check_size(size)
    if region is None:
        if tuple(crop.shape) != (H, W):
            raise DetectorInputError(f"crop: expected shape ({H}, {W}) (the whole image), got "
                                     f"{tuple(crop.shape)}")
        return crop
    x0, y0, x1, y1 = _check_region(region, (W, H))
    if tuple(crop.shape) != (y1 - y0, x1 - x0):
        raise DetectorInputError(f"crop: expected shape ({y1 - y0}, {x1 - x0}) (the region "
                                 f"{region}), got {tuple(crop.shape)}")
    out = torch.zeros((H, W), dtype=crop.dtype, device=crop.device)
    out[y0:y1, x0:x1] = crop
    return out


def keypoint_box(keypoints: Tensor, min_confidence: float = 0.0) -> Box | None:
    """The box ``(u_min, v_min, u_max, v_max)`` of the keypoints whose confidence is above
    ``min_confidence`` — e.g. a subject's keypoints of the previous frame, or the projection of
    its triangulated keypoints — to pass to a detector (widened by its ``margin``).

    Args:
        keypoints: ``(K, 3)`` u, v, confidence (or ``(1, K, 3)``: one person).
        min_confidence: keypoints at or below it are left out.

    Returns:
        the box, or None when fewer than two keypoints are kept or they span no area.

    Raises:
        DetectorInputError: another shape, or several people.
    """
    x = keypoints[0] if keypoints.dim() == 3 and keypoints.shape[0] == 1 else keypoints
    if x.dim() != 2 or x.shape[-1] != 3:
        raise DetectorInputError(f"keypoints: expected shape (K, 3) (u, v, confidence) of one "
                                 f"person, got {tuple(keypoints.shape)}")
    keep = (x[:, 2] > min_confidence) & torch.isfinite(x[:, :2]).all(-1)
    if int(keep.sum()) < 2:
        return None
    p = x[keep, :2].double()
    lo, hi = p.min(0).values.tolist(), p.max(0).values.tolist()
    if not (lo[0] < hi[0] and lo[1] < hi[1]):
        return None
    return lo[0], lo[1], hi[0], hi[1]
