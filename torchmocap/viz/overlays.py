"""Multi-view overlay grids: every camera of a rig side by side, the estimate and the ground
truth drawn in distinct colours, a legend, and the frame number and time in a title bar.

Pure numpy + PIL drawing (no matplotlib figure per frame), so a grid per tracked frame is cheap
enough for videos (:mod:`torchmocap.viz.video`).

Layout: a title bar of :data:`TITLE_HEIGHT` pixels on top (title left, legend right), then the
views in a grid of ``rows × columns`` cells, row-major in camera order; each cell is the camera
image scaled by ``scale``. Pixel ``(u, v)`` of camera ``c`` (pixel centres at integers) lands at
``(x0 + (u + 0.5)·scale − 0.5, y0 + (v + 0.5)·scale − 0.5)`` of the grid, ``(x0, y0)`` the cell's
top-left corner (see :func:`panel_origin`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from torch import Tensor

__all__ = [
    "DETECTION_COLOR",
    "ESTIMATE_COLOR",
    "MASK_TINT",
    "TITLE_HEIGHT",
    "TRUTH_COLOR",
    "frame_title",
    "grid_shape",
    "panel_origin",
    "render_overlay_grid",
    "track_overlay_frames",
    "write_overlay_grid",
]

#: colour of the estimate's skeleton (orange) and of its capsule outlines (lighter)
ESTIMATE_COLOR = (255, 128, 0)
_CAPSULE_COLOR = (255, 200, 140)
#: colour of the ground truth's skeleton (green)
TRUTH_COLOR = (40, 210, 40)
#: colour of the 2D keypoint detections (cyan)
DETECTION_COLOR = (0, 220, 255)
#: tint of the observed foreground mask (blue, 35 % opacity)
MASK_TINT = (70, 110, 255)
_MASK_ALPHA = 0.35
#: height of the title bar in pixels
TITLE_HEIGHT = 20
_JOINT_RADIUS = 2


@lru_cache(maxsize=4)
def _font(size: int = 12):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def frame_title(index: int, fps: float) -> str:
    """``"frame 12   t = 0.480 s"`` for frame ``index`` of a sequence at ``fps`` Hz."""
    return f"frame {int(index)}   t = {int(index) / float(fps):.3f} s"


def grid_shape(num_views: int, columns: int | None = None) -> tuple[int, int]:
    """``(rows, columns)`` of the view grid: ``ceil(sqrt(C))`` columns unless given."""
    if num_views < 1:
        raise ValueError(f"num_views: expected at least one view, got {num_views}")
    cols = math.ceil(math.sqrt(num_views)) if columns is None else int(columns)
    if cols < 1:
        raise ValueError(f"columns: expected a positive number, got {columns}")
    cols = min(cols, num_views)
    return math.ceil(num_views / cols), cols


def panel_origin(camera: int, cell: tuple[int, int], columns: int) -> tuple[int, int]:
    """Top-left pixel ``(x0, y0)`` in the grid of camera ``camera``'s cell (``cell`` = (w, h))."""
    r, c = divmod(int(camera), int(columns))
    return c * cell[0], TITLE_HEIGHT + r * cell[1]


def _numpy(x: Any) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu()
        return x.numpy() if x.dtype in (torch.uint8, torch.bool) else x.double().numpy()
    return np.asarray(x)


def _points(name: str, x: Any) -> Tensor:
    p = x.positions if hasattr(x, "positions") else x
    p = torch.as_tensor(p).detach()
    if p.dim() != 2 or p.shape[-1] != 3:
        raise ValueError(f"{name}: expected one pose as joint positions (J, 3) or its "
                         f"Kinematics, got shape {tuple(p.shape)}")
    if not bool(torch.isfinite(p).all()):
        raise ValueError(f"{name}: expected finite joint positions, found NaN or inf")
    return p


def _as_rgb(image: Any, name: str) -> np.ndarray:
    """``(H, W, 3)`` uint8 from a colour image, a grey image or a mask (bool/uint8/float 0–1)."""
    a = _numpy(image)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[-1] != 3):
        raise ValueError(f"{name}: expected (H, W) or (H, W, 3) per view, got {a.shape}")
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif a.dtype != np.uint8:
        a = a.astype(np.float64)
        if a.size and np.nanmax(a) <= 1.0:
            a = a * 255.0
        a = np.clip(np.nan_to_num(a), 0, 255).astype(np.uint8)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    return np.ascontiguousarray(a)


