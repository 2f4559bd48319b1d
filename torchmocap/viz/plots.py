"""Matplotlib figures (Agg backend, files only): skeleton sequences and image overlays."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from torch import Tensor  # noqa: E402

__all__ = ["capsule_outlines", "overlay_on_image", "plot_skeleton_sequence", "side_colors"]

_LEFT, _RIGHT, _MID = "#1f77b4", "#d62728", "#2ca02c"


def side_colors(joint_names: Sequence[str]) -> list[str]:
    """Colour per joint: left (``l_``/``Left``) blue, right red, centre green."""
    out = []
    for n in joint_names:
        low = n.lower()
        if low.startswith(("l_", "left")):
            out.append(_LEFT)
        elif low.startswith(("r_", "right")):
            out.append(_RIGHT)
        else:
            out.append(_MID)
    return out


def _np(x: Any) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _positions(skeleton: Any, data: Any) -> np.ndarray:
    """``(T, J, 3)`` joint positions from thetas ``(T, D)``, positions or ``Kinematics``."""
    if hasattr(data, "positions"):
        return _np(data.positions).reshape(-1, data.positions.shape[-2], 3)
    x = torch.as_tensor(data)
    J = len(skeleton.joint_names)
    if x.dim() >= 2 and x.shape[-2:] == (J, 3):
        return _np(x).reshape(-1, J, 3)
    if x.shape[-1] == skeleton.num_dofs:
        theta = x.to(skeleton.offsets.dtype).reshape(-1, skeleton.num_dofs)
        with torch.no_grad():
            return _np(skeleton.joint_positions(theta))
    raise ValueError(f"thetas: expected (T, {skeleton.num_dofs}) poses or (T, {J}, 3) "
                     f"positions, got {tuple(x.shape)}")


def _save(fig: Figure, path: str | Path, dpi: int) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def plot_skeleton_sequence(skeleton: Any, thetas: Any, frames: Sequence[int] | None, path: str |
                           Path, titles: Sequence[str] | None = None, elev: float = 15.0,
                           azim: float = -70.0, dpi: int = 100) -> Path:
    """3D stick figures of a few frames side by side, saved as an image.

    Args:
        skeleton: the :class:`~torchmocap.skeleton.Skeleton` (joint names and parents).
        thetas: poses ``(T, D)``, joint positions ``(T, J, 3)`` or batched ``Kinematics``.
        frames: frame indices to draw (default: up to 4 evenly spaced).
        path: output file (``.png``, ``.pdf``, ...).
        titles: optional per-panel titles (default ``frame k``).
        elev, azim: view angles (degrees) of every panel.

    Returns:
        the written path. All panels share one bounding box (equal scale, Z up).
    """
    pos = _positions(skeleton, thetas)
    T = pos.shape[0]
    if frames is None:
        frames = np.unique(np.linspace(0, T - 1, min(T, 4)).round().astype(int)).tolist()
    frames = list(frames)
    if not frames or min(frames) < -T or max(frames) >= T:
        raise ValueError(f"frames: expected indices in [0, {T}), got {frames}")
    parents = list(skeleton.parents)
    colors = side_colors(skeleton.joint_names)
    sel = pos[frames]
    lo, hi = sel.reshape(-1, 3).min(0), sel.reshape(-1, 3).max(0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 0.5)
    fig = plt.figure(figsize=(3.2 * len(frames), 4.2))
    for k, f in enumerate(frames):
        ax = fig.add_subplot(1, len(frames), k + 1, projection="3d")
        p = pos[f]
        for j, par in enumerate(parents):
            if par >= 0:
                ax.plot(*zip(p[par], p[j]), color=colors[j], lw=2.5)
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=colors, s=10, depthshade=False)
        for i in range(3):
            getattr(ax, f"set_{'xyz'[i]}lim")(centre[i] - half, centre[i] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_zlabel("z")
        ax.set_title(titles[k] if titles is not None else f"frame {f}")
    fig.tight_layout()
    return _save(fig, path, dpi)


def capsule_outlines(rig: Any, camera_index: int, endpoints: Tensor, radii: Tensor,
                     rings: int = 9, per_ring: int = 24) -> list[np.ndarray]:
    """Image outlines of capsules in one camera: convex hull of projected surface rings.

    A capsule is convex, so its perspective image is the convex hull of its projected surface;
    we project ``rings × per_ring`` points per hemisphere-capped capsule and take the hull.

    Args:
        rig: a :class:`~torchmocap.cameras.CameraRig`.
        endpoints: ``(B, 2, 3)`` capsule axes; radii ``(B,)``.

    Returns:
        list of ``(K, 2)`` pixel polygons (capsules partly behind the camera are skipped).
    """
    from scipy.spatial import ConvexHull

    from torchmocap.body.capsules import _orthonormal_frame

    dt = torch.float64
    ep = endpoints.detach().to("cpu", dt)
    r = radii.detach().to("cpu", dt).expand(ep.shape[0])
    a, b = ep[:, 0], ep[:, 1]
    axis = b - a
    L = axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    axis = axis / L
    e1, e2 = _orthonormal_frame(axis)
    phi = torch.linspace(0, 2 * np.pi, per_ring + 1, dtype=dt)[:-1]
    theta = torch.linspace(0, np.pi / 2, rings, dtype=dt)
    circ = torch.cos(phi)[:, None, None] * e1 + torch.sin(phi)[:, None, None] * e2  # (K, B, 3)
    pts = []
    for th in theta:  # hemisphere rings at both ends
        for end, sgn in ((a, -1.0), (b, 1.0)):
            ring = end + r[:, None] * (torch.cos(th) * circ + sgn * torch.sin(th) * axis)
            pts.append(ring)
    P = torch.cat(pts, 0).transpose(0, 1)  # (B, M, 3)
    sub = rig.subset([camera_index])
    pix, depth, _ = sub.project(P.to(sub.K.dtype), distort=True)
    out = []
    for i in range(P.shape[0]):
        if bool((depth[i, 0] <= 0).any()):
            continue
        q = _np(pix[i, 0])
        try:
            hull = ConvexHull(q)
        except Exception:  # noqa: BLE001 - degenerate (collinear) projection
            continue
        out.append(q[hull.vertices])
    return out


def overlay_on_image(image: Any, rig: Any, camera_index: int, pose: Any, path: str | Path,
                     skeleton: Any = None, capsules: Any = None, mask: Any = None,
                     title: str | None = None) -> Path:
    """Projected skeleton (and capsule outlines) drawn over a camera image, same pixel size.

    Args:
        image: ``(H, W)`` grey or ``(H, W, 3)`` colour image (numpy/tensor; uint8 or float 0–1).
        rig: :class:`~torchmocap.cameras.CameraRig`; ``camera_index`` selects the view.
        pose: ``Kinematics`` of one pose, or joint positions ``(J, 3)``.
        path: output PNG; its size is exactly ``W × H`` pixels, so pixel ``(u, v)`` of the
            figure is pixel ``(u, v)`` of the image.
        skeleton: gives bone connectivity (``parents``) and side colours; without it only joints
            are drawn.
        capsules: optional :class:`~torchmocap.body.CapsuleBody` whose outlines are drawn.
        mask: optional ``(H, W)`` foreground mask tinted in yellow.

    Returns:
        the written path.
    """
    img = _np(image)
    if img.ndim not in (2, 3):
        raise ValueError(f"image: expected (H, W) or (H, W, 3), got shape {img.shape}")
    if img.max() > 1.0:
        img = img / 255.0
    H, W = img.shape[:2]
    size = rig.image_size[camera_index].tolist()
    if [W, H] != size:
        raise ValueError(f"image: size {W}x{H} does not match camera {camera_index} "
                         f"({size[0]}x{size[1]})")
    P = pose.positions if hasattr(pose, "positions") else torch.as_tensor(pose)
    if P.dim() != 2 or P.shape[-1] != 3:
        raise ValueError(f"pose: expected one pose (J, 3) or its Kinematics, got "
                         f"{tuple(P.shape)}")
    sub = rig.subset([camera_index])
    pix, depth, _ = sub.project(P.detach().to(sub.K.dtype))
    uv = _np(pix[0])
    front = _np(depth[0]) > 0
    dpi = 100
    fig = plt.figure(figsize=(W / dpi, H / dpi), dpi=dpi)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(img, cmap="gray" if img.ndim == 2 else None, vmin=0, vmax=1,
              extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
    if mask is not None:
        m = _np(mask) > 0
        tint = np.zeros((H, W, 4))
        tint[m] = (1.0, 0.85, 0.0, 0.35)
        ax.imshow(tint, extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
    if capsules is not None:
        kin_like = pose if hasattr(pose, "positions") else P
        ep = capsules.endpoints(kin_like)
        for poly in capsule_outlines(rig, camera_index, ep, capsules.radii):
            ax.fill(poly[:, 0], poly[:, 1], facecolor=(0.3, 0.9, 1.0, 0.15),
                    edgecolor=(0.3, 0.9, 1.0, 0.9), lw=1)
    names = list(skeleton.joint_names) if skeleton is not None else [""] * len(uv)
    colors = side_colors(names)
    if skeleton is not None:
        for j, par in enumerate(skeleton.parents):
            if par >= 0 and front[j] and front[par]:
                ax.plot(uv[[par, j], 0], uv[[par, j], 1], color=colors[j], lw=2)
    ax.scatter(uv[front, 0], uv[front, 1], c=[c for c, f in zip(colors, front) if f], s=12,
               zorder=3)
    if title:
        ax.text(4, 12, title, color="white", fontsize=8)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.axis("off")
    return _save(fig, path, dpi)
