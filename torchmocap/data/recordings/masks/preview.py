"""Preview of foreground masks: a grid of views, each image with its mask tinted green, the
parts removed by the multi-view check (or the keypoint gate) magenta, and the keypoints
yellow."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from torch import Tensor

from torchmocap.atomic import atomic_path

__all__ = ["mask_preview", "write_mask_preview"]

_KEEP = np.array([40.0, 230.0, 60.0])
_REMOVED = np.array([255.0, 40.0, 230.0])
_KEYPOINT = np.array([255, 230, 0], dtype=np.uint8)
_GAP = 4


def mask_preview(images: Tensor, masks: Tensor, removed: Tensor | None = None,
                 sizes: Tensor | None = None, keypoints: Tensor | None = None,
                 columns: int | None = None, min_confidence: float = 0.3) -> np.ndarray:
    """The preview image ``(rows·h + gaps, columns·w + gaps, 3)`` uint8.

    Args:
        images: ``(C, h, w, 3)`` uint8 views at the masks' resolution.
        masks: ``(C, h, w)`` bool final masks (tinted green).
        removed: ``(C, h, w)`` bool foreground that the checks removed (tinted magenta).
        sizes: ``(C, 2)`` (width, height) of each view inside the arrays (default: all).
        keypoints: ``(C, K, 3)`` (u, v, confidence) drawn as yellow dots where the confidence
            is at least ``min_confidence``.
        columns: views per row (default: all in one row up to 4).
    """
    C, h, w = masks.shape
    img = images.detach().cpu().numpy().astype(np.float64)
    m = masks.detach().cpu().numpy().astype(bool)
    r = np.zeros_like(m) if removed is None else removed.detach().cpu().numpy().astype(bool)
    tint = img * 0.6
    tint[m] = 0.45 * img[m] + 0.55 * _KEEP
    tint[r] = 0.45 * img[r] + 0.55 * _REMOVED
    tint = tint.round().clip(0, 255).astype(np.uint8)
    if keypoints is not None:
        kp = keypoints.detach().cpu().numpy()
        for c in range(C):
            for u, v, conf in kp[c]:
                if not (conf >= min_confidence and np.isfinite(u) and np.isfinite(v)):
                    continue
                x, y = int(round(u)), int(round(v))
                tint[c, max(0, y - 1):y + 2, max(0, x - 1):x + 2] = _KEYPOINT
    if sizes is not None:
        for c, (wc, hc) in enumerate(sizes.tolist()):
            tint[c, hc:], tint[c, :, wc:] = 0, 0
    cols = min(C, 4) if columns is None else max(1, int(columns))
    rows = math.ceil(C / cols)
    grid = np.full((rows * h + (rows - 1) * _GAP, cols * w + (cols - 1) * _GAP, 3), 255,
                   dtype=np.uint8)
    for c in range(C):
        y, x = (c // cols) * (h + _GAP), (c % cols) * (w + _GAP)
        grid[y:y + h, x:x + w] = tint[c]
    return grid


def write_mask_preview(path: str | os.PathLike, images: Tensor, masks: Tensor,
                       removed: Tensor | None = None, sizes: Tensor | None = None,
                       keypoints: Tensor | None = None, columns: int | None = None) -> Path:
    """Write :func:`mask_preview` as a PNG at ``path`` (atomically); returns the path."""
    from PIL import Image

    grid = mask_preview(images, masks, removed, sizes, keypoints, columns)
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(grid).save(tmp, format="PNG")
    return path