def _panel(image: np.ndarray, mask: Any, cell: tuple[int, int], scale: float) -> Image.Image:
    rgb = image.astype(np.float32)
    if mask is not None:
        m = _numpy(mask).astype(bool)

        if m.shape != rgb.shape[:2]:
            raise ValueError(f"masks: expected {rgb.shape[:2]} per view, got {m.shape}")
        rgb[m] = (1 - _MASK_ALPHA) * rgb[m] + _MASK_ALPHA * np.array(MASK_TINT, np.float32)
    im = Image.fromarray(rgb.round().astype(np.uint8), "RGB")
    if scale != 1.0:
        H, W = rgb.shape[:2]
        im = im.resize((max(1, round(W * scale)), max(1, round(H * scale))), Image.BILINEAR)
    canvas = Image.new("RGB", cell, (0, 0, 0))
    canvas.paste(im, (0, 0))
    return canvas


def _to_panel(uv: np.ndarray, scale: float) -> np.ndarray:
    return (uv + 0.5) * scale - 0.5


def _draw_skeleton(draw: ImageDraw.ImageDraw, uv: np.ndarray, front: np.ndarray,
                   parents: Sequence[int], color: tuple[int, int, int], width: int) -> None:
    for j, p in enumerate(parents):
        if p is not None and p >= 0 and front[j] and front[p]:
            draw.line([tuple(uv[p]), tuple(uv[j])], fill=color, width=width)
    r = _JOINT_RADIUS
    for j in np.nonzero(front)[0]:
        u, v = uv[j]
        draw.ellipse([u - r, v - r, u + r, v + r], fill=color)


def _draw_text(draw: ImageDraw.ImageDraw, xy: tuple[float, float], text: str,
               color=(255, 255, 255)) -> None:
    x, y = xy
    draw.text((x + 1, y + 1), text, fill=(0, 0, 0), font=_font())
    draw.text((x, y), text, fill=color, font=_font())


def _title_width(title: str, legend: list[tuple[str, tuple[int, int, int]]]) -> int:
    """Pixels the title bar needs: title, gap, then a swatch and a label per legend entry."""
    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    font = _font()
    w = 8 + (draw.textlength(title, font=font) + 12 if title else 0)
    w += sum(draw.textlength(label, font=font) + 24 for label, _ in legend)
    return math.ceil(w)


def _title_bar(width: int, title: str, legend: list[tuple[str, tuple[int, int, int]]]
               ) -> Image.Image:
    bar = Image.new("RGB", (width, TITLE_HEIGHT), (32, 32, 32))
    draw = ImageDraw.Draw(bar)
    font = _font()
    draw.text((4, 3), title, fill=(255, 255, 255), font=font)
    x = width - 4
    for label, color in reversed(legend):
        w = draw.textlength(label, font=font)
        x -= w
        draw.text((x, 3), label, fill=(255, 255, 255), font=font)
        x -= 14
        draw.rectangle([x, 5, x + 9, 14], fill=color)
        x -= 10
    return bar


