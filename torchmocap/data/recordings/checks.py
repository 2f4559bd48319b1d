"""Whether a recording's cameras, units and detections agree, checked before anything is tracked.

:func:`~torchmocap.data.recordings.load_recording` calls these at marked places:

* :func:`check_camera_choice` — before any file is read: a tracker needs two tracked views to
  triangulate the subject (``data.cameras``, ``evaluation.heldout_camera`` named).
* :func:`check_detections` — on the keypoint source's detections (full-size pixels): a view
  where nobody was detected (a legitimate input: reported, its keypoints are missing), every
  view empty (refused), keypoints outside the image by more than :data:`OUTSIDE_MARGIN` of its
  size (dropped and reported), every keypoint of a view in the top-left quarter of the image
  (detections of images of half the size), confidences above 1.
* :func:`view_consistency` + :func:`check_views` — each view's agreement with the others on
  the first frames: the largest set of views whose detections one triangulated body explains
  (each view within :data:`MAX_VIEW_RESIDUAL` of the subject's size in that view of the
  triangulation from the set's other views; two views within :data:`MAX_PAIR_RESIDUAL` of
  their own triangulation) is the reference, and every view is scored against it: a view
  outside it is refused (``data.checks=warn``: reported) with its likely cause — calibrations
  or detections exchanged between two views, a camera whose calibrated distance to the subject
  contradicts the subject's size in its images, a subject behind the camera. The subject's
  size (the largest distance between two triangulated keypoints) outside
  :data:`STATURE_RANGE_M` is refused the same way, naming ``data.unit``: the calibration's
  translations are in another unit (millimetres read as metres: a 1650 m subject).

The report (:func:`view_consistency`) is ``meta.view_consistency`` of the sequence and is
written into ``metrics.json``. ``docs/reliability.md`` lists what is refused and warned about
and the measured margins behind the limits.

Example:
    >>> check_camera_choice(["cam01", "cam02", "cam03"], heldout="cam01", min_views=2)
    >>> try:
    ...     check_camera_choice(["cam01", "cam02"], heldout="cam01", min_views=2)
    ... except ValueError as e:
    ...     print(str(e)[:59])
    data.cameras: the tracker sees 1 view (cam02; cam01 is held
"""

from __future__ import annotations

import copy
import itertools
import math
import warnings
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

__all__ = [
    "CHECK_MODES",
    "MAX_PAIR_RESIDUAL",
    "MAX_VIEW_RESIDUAL",
    "OUTSIDE_MARGIN",
    "STATURE_RANGE_M",
    "RecordingCheckError",
    "check_camera_choice",
    "check_detections",
    "check_mode",
    "check_views",
    "mask_consistency",
    "view_consistency",
]

#: ``data.checks``: ``refuse`` (inconsistent views and implausible units are errors) or
#: ``warn`` (they are reported and the run goes on)
CHECK_MODES = ("refuse", "warn")
#: a view's median residual against the triangulation from the other views of a consistent
#: set, relative to the subject's size in that view (intact pose2sim_balancing: at most 0.062
#: over every window of 10 frames and every set of three or four views; exchanged
#: calibrations: at least 0.26 in every set holding an exchanged view)
MAX_VIEW_RESIDUAL = 0.12
#: the same for two views, each against their own two-view triangulation (intact: at most
#: 0.021; exchanged calibrations: at least 0.062)
MAX_PAIR_RESIDUAL = 0.04
#: the subject's size (metres: the largest distance between two of its triangulated
#: keypoints, median over the first frames; a person of 1.5-2 m measures 1.4-2.4 m)
STATURE_RANGE_M = (0.5, 3.0)
#: keypoints farther outside the image than this fraction of its width / height are dropped
OUTSIDE_MARGIN = 0.5
#: detections above this confidence are compared in the consistency check
MIN_CONFIDENCE = 0.3
#: observations (frame, keypoint) a view needs to be scored
MIN_POINTS = 10
#: a camera whose calibrated distance to the subject differs from the one its images show
#: (focal length x subject size / size in the image) by more than this factor is named
DISTANCE_FACTOR = 2.0
#: the subject's size (pixels of the scaled images) below which masks and silhouette scores
#: are not worth computing: a warning names ``data.scale``
MIN_SUBJECT_PX = 48
#: views up to which every subset is tried (more: views dropped one at a time, worst first)
EXHAUSTIVE_VIEWS = 8
#: masks-only recordings: the fraction of a view's foreground that the visual hull of the
#: other views covers (intact bodytrack frame: at least 0.83 in every set of three or four
#: views; two cameras' calibrations exchanged: every set holding one has a view at 0.59 or
#: less; a camera 1 km away: 0). Masks say less than keypoints: the margin is 1.2 x each side
MIN_MASK_AGREEMENT = 0.7
#: the voxel of those hulls (metres; coarse: a check, not the subject's start)
HULL_VOXEL_M = 0.08
#: the room the hulls are carved in (metres, the subject near the origin, z up)
HULL_BOUNDS = [[-3.0, 3.0], [-3.0, 3.0], [-0.1, 2.3]]
#: metres per unit of the calibration formats' default units, by file suffix
_DEFAULT_UNITS = {".toml": 1.0, ".yml": 1.0, ".yaml": 1.0, ".json": 1.0, ".cal": 0.001}
_UNIT_NAMES = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "in": 0.0254}


