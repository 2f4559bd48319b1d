"""Align a background plate to a video's own background: affine warp plus brightness gain/offset.

A plate taken at another time can be off by a few pixels (a camera nudged, a video resampled by
its encoder) and by exposure. :func:`register_images` finds, per camera, the affine map from the
template's pixels to the image's pixels and a gain/offset of the grey level, by robust
(Tukey-weighted) Gauss–Newton on an image pyramid; the subject, moved objects and people in
either picture are outliers.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["register_images", "warp_images"]

#: Tukey biweight constant (95 % efficiency under Gaussian noise)
_TUKEY = 4.685


def _blur(x: Tensor) -> Tensor:
    """3×3 binomial blur of ``(C, 1, H, W)`` (edges replicated)."""
    k = torch.tensor([1.0, 2.0, 1.0], dtype=x.dtype, device=x.device) / 4
    x = F.pad(x, (1, 1, 1, 1), mode="replicate")
    x = F.conv2d(x, k.view(1, 1, 1, 3))
    return F.conv2d(x, k.view(1, 1, 3, 1))


def _gradient(x: Tensor) -> Tensor:
    """Central differences ``(C, 2, H, W)`` (d/dx, d/dy) of ``(C, 1, H, W)``."""
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    gx = (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]) / 2
    gy = (p[..., 2:, 1:-1] - p[..., :-2, 1:-1]) / 2
    return torch.cat([gx, gy], 1)


def _pyramid(x: Tensor, levels: int) -> list[Tensor]:
    out = [x]
    for _ in range(levels - 1):
        if min(out[-1].shape[-2:]) < 32:
            break
        out.append(F.avg_pool2d(out[-1], 2, ceil_mode=True))
    return out


def _sample(x: Tensor, pix: Tensor, level: int) -> Tensor:
    """Bilinear samples of level-``level`` images ``(C, K, h, w)`` at level-0 pixel positions
    ``pix (C, H, W, 2)``: ``(C, K, H, W)`` (zeros outside)."""
    f = 2.0 ** level
    h, w = x.shape[-2:]
    g = torch.stack([((pix[..., 0] + 0.5) / f) / w * 2 - 1,
                     ((pix[..., 1] + 0.5) / f) / h * 2 - 1], -1)
    return F.grid_sample(x, g, mode="bilinear", padding_mode="zeros", align_corners=False)


def _warp_grid(affine: Tensor, H: int, W: int) -> Tensor:
    """Level-0 image positions ``(C, H, W, 2)`` of template pixels under ``affine (C, 2, 3)``."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=affine.dtype, device=affine.device),
                            torch.arange(W, dtype=affine.dtype, device=affine.device),
                            indexing="ij")
    xy1 = torch.stack([xs, ys, torch.ones_like(xs)], -1)  # (H, W, 3)
    return torch.einsum("cij,hwj->chwi", affine, xy1)


