"""Visual-hull carving from multi-view silhouettes (vectorised voxel carving)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torchmocap.cameras.rig import CameraError, CameraRig

__all__ = ["VisualHull", "largest_component", "visual_hull"]


@dataclass
class VisualHull:
    """Result of :func:`visual_hull`.

    Attributes:
        occupancy: ``(X, Y, Z)`` bool grid, True where the voxel centre projects inside every mask.
        origin: ``(3,)`` centre of voxel ``[0, 0, 0]`` (metres).
        voxel_size: edge length (metres).
    """

    occupancy: Tensor
    origin: Tensor
    voxel_size: float

    @property
    def voxel_volume(self) -> float:
        return self.voxel_size**3

    @property
    def volume(self) -> float:
        """Occupied volume in m³."""
        return int(self.occupancy.sum()) * self.voxel_volume

    def centers(self, occupied_only: bool = True) -> Tensor:
        """``(M, 3)`` voxel centres (occupied ones by default)."""
        idx = self.occupancy.nonzero() if occupied_only else torch.stack(torch.meshgrid(
            *[torch.arange(n, device=self.occupancy.device) for n in self.occupancy.shape],
            indexing="ij"), -1).reshape(-1, 3)
        return self.origin + idx.to(self.origin.dtype) * self.voxel_size

    def largest_component(self) -> VisualHull:
        """The hull restricted to its largest 26-connected component."""
        return VisualHull(largest_component(self.occupancy), self.origin, self.voxel_size)

    def silhouettes(self, rig: CameraRig) -> Tensor:
        """Render the occupied voxels into every view: ``(C, H, W)`` bool masks.

        Each voxel centre is projected (with distortion) and splatted as a square of half-width
        ``ceil(f · voxel_size / (2 · depth))`` pixels, the image of the voxel's cube; comparing
        with the input masks (IoU) measures how consistent calibration and silhouettes are.
        """
        sizes = rig.image_size.long()
        W, H = int(sizes[:, 0].max()), int(sizes[:, 1].max())
        Wc, Hc = sizes[:, 0, None], sizes[:, 1, None]  # (C, 1) each view's own size
        C = rig.num_cameras
        out = torch.zeros(C, H * W, dtype=torch.bool, device=self.occupancy.device)
        c = self.centers()
        if c.shape[0] == 0:
            return out.reshape(C, H, W)
        with torch.no_grad():
            pix, depth, vis = rig.project(c.to(rig.K.dtype))
        f = rig.K[:, 0, 0, None].to(depth.dtype)
        half = torch.ceil(f * self.voxel_size / (2 * depth.clamp_min(1e-6))).long().clamp(0, 8)
        u0, v0 = pix[..., 0].round().long(), pix[..., 1].round().long()
        cam = torch.arange(C, device=out.device)[:, None].expand_as(u0)
        kmax = int(half[vis].max()) if bool(vis.any()) else 0
        for dv in range(-kmax, kmax + 1):
            for du in range(-kmax, kmax + 1):
                u, v = u0 + du, v0 + dv
                ok = vis & (half >= max(abs(du), abs(dv))) & (u >= 0) & (u < Wc) & (v >= 0) & \
                    (v < Hc)
                out[cam[ok], (v * W + u)[ok]] = True
        return out.reshape(C, H, W)

    def extent(self) -> tuple[Tensor, Tensor]:
        """``(min, max)`` corners ``(3,)`` of the occupied voxels' cubes (metres)."""
        c = self.centers()
        if c.shape[0] == 0:
            raise CameraError("the visual hull is empty")
        h = self.voxel_size / 2
        return c.min(0).values - h, c.max(0).values + h