class RecordingCheckError(ValueError):
    """A recording's cameras, units or detections contradict each other (the views named)."""


def check_mode(mode: str) -> str:
    """The checked ``data.checks`` setting."""
    if mode not in CHECK_MODES:
        raise ValueError(f"data.checks: expected one of {list(CHECK_MODES)}, got {mode!r}")
    return mode


# ---------------------------------------------------------------- cameras (before loading)

def check_camera_choice(names: Sequence[str], heldout: str | None, min_views: int) -> None:
    """Refuse a choice of cameras that leaves fewer than ``min_views`` tracked views (the
    subject is triangulated from them), before anything is loaded.

    Args:
        names: the loaded cameras (``data.cameras``).
        heldout: the held-out one's name, or None.
        min_views: tracked views needed (0 or 1: no requirement).
    """
    tracked = [n for n in names if n != heldout]
    if len(tracked) >= min_views:
        return
    held = f"; {heldout} is held out (evaluation.heldout_camera)" if heldout else ""
    raise ValueError(f"data.cameras: the tracker sees {len(tracked)} view"
                     f"{'s' if len(tracked) != 1 else ''} ({', '.join(tracked) or 'none'}"
                     f"{held}); the subject is triangulated from at least {min_views} views: "
                     f"choose more cameras (data.cameras: {list(names)})"
                     + (" or hold none out" if heldout else ""))


# ---------------------------------------------------------------- detections