def render_overlay_grid(views: Any, rig: Any, estimate: Any, parents: Sequence[int], *,
                        truth: Any = None, truth_parents: Sequence[int] | None = None,
                        masks: Any = None, capsules: tuple[Tensor, Tensor] | None = None,
                        detections: Any = None,
                        title: str = "", labels: Sequence[str] | None = None,
                        columns: int | None = None, scale: float = 1.0,
                        min_width: int = 0) -> np.ndarray:
    """Every view of ``rig`` in one image with the projected estimate (and truth) drawn over it.

    Args:
        views: ``C`` images, ``(C, H, W, 3)`` colour (uint8, or float 0–1) or ``(C, H, W)``
            grey/silhouettes (bool, uint8 or float), or a list of such per-view arrays; ``None``
            draws on black panels of the cameras' image size. A view (or mask) of the largest
            camera's size is cropped to its own camera's (a sequence's padded layout).
        rig: :class:`~torchmocap.cameras.CameraRig` with ``C`` cameras.
        estimate: joint positions ``(J, 3)`` (metres, world) or a one-pose ``Kinematics``.
        parents: parent index per joint (``-1`` for the root), e.g. ``skeleton.parents``.
        truth: optional ground-truth joint positions ``(J', 3)`` or ``Kinematics``.
        truth_parents: the truth's parents (default: ``parents``).
        masks: optional ``(C, H, W)`` foreground masks, tinted blue.
        capsules: optional ``(endpoints (B, 2, 3), radii (B,))`` of the estimate's capsule body;
            their image outlines are drawn.
        detections: optional ``(C, K, 3)`` 2D detections (u, v, confidence) in the cameras'
            pixels, drawn as :data:`DETECTION_COLOR` rings where the confidence is positive.
        title: text at the left of the title bar (e.g. :func:`frame_title`).
        labels: per-view labels (default ``cam 1 … cam C``).
        columns: grid columns (default ``ceil(sqrt(C))``).
        scale: panel size relative to the camera images (``> 0``).
        min_width: the grid is at least this wide (black on the right), e.g. so that the
            frames of a video, whose titles differ, all have one size.

    Returns:
        ``(TITLE_HEIGHT + rows·h, columns·w, 3)`` uint8 RGB, ``(w, h)`` the largest camera
        image times ``scale`` (wider, black on the right, when the title and legend need it).
        Estimate: :data:`ESTIMATE_COLOR`; truth: :data:`TRUTH_COLOR` (drawn first, so the
        estimate is on top where they coincide).

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> from torchmocap.skeleton import human31
        >>> sk, rig = human31(), make_ring_rig(4, image_size=(80, 60))
        >>> render_overlay_grid(None, rig, sk(sk.zero_pose()), sk.parents).shape
        (140, 160, 3)
    """
    C = int(rig.num_cameras)
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale: expected a finite number > 0, got {scale!r}")
    sizes = rig.image_size.detach().cpu().long().tolist()  # (C, 2) width, height
    largest = (max(h for _, h in sizes), max(w for w, _ in sizes))
    if views is None:
        images = [np.zeros((h, w, 3), np.uint8) for w, h in sizes]
    else:
        if len(views) != C:
            raise ValueError(f"views: expected {C} views (one per camera), got {len(views)}")
        images = [_as_rgb(v, "views") for v in views]
        for c, (img, (w, h)) in enumerate(zip(images, sizes)):
            if img.shape[:2] == largest:  # a sequence's layout: a smaller view in the corner
                images[c] = img = img[:h, :w]
            if img.shape[:2] != (h, w):
                raise ValueError(f"views: view {c} is {img.shape[1]}x{img.shape[0]}, camera {c} "
                                 f"is {w}x{h}")
    if masks is not None:
        if len(masks) != C:
            raise ValueError(f"masks: expected {C} masks (one per camera), got {len(masks)}")
        largest = (max(h for _, h in sizes), max(w for w, _ in sizes))
        masks = [m[:h, :w] if tuple(m.shape[:2]) == largest else m
                 for m, (w, h) in zip(masks, sizes)]
    if labels is not None and len(labels) != C:
        raise ValueError(f"labels: expected {C} labels, got {len(labels)}")
    est = _points("estimate", estimate)
    if len(parents) != est.shape[0]:
        raise ValueError(f"parents: expected {est.shape[0]} entries (one per joint), "
                         f"got {len(parents)}")
    tru = None if truth is None else _points("truth", truth)
    tparents = list(parents if truth_parents is None else truth_parents)
    if tru is not None and len(tparents) != tru.shape[0]:
        raise ValueError(f"truth_parents: expected {tru.shape[0]} entries, got {len(tparents)}")

    dt = rig.K.dtype
    est_pix, est_depth, _ = rig.project(est.to(dt))
    if tru is not None:
        tru_pix, tru_depth, _ = rig.project(tru.to(dt))
    outlines = None
    if capsules is not None:
        from torchmocap.viz.plots import capsule_outlines

        ep, radii = capsules
        outlines = [capsule_outlines(rig, c, ep, radii) for c in range(C)]

    det = None
    if detections is not None:
        det = _numpy(detections).astype(float)
        if det.ndim != 3 or det.shape[0] != C or det.shape[-1] != 3:
            raise ValueError(f"detections: expected shape ({C}, K, 3) (u, v, confidence per "
                             f"camera), got {det.shape}")
    legend = _legend(tru is not None, det is not None)
    rows, cols = grid_shape(C, columns)
    cell = (max(round(w * scale) for w, _ in sizes), max(round(h * scale) for _, h in sizes))
    # a grid narrower than its title and legend is widened (black on the right)
    width_px = max(cols * cell[0], _title_width(title, legend), int(min_width))
    grid = Image.new("RGB", (width_px, TITLE_HEIGHT + rows * cell[1]), (0, 0, 0))
    width = max(1, round(2 * min(scale, 1.5)))
    for c in range(C):
        panel = _panel(images[c], None if masks is None else masks[c], cell, scale)
        draw = ImageDraw.Draw(panel)
        if outlines is not None:
            for poly in outlines[c]:
                pts = [tuple(p) for p in _to_panel(poly, scale)]
                draw.line(pts + pts[:1], fill=_CAPSULE_COLOR, width=1)
        if tru is not None:
            _draw_skeleton(draw, _to_panel(_numpy(tru_pix[c]).astype(float), scale),
                           _numpy(tru_depth[c]) > 0, tparents, TRUTH_COLOR, width)
        _draw_skeleton(draw, _to_panel(_numpy(est_pix[c]).astype(float), scale),
                       _numpy(est_depth[c]) > 0, list(parents), ESTIMATE_COLOR, width)
        if det is not None:
            seen = (det[c, :, 2] > 0) & np.isfinite(det[c, :, :2]).all(-1)
            r = _JOINT_RADIUS + 1
            for u, v in _to_panel(det[c, seen, :2], scale):
                draw.ellipse([u - r, v - r, u + r, v + r], outline=DETECTION_COLOR, width=1)
        _draw_text(draw, (3, 2), labels[c] if labels is not None else f"cam {c + 1}")
        grid.paste(panel, panel_origin(c, cell, cols))
    grid.paste(_title_bar(grid.width, title, legend), (0, 0))
    return np.asarray(grid)