def largest_component(occupancy: Tensor) -> Tensor:
    """Keep the largest 26-connected component of a boolean ``(X, Y, Z)`` grid (scipy.ndimage)."""
    from scipy import ndimage

    occ = occupancy.detach().cpu().numpy().astype(bool)
    labels, n = ndimage.label(occ, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return torch.zeros_like(occupancy, dtype=torch.bool)
    sizes = np.bincount(labels.ravel())[1:]
    keep = labels == (int(np.argmax(sizes)) + 1)
    return torch.from_numpy(keep).to(occupancy.device)


def _masks_tensor(masks: Tensor | Sequence[Tensor] | np.ndarray, rig: CameraRig) -> Tensor:
    if isinstance(masks, (list, tuple)):
        masks = torch.stack([torch.as_tensor(np.asarray(m)) for m in masks])
    m = torch.as_tensor(masks)
    C = rig.num_cameras
    if m.dim() != 3 or m.shape[0] != C:
        raise CameraError(f"masks must have shape ({C}, H, W), got {tuple(m.shape)}")
    sizes = rig.image_size.long()
    W, H = int(sizes[:, 0].max()), int(sizes[:, 1].max())
    if m.shape[1:] != (H, W):
        raise CameraError(f"masks of shape {tuple(m.shape)} do not match the rig's image sizes "
                          f"{rig.image_size.tolist()} (width, height): expected (C, {H}, {W}), "
                          "the largest view's size (a smaller view in the top-left corner)")
    m = m.to(rig.K.device)
    return m > 0 if m.dtype != torch.bool else m


def visual_hull(rig: CameraRig, masks: Tensor | Sequence[Tensor] | np.ndarray,
                bounds: Tensor | Sequence[Sequence[float]], resolution: float,
                min_views: int | None = None, chunk: int = 1 << 18) -> VisualHull:
    """Carve a visual hull: keep voxels whose centre projects inside the silhouette of every view.

    Args:
        rig: C calibrated cameras (with distortion, which is applied: masks are raw images).
        masks: ``(C, H, W)`` foreground masks (bool, or any dtype where > 0 is foreground, e.g.
            0/255 BMPs) of the largest view's size; a smaller view fills the top-left corner
            (the layout of a sequence's silhouettes), its pixels beyond its own
            ``image_size`` are not looked at.
        bounds: ``(3, 2)`` world box ``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` in metres.
        resolution: voxel edge in metres.
        min_views: voxels must fall inside this many masks (default: all C). A voxel that
            projects outside an image (or behind a camera) counts as outside that mask.
        chunk: voxels projected per batch (memory bound).

    Returns:
        :class:`VisualHull` with the occupancy grid.

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> masks = torch.ones(4, 240, 320, dtype=torch.bool)
        >>> hull = visual_hull(make_ring_rig(4), masks, [[-0.5, 0.5], [-0.5, 0.5], [0, 2]], 0.1)
        >>> hull.occupancy.shape
        torch.Size([10, 10, 20])
    """
    m = _masks_tensor(masks, rig)
    C = rig.num_cameras
    need = C if min_views is None else int(min_views)
    if not 1 <= need <= C:
        raise CameraError(f"min_views must be in [1, {C}], got {min_views}")
    b = torch.as_tensor(bounds, dtype=torch.float64)
    if b.shape != (3, 2) or bool((b[:, 1] <= b[:, 0]).any()):
        raise CameraError(f"bounds must be (3, 2) with min < max per axis, got {b.tolist()}")
    if not resolution > 0:
        raise CameraError(f"resolution must be positive, got {resolution}")
    n = torch.floor((b[:, 1] - b[:, 0]) / resolution).long().clamp_min(1)
    origin = b[:, 0] + resolution / 2
    dev = rig.K.device
    axes = [origin[i] + torch.arange(int(n[i]), dtype=torch.float64) * resolution for i in range(3)]
    axes = [a.to(dev) for a in axes]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    H, W = m.shape[1:]
    Wc, Hc = rig.image_size.long()[:, 0, None], rig.image_size.long()[:, 1, None]  # (C, 1)
    flat = m.reshape(C, -1)
    count = torch.empty(grid.shape[0], dtype=torch.int16, device=dev)
    cam_idx = torch.arange(C, device=dev)[:, None]
    with torch.no_grad():
        for s in range(0, grid.shape[0], chunk):
            pts = grid[s:s + chunk]
            pix, _, vis = rig.project(pts)  # (C, M, 2), (C, M)
            u, v = pix[..., 0].round().long(), pix[..., 1].round().long()
            in_image = (u >= 0) & (u < Wc) & (v >= 0) & (v < Hc)
            ui, vi = u.clamp(0, W - 1), v.clamp(0, H - 1)
            inside = flat[cam_idx, vi * W + ui] & vis & in_image
            count[s:s + chunk] = inside.sum(0).to(torch.int16)
    occ = (count >= need).reshape(*n.tolist())
    return VisualHull(occ, origin.to(dev), float(resolution))