def check_detections(people: list[list[Tensor]], num_keypoints: int, names: Sequence[str],
                     sizes: Sequence[tuple[int, int]], folders: Sequence[str] | None = None,
                     frames: Sequence[int] | None = None) -> list[list[Tensor]]:
    """The detections with implausible keypoints dropped; what is wrong is reported by name.

    Args:
        people: ``people[t][c]`` ``(P, K, 3)`` (u, v, confidence) in the full-size images'
            pixels (a view with nobody may be ``(0, 0, 3)``: reshaped to ``(0, K, 3)``).
        num_keypoints: ``K``.
        names: the ``C`` cameras; sizes: their images' ``(width, height)``.
        folders: where each camera's detections were read (messages).
        frames: the loaded frame indices (messages).

    Returns:
        ``people`` with every tensor ``(P, K, 3)`` float64 and the keypoints farther than
        :data:`OUTSIDE_MARGIN` outside the image zeroed (missed).

    Warns:
        UserWarning: a view without any detection, keypoints dropped outside the image, every
            keypoint of a view in the top-left quarter of the image, confidences above 1.

    Raises:
        RecordingCheckError: nobody detected in any view of any loaded frame.
    """
    K = int(num_keypoints)
    out = [[x.double().clone() if x.shape[0] else torch.zeros(0, K, 3, dtype=torch.float64)
            for x in frame] for frame in people]
    where = (lambda c: f" ({folders[c]})") if folders else (lambda c: "")
    span = "" if not frames else f" {frames[0]}..{frames[-1]}"
    empty = []
    for c, name in enumerate(names):
        W, H = sizes[c]
        xs = [frame[c] for frame in out]
        seen = [x[..., 2] > 0 for x in xs]
        n_seen = sum(int(s.sum()) for s in seen)
        if n_seen == 0:
            empty.append(c)
            continue
        conf = max(float(x[..., 2].max()) for x in xs if x.shape[0])
        if conf > 1.0:
            warnings.warn(f"{name}: keypoint confidences up to {conf:.3g}{where(c)}: above 1, "
                          "not probabilities; data.keypoints.min_confidence and "
                          "evaluation.min_confidence assume confidences in [0, 1]",
                          stacklevel=3)
        mu, mv = OUTSIDE_MARGIN * W, OUTSIDE_MARGIN * H
        dropped = 0
        for x, s in zip(xs, seen):
            if not x.shape[0]:
                continue
            u, v = x[..., 0], x[..., 1]
            far = s & ((u < -mu) | (u > W + mu) | (v < -mv) | (v > H + mv))
            if bool(far.any()):
                dropped += int(far.sum())
                x[far] = 0.0
        if dropped:
            every = dropped == n_seen
            warnings.warn(f"{name}: {'all' if every else dropped} of its {n_seen} detected "
                          f"keypoints{where(c)} lie farther than {OUTSIDE_MARGIN:.0%} of the "
                          f"image outside its {W}x{H} pixels; dropped (detections of another "
                          "camera or resolution, or shifted?)", stacklevel=3)
            if every:
                empty.append(c)
                continue
        kept = torch.cat([x[..., :2][x[..., 2] > 0] for x in xs if x.shape[0]])
        if kept.shape[0] >= MIN_POINTS and bool((kept[:, 0] <= W / 2).all()) and \
                bool((kept[:, 1] <= H / 2).all()):
            warnings.warn(f"{name}: every keypoint{where(c)} lies in the top-left quarter of "
                          f"its {W}x{H} images (u <= {W / 2:g}, v <= {H / 2:g}): detections "
                          "made on images of half the size? (their pixels must be those of "
                          "the full-size frames)", stacklevel=3)
    if len(empty) == len(names):
        raise RecordingCheckError(
            f"data.keypoints: nobody detected in any loaded frame{span} of any camera "
            f"({', '.join(names)}): there is no subject to fit; choose other frames "
            "(data.start, data.stop) or load without keypoints (data.keypoints.source=none)")
    for c in empty:
        if any(bool((frame[c][..., 2] > 0).any()) for frame in people):
            continue  # all dropped: said above
        warnings.warn(f"{names[c]}: nobody detected in any loaded frame{span}{where(c)}: the "
                      "view has no keypoints (its images and masks are still used)",
                      stacklevel=3)
    return out


# ---------------------------------------------------------------- views' agreement

def _subject_size(joints: Tensor, seen: Tensor) -> Tensor:
    """``(C,)`` median over frames of the larger side of the seen keypoints' box (NaN: none).

    ``joints (T, C, K, 3)``, ``seen (T, C, K)``."""
    big = torch.tensor(float("inf"), dtype=joints.dtype)
    lo = torch.where(seen[..., None], joints[..., :2], big).amin(-2)
    hi = torch.where(seen[..., None], joints[..., :2], -big).amax(-2)
    side = (hi - lo).amax(-1)  # (T, C)
    side = torch.where(seen.sum(-1) >= 4, side, torch.full_like(side, float("nan")))
    return side.nanmedian(0).values