def _legend(truth: bool, detections: bool) -> list[tuple[str, tuple[int, int, int]]]:
    return ([("estimate", ESTIMATE_COLOR)] + ([("ground truth", TRUTH_COLOR)] if truth else [])
            + ([("detections", DETECTION_COLOR)] if detections else []))


def write_overlay_grid(path: str | Path, grid: np.ndarray) -> Path:
    """Save an overlay grid (``(H, W, 3)`` uint8) as an image, atomically."""
    from torchmocap.atomic import atomic_path

    arr = np.asarray(grid)
    if arr.ndim != 3 or arr.shape[-1] != 3 or arr.dtype != np.uint8:
        raise ValueError(f"grid: expected (H, W, 3) uint8, got {arr.shape} {arr.dtype}")
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(arr, "RGB").save(tmp, format=_format(path))
    return path


def _format(path: Path) -> str:
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"path: unknown image format {path.suffix!r} ({path})")
    return fmt


def track_overlay_frames(sequence: Any, skeleton: Any, theta: Tensor, frames: Sequence[int],
                         rig: Any = None, body: Any = None, scale: float = 1.0,
                         columns: int | None = None, labels: Sequence[str] | None = None
                         ) -> Iterator[tuple[int, np.ndarray]]:
    """Overlay grids of a track: ``(t, grid)`` for each frame index in ``frames``.

    Args:
        sequence: a :class:`~torchmocap.data.Sequence` (its images, or else its silhouettes, are
            the panels; its silhouettes tint the images; its ground truth, when present, is
            drawn in :data:`TRUTH_COLOR`, its 2D detections in :data:`DETECTION_COLOR`).
        skeleton: the tracking :class:`~torchmocap.skeleton.Skeleton`.
        theta: the track ``(T, D)``.
        rig: the cameras (default ``sequence.rig``).
        body: optional :class:`~torchmocap.body.CapsuleBody` whose outlines are drawn.
        scale, columns, labels: see :func:`render_overlay_grid`.

    Every grid has the same size (the widest title of ``frames`` sets the width).
    """
    rig = sequence.rig if rig is None else rig
    if rig is None:
        raise ValueError("rig: the sequence has no cameras to draw overlays on")
    T = int(theta.shape[0])
    frames = [int(t) for t in frames]
    for t in frames:
        if not 0 <= t < T:
            raise ValueError(f"frames: index {t} out of range for a {T}-frame track")
    gt = sequence.ground_truth
    truth_parents = None
    if gt is not None and gt.positions.shape[-2] != len(skeleton.parents):
        truth_parents = gt.build_skeleton().parents
    # one width for every grid of the track (the titles' widths differ)
    legend = _legend(gt is not None, getattr(sequence, "joints2d", None) is not None)
    min_width = max((_title_width(frame_title(t, sequence.fps), legend) for t in frames),
                    default=0)
    for t in frames:
        f = sequence.frame(int(t))
        with torch.no_grad():
            kin = skeleton(theta[int(t)].to(skeleton.offsets.dtype))
            caps = None if body is None else (body.endpoints(kin), body.radii)
        views = f.images if f.images is not None else f.silhouettes
        masks = f.silhouettes if f.images is not None else None
        yield int(t), render_overlay_grid(
            views, rig, kin, skeleton.parents, truth=f.positions, truth_parents=truth_parents,
            masks=masks, capsules=caps, detections=getattr(f, "joints2d", None),
            title=frame_title(t, sequence.fps), labels=labels, columns=columns, scale=scale,
            min_width=min_width)
