"""The subject and the first pose of a real recording, from its own observations.

* With 2D keypoints (:func:`keypoint_start`): the first frames' detections are triangulated
  (confidence-weighted DLT; per keypoint, a view that disagrees with the others by more than
  ``max_error_px`` is dropped: :func:`~torchmocap.cameras.triangulate_robust`) and the
  skeleton is fitted to them (:func:`~torchmocap.ik.fit_keypoint_subject`: body scale, bone
  lengths, the keypoints' offsets scaled with the body, and the poses of those frames from
  several starts — no standing start is assumed). The sequence then carries the subject's
  skeleton, the fitted pose of frame 0 and the fitted keypoint map.
* With masks only (:func:`hull_start`): the visual hull of the first frame's masks; a human31
  scaled to the hull's height, standing at its centre, one candidate per heading (what a
  tracker with ``refine_first_frame`` starts from, e.g. ``tracker=real_frame``).

Both return ``meta`` entries of the :class:`~torchmocap.data.Sequence`:
``subject_skeleton`` (:meth:`~torchmocap.skeleton.Skeleton.to_dict`), ``initial_poses``
(``(K, D)`` nested lists, the best first), ``skeleton_scale``, and ``keypoint_map``
(:meth:`~torchmocap.skeleton.KeypointMap.to_dict`) / ``subject_fit`` or ``hull_centre`` /
``hull_top_m``.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from torchmocap.data.settings import with_defaults

__all__ = ["MAX_FOREGROUND", "SCALE_RANGE", "SUBJECT_DEFAULTS", "hull_start", "keypoint_start",
           "subject_settings"]

#: the subject's height (human31 at 1.75 m) scaled to the hull within this range
SCALE_RANGE = (0.85, 1.15)
#: a view whose mask has more foreground than this is reported (inverted or all foreground)
MAX_FOREGROUND = 0.5
#: human31's standing height (metres) that the hull's top is compared with
_HEIGHT = 1.75
#: the ``data.subject`` settings and their defaults
SUBJECT_DEFAULTS = {"frames": 10, "max_error_px": 30.0, "keypoint_map": None}
#: keypoints a frame needs triangulated to be fitted (a rigid placement needs 3)
_MIN_POINTS = 4


def subject_settings(subject: Mapping[str, Any] | None) -> dict[str, Any]:
    """The checked ``data.subject`` settings (defaults filled in).

    Raises:
        ValueError: an unknown key or a bad value, naming ``data.subject.<key>``.
    """
    s = with_defaults("data.subject", subject, SUBJECT_DEFAULTS)
    n = s["frames"]
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"data.subject.frames: expected an int >= 1, got {n!r}")
    e = s["max_error_px"]
    if isinstance(e, bool) or not isinstance(e, (int, float)) or not (math.isfinite(e)
                                                                     and e > 0):
        raise ValueError(f"data.subject.max_error_px: expected a number of pixels > 0, got "
                         f"{e!r}")
    if s["keypoint_map"] is not None and not isinstance(s["keypoint_map"], str):
        raise ValueError(f"data.subject.keypoint_map: expected a format name or a map YAML "
                         f"path, got {s['keypoint_map']!r}")
    return s


def keypoint_start(joints2d: torch.Tensor, keypoint_names: Sequence[str], keypoint_format: str,
                   rig, settings: Mapping[str, Any] | None = None,
                   pixel_scale: float = 1.0) -> dict[str, Any]:
    """Subject skeleton, first pose and keypoint map fitted to the first frames' keypoints.

    Args:
        joints2d: ``(T, C, K, 3)`` detections (u, v, confidence; 0 = missed) in ``rig``'s
            pixels.
        keypoint_names: the ``K`` column names.
        keypoint_format: the detections' format (its built-in map unless
            ``settings["keypoint_map"]`` names another).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the ``C >= 2`` views.
        settings: ``frames`` (the first frames fitted), ``max_error_px`` (a view's largest
            reprojection error per keypoint, in pixels of the full-size images),
            ``keypoint_map`` (:func:`subject_settings`).
        pixel_scale: the images' scale (``rig``'s pixels per full-size pixel).

    Returns:
        ``meta`` entries (module docstring); ``subject_fit`` reports the frames used, the views
        dropped by the triangulation, the fit's median keypoint residual (m) and reprojection
        error (full-size pixels), the stature and the bone lengths.

    Raises:
        ValueError: fewer than two views, or frame 0 with fewer than 4 keypoints triangulated
            (named).
    """
    from torchmocap.cameras import triangulate_robust
    from torchmocap.ik import fit_keypoint_subject
    from torchmocap.skeleton import keypoint_positions

    s = subject_settings(settings)
    C = rig.num_cameras
    if C < 2:
        raise ValueError(f"data.subject: fitting the subject to keypoints needs at least two "
                         f"views to triangulate, got {C} ({rig.names})")
    T0 = min(int(s["frames"]), joints2d.shape[0])
    det = joints2d[:T0].double()
    rig64 = copy.deepcopy(rig).double()  # Module.double() converts in place
    X, used = triangulate_robust(det[..., :2], det[..., 2], rig64,
                                 float(s["max_error_px"]) * pixel_scale)
    ok = torch.isfinite(X).all(-1)  # (T0, K)
    if int(ok[0].sum()) < _MIN_POINTS:
        raise ValueError(f"data.subject: frame 0 has {int(ok[0].sum())} keypoints seen by two "
                         f"views (the subject fit needs {_MIN_POINTS}); start at another frame "
                         "(data.start)")
    frames = [t for t in range(T0) if int(ok[t].sum()) >= _MIN_POINTS]
    X, used, det = X[frames], used[frames], det[frames]
    fit = fit_keypoint_subject(X, used.mean(1), s["keypoint_map"] or keypoint_format,
                               keypoint_names=list(keypoint_names))
    sk = fit.skeleton
    kin = sk(fit.theta)
    cols = fit.keypoint_map.columns(list(keypoint_names))
    model = keypoint_positions(kin.positions, kin.rotations, fit.keypoint_map)
    seen = det[:, :, cols, 2] > 0
    err = (rig64.project(model)[0] - det[:, :, cols, :2]).norm(dim=-1)[seen] / pixel_scale
    rest = sk(sk.zero_pose((), dtype=torch.float64))
    feet = keypoint_positions(rest.positions, rest.rotations, fit.keypoint_map)[:, 2].min()
    head = rest.positions[sk.joint_index("head_top"), 2] if "head_top" in sk.joint_names \
        else rest.positions[:, 2].max()
    report = {
        "frames": frames, "views": list(rig.names),
        "dropped_views": int(((det[..., 2] > 0) & (used == 0)).sum()),
        "max_error_px": float(s["max_error_px"]),
        "residual_m": float(fit.residual.nanmedian()),
        "reprojection_px": float(err.median()) if err.numel() else float("nan"),
        "stature_m": float(head - feet), "scale": fit.scale,
        "lengths": {k: round(v, 4) for k, v in fit.lengths.items()},
    }
    return {"subject_skeleton": sk.to_dict(), "initial_poses": fit.theta[:1].tolist(),
            "keypoint_map": fit.keypoint_map.to_dict(), "skeleton_scale": fit.scale,
            "subject_fit": report}


def hull_start(rig, masks: torch.Tensor, headings: int = 12, voxel: float = 0.04,
               labels: Sequence[str] | None = None) -> dict[str, Any]:
    """A standing subject at the visual hull of one frame's masks, one candidate per heading.

    Implausible masks are reported: a view more than :data:`MAX_FOREGROUND` foreground (a whole
    person covers a few % of a view: inverted or all-foreground masks) and a hull whose height
    puts the subject outside :data:`SCALE_RANGE` (the scale is then held at the bound: masks or
    calibrations wrong, e.g. swapped) each give a warning.

    Args:
        rig: the :class:`~torchmocap.cameras.CameraRig` of the masks.
        masks: ``(C, H, W)`` bool foreground masks.
        headings: candidate headings (turns about the vertical).
        voxel: hull voxel size (metres).
        labels: the views' names in messages (default: the rig's camera names).

    Returns:
        ``meta`` entries (module docstring): the human31 scaled to the hull's top (clamped to
        :data:`SCALE_RANGE`), ``initial_poses (headings, D)`` with the feet on the hull's floor.

    Raises:
        ValueError: an empty hull (naming each view's foreground), a bad ``headings``.
    """
    from torchmocap.cameras import visual_hull
    from torchmocap.skeleton import human31

    if isinstance(headings, bool) or not isinstance(headings, int) or headings < 1:
        raise ValueError(f"data.headings: expected an int >= 1, got {headings!r}")
    labels = list(rig.names) if labels is None else list(labels)
    fg = masks.flatten(1).float().mean(1).tolist()
    views = ", ".join(f"{n} {100 * f:.1f} %" for n, f in zip(labels, fg))
    full = [n for n, f in zip(labels, fg) if f > MAX_FOREGROUND]
    if full:
        warnings.warn(f"data.path: the masks of {', '.join(full)} are more than "
                      f"{100 * MAX_FOREGROUND:.0f} % foreground ({views}); a whole person covers "
                      f"a few % of a view: inverted (person black) or all-foreground masks?",
                      stacklevel=3)
    hull = visual_hull(copy.deepcopy(rig).double(), masks, [[-3, 3], [-3, 3], [-0.1, 2.3]],
                       float(voxel))
    pts = hull.largest_component().centers()
    if pts.shape[0] == 0:
        raise ValueError(f"data.path: the visual hull of the masks is empty: no point of the "
                         f"room is foreground in every view (foreground read: {views}); masks "
                         f"empty, or a calibration of other cameras")
    top = float(pts[:, 2].max())
    centre = pts.mean(0)
    lo, hi = SCALE_RANGE
    size = min(max(top / _HEIGHT, lo), hi)
    if size != top / _HEIGHT:
        warnings.warn(f"data.path: the visual hull is {top:.2f} m tall, a subject "
                      f"{top / _HEIGHT:.2f} x human31's {_HEIGHT} m, outside the scale range "
                      f"[{lo}, {hi}]: the skeleton is held at {size}; the masks (inverted, all "
                      f"foreground) or the calibrations (swapped, of other cameras) are likely "
                      f"wrong ({views})", stacklevel=3)
    sk = human31().with_bone_lengths(scale=size)
    base = sk.zero_pose(dtype=torch.float32)
    base[0], base[1] = float(centre[0]), float(centre[1])
    base[2] = float(pts[:, 2].min().clamp(max=0.1))  # feet on the hull's floor
    cands = base.repeat(headings, 1)
    cands[:, sk.dof_index("pelvis_rz")] = torch.arange(headings) * (2 * math.pi / headings)
    return {"subject_skeleton": sk.to_dict(), "initial_poses": cands.tolist(),
            "hull_centre": centre.tolist(), "hull_top_m": top, "skeleton_scale": size}