class _Views:
    """Triangulations and residuals of the first frames' detections (``rig``'s pixels)."""

    def __init__(self, joints: Tensor, rig) -> None:
        from torchmocap.cameras import triangulate_dlt

        self._dlt = triangulate_dlt
        self.j = joints
        self.rig = rig
        self.seen = joints[..., 2] > MIN_CONFIDENCE
        self.w = torch.where(self.seen, joints[..., 2], torch.zeros_like(joints[..., 2]))
        self.size = _subject_size(joints, self.seen)
        self._points: dict[tuple[int, ...], Tensor] = {}
        self._res: dict[tuple[tuple[int, ...], int, int], tuple[float, int, bool]] = {}

    def points(self, views: Sequence[int]) -> Tensor:
        """``(T, K, 3)`` the keypoints triangulated from ``views`` (NaN: seen by < 2)."""
        key = tuple(sorted(views))
        if key not in self._points:
            idx = list(key)
            self._points[key] = self._dlt(self.j[:, idx, :, :2], self.w[:, idx],
                                          self.rig.subset(idx))
        return self._points[key]

    def residual(self, views: Sequence[int], c: int, camera: int | None = None
                 ) -> tuple[float, int, bool]:
        """View ``c``'s detections against the points of ``views`` projected by camera
        ``camera`` (default ``c``): the median distance (px, inf when the projections are
        behind the camera), the observations compared, and whether most were behind it."""
        cam = c if camera is None else camera
        key = (tuple(sorted(views)), c, cam)
        if key not in self._res:
            X = self.points(views)
            have = torch.isfinite(X).all(-1)
            pix, depth, _ = self.rig.subset([cam]).project(
                torch.where(have[..., None], X, torch.zeros_like(X)))
            pix, depth = pix[:, 0], depth[:, 0]
            ok = have & self.seen[:, c]
            n = int(ok.sum())
            if n == 0:
                self._res[key] = (math.nan, 0, False)
            else:
                behind = depth[ok] <= 0
                d = (pix - self.j[:, c, :, :2]).norm(dim=-1)[ok]
                d = torch.where(behind, torch.full_like(d, math.inf), d)
                self._res[key] = (float(d.median()), n, bool(behind.double().mean() > 0.5))
        return self._res[key]

    def relative(self, views: Sequence[int], c: int) -> float:
        """The residual relative to the subject's size in view ``c`` (NaN: not measured)."""
        r, n, _ = self.residual(views, c)
        if n < MIN_POINTS or not math.isfinite(float(self.size[c])):
            return math.nan
        return r / float(self.size[c])

    def set_error(self, views: Sequence[int]) -> float:
        """The largest relative residual of ``views``: each against the others' triangulation
        (three views or more), or against their own (two); inf when one is not measured,
        and the limit's multiple (so that sets of two and of more compare)."""
        views = list(views)
        if len(views) == 2:
            errs = [self.relative(views, c) / MAX_PAIR_RESIDUAL for c in views]
        else:
            errs = [self.relative([v for v in views if v != c], c) / MAX_VIEW_RESIDUAL
                    for c in views]
        return max(math.inf if math.isnan(e) else e for e in errs)


def _consistent_set(v: _Views, measured: list[int]) -> list[int]:
    """The largest set of views within the limits (ties: the smallest error), else []."""
    if len(measured) < 2:
        return []
    if len(measured) <= EXHAUSTIVE_VIEWS:
        for n in range(len(measured), 1, -1):
            scored = [(v.set_error(S), S) for S in itertools.combinations(measured, n)]
            good = [(e, S) for e, S in scored if e <= 1.0]
            if good:
                return list(min(good)[1])
        return []
    views = list(measured)
    while len(views) >= 2:
        if v.set_error(views) <= 1.0:
            return views
        if len(views) == 2:
            break
        worst = max(views, key=lambda c: (lambda e: math.inf if math.isnan(e) else e)(
            v.relative([o for o in views if o != c], c)))
        views.remove(worst)
    return []


