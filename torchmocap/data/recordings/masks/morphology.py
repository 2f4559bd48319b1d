"""Binary morphology on batches of masks ``(N, H, W)``: square dilation/erosion, opening,
closing (torch, any device), hole filling and small-component removal (scipy.ndimage, per image).

Outside the image counts as background for dilation and as foreground for erosion, so a
region touching the border is neither eroded from it nor grown into it.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["closing", "dilate", "drop_small_components", "erode", "fill_holes", "opening"]


def _window_any(x: Tensor, radius: int, dim: int) -> Tensor:
    """True where any of ``x[i - r .. i + r]`` along ``dim`` is (outside counts as False).

    The window doubles in length with each OR of two shifted copies, so the cost grows with
    log(r) (bool tensors, any device).
    """
    n, k = x.shape[dim], 2 * radius + 1
    pad = torch.zeros_like(x.narrow(dim, 0, 1)).expand(
        *[radius if d == dim % x.dim() else s for d, s in enumerate(x.shape)])
    y = torch.cat([pad, x, pad], dim)  # y[j] will cover x[j - r .. j + r]
    length, w = n + 2 * radius, 1
    while 2 * w <= k:  # y[j]: any of the padded x[j .. j + 2w - 1]
        y = y.narrow(dim, 0, length - w) | y.narrow(dim, w, length - w)
        length, w = length - w, 2 * w
    if w < k:  # two overlapping windows of w cover k
        y = y.narrow(dim, 0, length - (k - w)) | y.narrow(dim, k - w, length - (k - w))
    return y


def dilate(masks: Tensor, radius: int) -> Tensor:
    """Dilation of bool ``(N, H, W)`` by a ``(2r+1)²`` square."""
    if radius <= 0:
        return masks
    return _window_any(_window_any(masks, radius, -1), radius, -2)


def erode(masks: Tensor, radius: int) -> Tensor:
    """Erosion of bool ``(N, H, W)`` by a ``(2r+1)²`` square (the border does not erode)."""
    if radius <= 0:
        return masks
    return ~dilate(~masks, radius)


def opening(masks: Tensor, radius: int) -> Tensor:
    """Opening (erosion then dilation): removes specks narrower than ``2r+1`` pixels."""
    return dilate(erode(masks, radius), radius)


def closing(masks: Tensor, radius: int) -> Tensor:
    """Closing (dilation then erosion): bridges gaps narrower than ``2r+1`` pixels."""
    return erode(dilate(masks, radius), radius)


def _per_image_structure() -> np.ndarray:
    """8-connectivity within an image, none across the batch axis."""
    s = np.zeros((3, 3, 3), dtype=bool)
    s[1] = True
    return s


def fill_holes(masks: Tensor) -> Tensor:
    """Fill background regions of ``(N, H, W)`` bool masks that do not reach the image border
    (4-connected background, so a diagonal gap in an outline does not let a hole leak)."""
    from scipy import ndimage

    m = masks.detach().cpu().numpy()
    s = np.zeros((3, 3, 3), dtype=bool)
    s[1] = ndimage.generate_binary_structure(2, 1)
    labels, n = ndimage.label(~m, structure=s)
    if n == 0:
        return masks
    border = np.concatenate([labels[:, 0].ravel(), labels[:, -1].ravel(),
                             labels[:, :, 0].ravel(), labels[:, :, -1].ravel()])
    outside = np.zeros(n + 1, dtype=bool)
    outside[border] = True
    outside[0] = True  # label 0 is the foreground itself
    return torch.from_numpy(m | ~outside[labels]).to(masks.device)


def drop_small_components(masks: Tensor, min_pixels: int) -> Tensor:
    """Remove 8-connected components of fewer than ``min_pixels`` pixels from ``(N, H, W)``."""
    if min_pixels <= 1:
        return masks
    from scipy import ndimage

    m = masks.detach().cpu().numpy()
    labels, n = ndimage.label(m, structure=_per_image_structure())
    if n == 0:
        return masks
    sizes = np.bincount(labels.ravel())
    keep = sizes >= min_pixels
    keep[0] = False
    return torch.from_numpy(keep[labels]).to(masks.device)