def warp_images(images: Tensor, affine: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Resample ``images (C, K, h', w')`` onto a ``size = (H, W)`` grid: output pixel ``(x, y)``
    takes the image at ``affine[c] @ (x, y, 1)`` (bilinear).

    Returns:
        ``(C, K, H, W)`` warped images and ``(C, H, W)`` bool, True where the source position
        lies inside the image.
    """
    H, W = size
    pix = _warp_grid(affine.to(images.dtype), H, W)
    h, w = images.shape[-2:]
    inside = ((pix[..., 0] >= -0.5) & (pix[..., 0] <= w - 0.5) & (pix[..., 1] >= -0.5)
              & (pix[..., 1] <= h - 0.5))
    return _sample(images, pix, 0), inside


def _robust_scale(r: Tensor, w: Tensor) -> Tensor:
    """``(C,)`` 1.4826 · median |r| over the pixels where ``w`` is True (at least 1e-3)."""
    out = []
    for rc, wc in zip(r, w):
        v = rc[wc].abs()
        out.append(v.median() if v.numel() else torch.ones((), dtype=r.dtype, device=r.device))
    return (torch.stack(out) * 1.4826).clamp_min(1e-3)


def register_images(template: Tensor, image: Tensor, valid: Tensor, levels: int = 3,
                    iterations: int = 12, max_size: int = 640) -> dict[str, Tensor]:
    """Affine + gain/offset alignment ``template(x) ≈ gain · image(A x) + offset`` per camera.

    Args:
        template: ``(C, H, W)`` grey images (float) that define the output geometry.
        image: ``(C, H', W')`` grey images to align to them; pixel ``(0, 0)`` of both is
            assumed to show about the same point (the search starts at the identity).
        valid: ``(C, H, W)`` bool, template pixels to use.
        levels: pyramid levels used (each halves the size).
        iterations: Gauss–Newton steps per level.
        max_size: the finest level used is the first whose larger side is at most this
            (sub-pixel accuracy there is plenty; finer levels cost time).

    Returns:
        dict with ``affine (C, 2, 3)`` (template pixel → image pixel, OpenCV pixel centres),
        ``gain (C,)``, ``offset (C,)``, ``inliers (C,)`` (fraction of valid pixels with
        non-zero Tukey weight at the end) and ``residual (C,)`` (robust residual scale).

    Example:
        >>> t = torch.rand(1, 64, 64)
        >>> register_images(t, t, torch.ones(1, 64, 64, dtype=torch.bool))["affine"].shape
        torch.Size([1, 2, 3])
    """
    C, H, W = template.shape
    dt, dev = torch.float32, template.device
    finest = max(0, math.ceil(math.log2(max(H, W) / max_size)))
    tpl = _pyramid(_blur(template.to(dt)[:, None]), finest + levels)
    img = _pyramid(_blur(image.to(dt)[:, None]), len(tpl))
    val = _pyramid(valid.to(dt)[:, None], len(tpl))
    finest = min(finest, len(tpl) - 1)
    # normalised coordinates: x~ = (x - cx) / L in level-0 pixels
    cx, cy, L = (W - 1) / 2, (H - 1) / 2, max(H, W) / 2
    M = torch.zeros(C, 2, 3, dtype=torch.float64, device=dev)  # warp in normalised units
    # grey-level gain/offset start from matched medians and spreads
    t0, i0 = template.to(dt).reshape(C, -1), image.to(dt).reshape(C, -1)
    tm, im = t0.median(1).values, i0.median(1).values
    gain = ((t0 - tm[:, None]).abs().median(1).values.clamp_min(1e-3)
            / (i0 - im[:, None]).abs().median(1).values.clamp_min(1e-3)).double()
    offset = (tm - gain.float() * im).double()
    eye = torch.eye(8, dtype=torch.float64, device=dev)
    weights = inside = None
    for level in reversed(range(finest, len(tpl))):
        T = tpl[level][:, 0]
        h, w = T.shape[-2:]
        f = 2.0 ** level
        ys, xs = torch.meshgrid(torch.arange(h, dtype=dt, device=dev),
                                torch.arange(w, dtype=dt, device=dev), indexing="ij")
        x0, y0 = (xs + 0.5) * f - 0.5, (ys + 0.5) * f - 0.5  # level-0 pixel centres
        xn, yn = (x0 - cx) / L, (y0 - cy) / L
        basis = torch.stack([xn, yn, torch.ones_like(xn)], -1)  # (h, w, 3)
        grad = _gradient(img[level]) / f  # per level-0 pixel
        src = torch.cat([img[level], grad], 1)
        hi, wi = img[level].shape[-2:]
        for _ in range(iterations):
            A = M.to(dt)
            disp = torch.einsum("cij,hwj->chwi", A, basis) * L  # (C, h, w, 2) level-0 pixels
            pix = torch.stack([x0, y0], -1) + disp
            s = _sample(src, pix, level)  # (C, 3, h, w)
            Iw, gx, gy = s[:, 0], s[:, 1], s[:, 2]
            lx, ly = (pix[..., 0] + 0.5) / f - 0.5, (pix[..., 1] + 0.5) / f - 0.5
            inside = ((lx >= 0) & (lx <= wi - 1) & (ly >= 0) & (ly <= hi - 1)
                      & (val[level][:, 0] > 0.99))
            g, o = gain.to(dt)[:, None, None], offset.to(dt)[:, None, None]
            r = T - g * Iw - o
            sigma = _robust_scale(r, inside)
            u = r / (_TUKEY * sigma[:, None, None])
            weights = torch.where(inside & (u.abs() < 1), (1 - u * u) ** 2, torch.zeros_like(u))
            # Jacobian of g·I(W(x)) + o w.r.t. (M row 0, M row 1, gain, offset)
            jx = (g * gx * L)[..., None] * basis
            jy = (g * gy * L)[..., None] * basis
            J = torch.cat([jx, jy, Iw[..., None], torch.ones_like(Iw)[..., None]], -1)
            Jw = J * weights[..., None]
            Hm = torch.einsum("chwi,chwj->cij", Jw.double(), J.double())
            b = torch.einsum("chwi,chw->ci", Jw.double(), r.double())
            damp = 1e-6 * Hm.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] + 1e-9
            step = torch.linalg.solve(Hm + damp * eye, b[..., None])[..., 0]
            M = M + step[:, :6].reshape(C, 2, 3)
            gain, offset = gain + step[:, 6], offset + step[:, 7]
            if float(step[:, :6].abs().max()) * L < 1e-3 * f:
                break
    # back to pixels: A x = x + L · (M · [(x - c)/L, 1])
    Mp = M.clone()
    Mp[:, :, 2] = M[:, :, 2] * L - M[:, :, 0] * cx - M[:, :, 1] * cy
    affine = Mp + torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64,
                               device=dev)
    n_in = inside.flatten(1).sum(1).clamp_min(1)
    return {"affine": affine, "gain": gain, "offset": offset,
            "inliers": ((weights > 0).flatten(1).sum(1) / n_in).double(),
            "residual": _robust_scale(r, inside).double()}