def view_consistency(joints: Tensor, rig, names: Sequence[str], pixel_scale: float = 1.0,
                     frames: Sequence[int] | None = None, heldout: str | None = None
                     ) -> dict[str, Any]:
    """Each view's agreement with the others on the first frames (module docstring).

    Args:
        joints: ``(T0, C, K, 3)`` the chosen detections (u, v, confidence; 0 = missed) in
            ``rig``'s pixels.
        rig: the :class:`~torchmocap.cameras.CameraRig` of the ``C`` views (its images at
            ``pixel_scale`` of the full-size ones).
        names: the views' names.
        pixel_scale: the images' scale (residuals are reported in full-size pixels).
        frames: the frames' indices (reported).
        heldout: the held-out camera's name (reported).

    Returns:
        a JSON-ready report: ``frames``, ``limits`` (the relative limits and what they are
        relative to), ``consistent_views`` (the reference set), ``stature_m`` (the subject's
        size triangulated from it, None without one), and per view ``status`` (``consistent``,
        ``inconsistent``, ``no detections``, ``too few keypoints``, ``no other view``: the only
        view with detections), ``residual_px`` (median,
        full-size pixels; None: not measured), ``relative`` (to ``subject_px``, the subject's
        size in the view), ``points`` (observations compared), ``against`` (the views it was
        triangulated from), ``distance_m`` (camera to the subject), ``apparent_distance_m``
        (what its images show: focal length x subject size / size in pixels) and, for an
        inconsistent view, ``cause``.
    """
    j = joints.double()
    rig = copy.deepcopy(rig).double()
    T, C = j.shape[:2]
    v = _Views(j, rig)
    names = list(names)
    counts = v.seen.sum((0, 2)).tolist()
    measured = [c for c in range(C) if counts[c] >= MIN_POINTS and
                math.isfinite(float(v.size[c]))]
    ref = _consistent_set(v, measured)
    report: dict[str, Any] = {
        "method": "keypoints",
        "frames": list(frames) if frames is not None else list(range(T)),
        "heldout_camera": heldout,
        "limits": {"view": MAX_VIEW_RESIDUAL, "pair": MAX_PAIR_RESIDUAL,
                   "stature_m": list(STATURE_RANGE_M),
                   "relative_to": "the subject's size in the view (the larger side of its "
                                  "keypoints' box, median over the frames)"},
        "min_confidence": MIN_CONFIDENCE, "image_scale": pixel_scale,
        "consistent_views": [names[c] for c in ref],
        "stature_m": None, "views": {},
    }
    centre = None
    if ref:
        X = v.points(ref)
        ext = []
        for t in range(T):
            P = X[t][torch.isfinite(X[t]).all(-1)]
            if P.shape[0] >= 4:
                ext.append(float(torch.cdist(P, P).max()))
        if ext:
            report["stature_m"] = round(float(torch.tensor(ext).median()), 4)
        finite = torch.isfinite(X).all(-1)
        if bool(finite.any()):
            centre = X[finite].mean(0)
    centres = rig.camera_centers()
    focal = rig.K[:, [0, 1], [0, 1]].mean(-1)
    for c, name in enumerate(names):
        entry: dict[str, Any] = {"status": None, "residual_px": None, "relative": None,
                                 "points": int(counts[c]), "subject_px": None, "against": []}
        size = float(v.size[c])
        if math.isfinite(size):
            entry["subject_px"] = round(size / pixel_scale, 1)
        if counts[c] == 0:
            entry["status"] = "no detections"
        elif c not in measured:
            entry["status"] = "too few keypoints"
        if centre is not None:
            entry["distance_m"] = round(float((centres[c] - centre).norm()), 4)
            if report["stature_m"] and math.isfinite(size) and size > 0:
                entry["apparent_distance_m"] = round(
                    float(focal[c]) * report["stature_m"] / size, 4)
        if c in measured and len(ref) >= 2:
            against = [o for o in ref if o != c] if len(ref) >= 3 or c not in ref else ref
            r, n, _ = v.residual(against, c)
            entry["against"] = [names[o] for o in against]
            entry["points"] = n
            if n:
                entry["residual_px"] = round(r / pixel_scale, 2) if math.isfinite(r) else None
                entry["relative"] = round(r / size, 4) if math.isfinite(r) else None
            entry["status"] = "consistent" if c in ref else "inconsistent"
        elif c in measured:
            entry["status"] = "inconsistent" if len(measured) >= 2 else "no other view"
        report["views"][name] = entry
    for c in measured:
        if c not in ref and len(measured) >= 2:
            report["views"][names[c]]["cause"] = _cause(v, c, ref, measured, names,
                                                         report["views"])
    return report


def _cause(v: _Views, c: int, ref: list[int], measured: list[int], names: list[str],
           entries: dict) -> str:
    """The likely reason view ``c`` disagrees with the views ``ref``."""
    name = names[c]
    if len(ref) < 2:
        return ("no two views agree: calibrations of other cameras or another rig, or "
                "detections of other views or frames")
    _, _, behind = v.residual(ref, c)
    if behind:
        return (f"the subject triangulated from {', '.join(names[o] for o in ref)} is behind "
                f"{name}: its calibration (rotation) is wrong or of another camera")
    for o in measured:
        if o == c or o in ref:
            continue
        r, n, _ = v.residual(ref, c, camera=o)
        back, m, _ = v.residual(ref, o, camera=c)
        size_c, size_o = float(v.size[c]), float(v.size[o])
        if n >= MIN_POINTS and m >= MIN_POINTS and r / size_c <= MAX_VIEW_RESIDUAL and \
                back / size_o <= MAX_VIEW_RESIDUAL:
            a, b = sorted([name, names[o]])
            return (f"{a}'s detections fit {b}'s calibration and {b}'s fit {a}'s: their "
                    f"calibrations or their detections are exchanged")
    e = entries[name]
    d, seen_d = e.get("distance_m"), e.get("apparent_distance_m")
    if d and seen_d and not (1 / DISTANCE_FACTOR <= d / seen_d <= DISTANCE_FACTOR):
        return (f"its calibration: the camera is {d:.4g} m from the subject, while the "
                f"subject's size in its images puts it about {seen_d:.2g} m away")
    return ("its calibration (of another camera, or moved) or its detections (of another view "
            "or other frames)")


def _hull_points(rig, masks: Tensor, views: Sequence[int], voxel: float) -> Tensor:
    """``(M, 3)`` voxel centres of the largest component of the hull of ``views``' masks."""
    from torchmocap.cameras import visual_hull

    idx = list(views)
    hull = visual_hull(rig.subset(idx), masks[idx], HULL_BOUNDS, voxel)
    return hull.largest_component().centers().to(torch.float64)


def _mask_agreement(rig, masks: Tensor, points: Tensor, c: int) -> tuple[float, float]:
    """How view ``c``'s mask and the ``points`` (a hull of other views) agree: the fraction of
    the points projecting onto its foreground (precision) and of its foreground within a few
    pixels of a projected point (coverage)."""
    import torch.nn.functional as F

    W, H = (int(v) for v in rig.image_size[c].tolist())
    mask = masks[c, :H, :W].bool()
    if points.shape[0] == 0:
        return 0.0, 0.0
    pix, _, vis = rig.subset([c]).project(points)
    uv = pix[0].round().long()
    inside = vis[0] & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    on = torch.zeros(points.shape[0], dtype=torch.bool)
    on[inside] = mask[uv[inside, 1], uv[inside, 0]]
    hit = torch.zeros(H, W)
    hit[uv[inside, 1], uv[inside, 0]] = 1.0
    # a voxel's footprint: about its size in pixels at the subject's depth
    depth = float(rig.subset([c]).project(points.mean(0, keepdim=True))[1][0, 0])
    r = max(1, round(float(rig.K[c, 0, 0]) * HULL_VOXEL_M / max(depth, 1e-6) / 2))
    hit = F.max_pool2d(hit[None, None], 2 * r + 1, 1, r)[0, 0] > 0
    coverage = float((hit & mask).sum()) / max(1, int(mask.sum()))
    return float(on.double().mean()), coverage


def mask_consistency(masks: Tensor, rig, names: Sequence[str], heldout: str | None = None
                     ) -> dict[str, Any]:
    """Each view's agreement with the others in a masks-only recording: its mask against the
    visual hull of the other views' masks (:data:`HULL_VOXEL_M` voxels), projected into it.
    A hull contains the body, so with consistent calibrations and masks it covers the view's
    foreground: the fraction covered is the view's ``agreement`` (the fraction of the hull on
    the foreground, ``precision``, says how tight the hull is, not whether it is right: two
    views facing each other carve a loose one). The reference is the largest set of three views
    or more whose every view agrees at :data:`MIN_MASK_AGREEMENT` or more with the others of
    the set; the report is that of :func:`view_consistency` (``method: masks``).

    Args:
        masks: ``(C, H, W)`` one frame's masks; rig: the ``C`` views; names: their names.
        heldout: the held-out camera's name (reported).
    """
    rig = copy.deepcopy(rig).double()
    C = rig.num_cameras
    names = list(names)
    fg = masks.flatten(1).float().mean(1).tolist()
    measured = [c for c in range(C) if 0 < fg[c] <= 0.5]
    hulls: dict[tuple[int, ...], Tensor] = {}
    agree: dict[tuple[tuple[int, ...], int], tuple[float, float]] = {}

    def points(views):
        key = tuple(sorted(views))
        if key not in hulls:
            hulls[key] = _hull_points(rig, masks, key, HULL_VOXEL_M)
        return hulls[key]

    def score(views, c):
        key = (tuple(sorted(views)), c)
        if key not in agree:
            agree[key] = _mask_agreement(rig, masks, points(views), c)
        return agree[key]

    def set_error(views):
        return max(MIN_MASK_AGREEMENT / max(score([o for o in views if o != c], c)[1], 1e-9)
                   for c in views)

    ref: list[int] = []
    if len(measured) >= 3:
        for n in range(len(measured), 2, -1):
            good = [(set_error(S), S) for S in itertools.combinations(measured, n)]
            good = [(e, S) for e, S in good if e <= 1.0]
            if good:
                ref = list(min(good)[1])
                break
            if len(measured) > EXHAUSTIVE_VIEWS:
                break
    report: dict[str, Any] = {
        "method": "masks", "heldout_camera": heldout,
        "limits": {"agreement": MIN_MASK_AGREEMENT, "voxel_m": HULL_VOXEL_M,
                   "relative_to": "the visual hull of the other views' masks, projected"},
        "consistent_views": [names[c] for c in ref], "stature_m": None, "views": {}}
    if ref:
        pts = points(ref)
        if pts.shape[0]:
            report["stature_m"] = round(float(pts[:, 2].max() - pts[:, 2].min()), 4)
    for c, name in enumerate(names):
        e: dict[str, Any] = {"status": None, "agreement": None, "precision": None,
                             "coverage": None, "foreground": round(fg[c], 4), "against": []}
        if fg[c] == 0:
            e["status"] = "no detections"
        elif fg[c] > 0.5:
            e["status"] = "mostly foreground"
        elif len(measured) < 3:
            e["status"] = "too few views"
        else:
            against = [o for o in (ref or measured) if o != c]
            prec, cov = score(against, c)
            e.update(agreement=round(cov, 4), precision=round(prec, 4),
                     coverage=round(cov, 4), against=[names[o] for o in against],
                     status="consistent" if c in ref else "inconsistent")
            if c not in ref:
                e["cause"] = ("its calibration (of another camera, or moved) or its mask (of "
                              "another view or frame)" if ref else
                              "no three views agree: calibrations of other cameras or another "
                              "rig, or masks of other views")
        report["views"][name] = e
    return report


def _unit_hint(stature: float, unit, calibration) -> str:
    """What ``data.unit`` makes a ``stature``-metre subject a person's size."""
    from pathlib import Path

    if unit is None:
        path = Path(str(calibration)) if calibration else None
        per_unit = 1.0
        if path is not None:
            per_unit = (0.001 if any(path.glob("*.cal")) else 1.0) if path.is_dir() else \
                _DEFAULT_UNITS.get(path.suffix.lower(), 1.0)
        read_as = next(k for k, x in _UNIT_NAMES.items() if x == per_unit)
        how = f"as {read_as}, the format's default (data.unit unset)"
    else:
        per_unit = _UNIT_NAMES[unit] if isinstance(unit, str) and unit in _UNIT_NAMES \
            else float(unit)
        how = f"with data.unit={unit}"
    want = per_unit * 1.7 / stature
    best = min(_UNIT_NAMES, key=lambda k: abs(math.log(_UNIT_NAMES[k] / want)))
    return (f"the calibration's translations were read {how}; if they are in {best}, set "
            f"data.unit={best}")


def check_views(report: dict[str, Any], mode: str = "refuse", unit=None,
                calibration=None) -> None:
    """Refuse (``mode="refuse"``) or report (``"warn"``) what :func:`view_consistency` found:
    views outside the consistent set (named, with their residuals and likely cause) and a
    subject whose size is not a person's (naming ``data.unit``).

    Raises:
        RecordingCheckError: in ``refuse`` mode, naming the views or ``data.unit`` and how
            to go on (``data.cameras``, ``data.checks=warn``).
    """
    check_mode(mode)
    problems = []
    views = report["views"]
    ref = report["consistent_views"]
    lo, hi = STATURE_RANGE_M
    s = report.get("stature_m")
    if s is not None and not lo <= s <= hi:
        d = [e["distance_m"] for e in views.values() if e.get("distance_m") is not None]
        far = f" and the cameras {min(d):.4g}-{max(d):.4g} m from it" if d else ""
        problems.append(f"data.unit: the subject triangulated from the first frames measures "
                        f"{s:.4g} m{far}, a person {lo}-{hi} m: "
                        + _unit_hint(s, unit, calibration))
    bad = [n for n, e in views.items() if e["status"] == "inconsistent"]
    if bad and report.get("method") == "masks":
        held = report.get("heldout_camera")
        figures = ", ".join(f"{n}{' (held out)' if n == held else ''} "
                            f"{100 * views[n]['agreement']:.0f} %" for n in bad)
        limit = f"{100 * MIN_MASK_AGREEMENT:.0f} %"
        if ref:
            worst = min(views[n]["agreement"] for n in ref)
            head = (f"data.cameras: the masks of {', '.join(bad)} disagree with the other "
                    f"views': {figures} agreement with the visual hull of {', '.join(ref)} "
                    f"(which agree at {100 * worst:.0f} % or more; the limit is {limit})")
        else:
            head = (f"data.cameras: no three views' masks agree ({figures} agreement with the "
                    f"hull of the others; the limit is {limit})")
        empty = [n for n in views if views[n]["status"] == "no detections"]
        fg = ", ".join(f"{n} {100 * e['foreground']:.1f} %" for n, e in views.items())
        head += (f"; the mask{'s' if len(empty) > 1 else ''} of {', '.join(empty)} "
                 f"{'are' if len(empty) > 1 else 'is'} empty" if empty else "") + \
            f" (foreground read: {fg})"
        keep = [n for n in views if n not in bad and n not in empty]
        cause = views[bad[0]].get("cause")
        problems.append(head + (f"; {cause}" if cause else "") + (
            f"; fix them, track without them (data.cameras={_list(keep)})" if len(keep) >= 3
            else "; fix them"))
    elif bad:
        held = report.get("heldout_camera")
        figures = ", ".join(
            f"{n}{' (held out)' if n == held else ''} "
            + (f"{views[n]['residual_px']:.0f} px = {100 * views[n]['relative']:.0f} %"
               if views[n]["residual_px"] is not None else "not measurable")
            for n in bad)
        if ref:
            worst = max((views[n]["relative"] or 0.0) for n in ref)
            head = (f"data.cameras: {', '.join(bad)} disagree{'s' if len(bad) == 1 else ''} "
                    f"with the other views: {figures} of the subject's size from the "
                    f"triangulation of {', '.join(ref)} (which agree within "
                    f"{100 * worst:.0f} %; the limit is {100 * MAX_VIEW_RESIDUAL:.0f} %)")
        else:
            head = (f"data.cameras: no two views agree ({', '.join(bad)} pairwise more than "
                    f"{100 * MAX_PAIR_RESIDUAL:.0f} % of the subject's size apart)")
        causes = []
        for n in bad:
            cause = views[n].get("cause")
            if cause and cause not in causes:
                causes.append(cause)
        keep = [n for n in views if n not in bad and views[n]["status"] != "no detections"]
        hint = (f"; fix them, track without them (data.cameras={_list(keep)})"
                if len(keep) >= 2 else "; fix them")
        problems.append(head + ("; " + "; ".join(f"{c}" for c in causes) if causes else "")
                        + hint)
    sizes = [e["subject_px"] for e in views.values() if e.get("subject_px")]
    scale = report.get("image_scale") or 1.0
    if sizes and max(sizes) * scale < MIN_SUBJECT_PX:
        warnings.warn(f"data.scale={scale:g}: the subject is at most {max(sizes) * scale:.0f} "
                      f"px tall in the scaled images; masks and silhouette scores need about "
                      f"{MIN_SUBJECT_PX} px (data.scale >= {MIN_SUBJECT_PX / max(sizes):.2g})",
                      stacklevel=3)
    if not problems:
        return
    if mode == "refuse":
        raise RecordingCheckError(" | ".join(problems) + " (or set data.checks=warn to go on)")
    for p in problems:
        warnings.warn(p, stacklevel=3)


def _list(names: Sequence[str]) -> str:
    return "[" + ",".join(names) + "]"
