"""What a rig refinement changed, camera by camera, with its uncertainty: a JSON-ready dict
and a markdown table.

Per camera (:func:`refinement_report`): the rotation change (degrees; the angle and its
components about the camera's own axes: x tilt, y pan, z roll), the centre change (mm, world
axes, with the standard deviation along the camera's optical axis: the camera's distance, the
direction focal length trades against) and the translation change it implies, the focal change
(%), the principal point change (px), the change of k1 and k2, the time offset (frames), the
median reprojection distance before and after (px), the correlation of focal length and
distance, and the parameters the data did not determine (posterior std above half the prior
width). Every change comes with its standard deviation (Gauss–Newton, at the solution); a value
that was not refined is ``None``.

Example:
    >>> from torchmocap.cameras import make_ring_rig, bundle_adjust
    >>> rig = make_ring_rig(3, image_size=(640, 480)).double()
    >>> X = torch.rand(6, 9, 3, generator=torch.Generator().manual_seed(1),
    ...                dtype=torch.float64) + torch.tensor([-0.5, -0.5, 0.5])
    >>> uv = rig.project(X)[0]
    >>> res = bundle_adjust(torch.cat([uv, torch.ones_like(uv[..., :1])], -1), rig,
    ...                     groups=("rotation",), noise_px=1.0)
    >>> rep = refinement_report(res)
    >>> round(rep["cameras"][0]["rotation_change_deg"], 6), "| camera |" in report_markdown(rep)
    (0.0, True)
"""

from __future__ import annotations

import math
from typing import Any

import torch

from torchmocap.geometry import geodesic_angle

__all__ = ["refinement_report", "report_markdown"]


def _f(x, digits: int = 4):
    if x is None:
        return None
    x = float(x)
    return None if not math.isfinite(x) else round(x, digits)


def _vec(x, digits: int = 4):
    return [_f(v, digits) for v in x.tolist()]


def _norm_std(v: torch.Tensor, cov: torch.Tensor) -> float:
    """Std of ``‖v‖`` by the delta method (the largest axis std at zero)."""
    n = float(v.norm())
    if n < 1e-15:
        return float(torch.linalg.eigvalsh(cov).max().clamp_min(0).sqrt())
    u = v / n
    return float((u @ cov @ u).clamp_min(0).sqrt())


def refinement_report(result) -> dict[str, Any]:
    """The per-camera report of a :class:`~torchmocap.cameras.BundleAdjustmentResult`
    (module docstring): ``{"cameras": [...], "solver": {...}, "settings": {...},
    "poorly_determined": [...]}``, plain numbers (JSON-ready)."""
    par = result.parametrization
    C = par.num_cameras
    v, std, cov = result.values, result.std, result.covariance
    groups = set(par.groups)
    refined_rig = result.rig.double()
    base_R = par.R.to(refined_rig.R.device)
    flags = result.poorly_determined()
    cams = []
    for c, name in enumerate(par.names):
        block = cov[c * 13:(c + 1) * 13, c * 13:(c + 1) * 13]
        R = par.R[c]
        axis = R[2]  # optical axis in world
        entry: dict[str, Any] = {"name": name}
        if "rotation" in groups:
            w = v[c, 0:3]
            S = block[0:3, 0:3]
            entry["rotation_change_deg"] = _f(math.degrees(float(geodesic_angle(
                base_R[c], refined_rig.R[c]))))
            entry["rotation_change_std_deg"] = _f(math.degrees(_norm_std(w, S)))
            entry["rotation_camera_axes_deg"] = _vec(torch.rad2deg(R @ w))
            entry["rotation_camera_axes_std_deg"] = _vec(torch.rad2deg(
                (R @ S @ R.T).diagonal().clamp_min(0).sqrt()))
        else:
            entry.update(rotation_change_deg=None, rotation_change_std_deg=None)
        if "translation" in groups:
            d = v[c, 3:6]
            S = block[3:6, 3:6]
            entry["centre_change_mm"] = _f(1000 * float(d.norm()), 2)
            entry["centre_change_std_mm"] = _f(1000 * _norm_std(d, S), 2)
            entry["centre_change_xyz_mm"] = _vec(1000 * d, 2)
            entry["centre_std_mm"] = _vec(1000 * S.diagonal().clamp_min(0).sqrt(), 2)
            entry["depth_change_mm"] = _f(1000 * float(axis @ d), 2)
            entry["depth_std_mm"] = _f(1000 * float((axis @ S @ axis).clamp_min(0).sqrt()), 2)
        else:
            entry.update(centre_change_mm=None, centre_change_std_mm=None,
                         centre_std_mm=None, depth_std_mm=None)
        if "rotation" in groups or "translation" in groups:
            entry["translation_change_mm"] = _f(1000 * float(
                (refined_rig.t[c] - par.t[c].to(refined_rig.t)).norm()), 2)
        if "focal" in groups or "focal_xy" in groups:
            for key, i in (("focal_change_percent", 6), ("focal_y_change_percent", 7)):
                if key == "focal_y_change_percent" and "focal_xy" not in groups:
                    continue
                s = float(v[c, i])
                entry[key] = _f(100 * math.expm1(s), 3)
                entry[key.replace("change", "std")] = _f(100 * math.exp(s) * float(std[c, i]),
                                                         3)
            if "translation" in groups:
                sd = float((axis @ block[3:6, 3:6] @ axis).clamp_min(0).sqrt())
                cross = float(axis @ block[3:6, 6])
                sf = float(std[c, 6])
                entry["focal_depth_correlation"] = _f(cross / (sd * sf), 3) \
                    if sd > 0 and sf > 0 else None
        else:
            entry.update(focal_change_percent=None, focal_std_percent=None)
        if "principal_point" in groups:
            entry["principal_point_change_px"] = _vec(v[c, 8:10], 3)
            entry["principal_point_std_px"] = _vec(std[c, 8:10], 3)
        else:
            entry.update(principal_point_change_px=None, principal_point_std_px=None)
        if "distortion" in groups:
            entry["k1_change"], entry["k2_change"] = _vec(v[c, 10:12], 6)
            entry["k1_std"], entry["k2_std"] = _vec(std[c, 10:12], 6)
        if "time_offset" in groups:
            entry["time_offset_frames"] = _f(v[c, 12])
            entry["time_offset_std_frames"] = _f(std[c, 12])
        else:
            entry.update(time_offset_frames=None, time_offset_std_frames=None)
        entry["residual_median_px_before"] = _f(result.residual_px_before[c], 3)
        entry["residual_median_px_after"] = _f(result.residual_px_after[c], 3)
        entry["detections"] = result.detections_per_camera[c] if \
            result.detections_per_camera else None
        entry["poorly_determined"] = [f.split(".", 1)[1] for f in flags
                                      if f.split(".", 1)[0] == name]
        cams.append(entry)
    return {
        "cameras": cams,
        "solver": {"iterations": result.iterations, "converged": bool(result.converged),
                   "message": result.message, "cost_initial": _f(result.cost_initial, 6),
                   "cost_final": _f(result.cost_final, 6), "noise_px": _f(result.noise_px),
                   "noise_rounds": result.noise_rounds,
                   "detections": result.num_detections,
                   "frames": [result.frames.start, result.frames.stop]},
        "settings": dict(result.settings),
        "poorly_determined": flags,
        "cameras_count": C,
    }


def _pm(value, sd, fmt: str) -> str:
    if value is None:
        return "–"
    if sd is None:
        return format(value, fmt)
    return f"{format(value, fmt)} ± {format(sd, fmt)}"


def report_markdown(report: dict[str, Any]) -> str:
    """A markdown table of :func:`refinement_report`'s dict (one row per camera), with the
    solver's summary line below it.

    Example:
        >>> text = report_markdown({"cameras": [], "solver": {"iterations": 3,
        ...     "converged": True, "noise_px": 1.5, "cost_initial": 9.0, "cost_final": 2.0,
        ...     "frames": [0, 10], "detections": 80}, "poorly_determined": []})
        >>> text.splitlines()[0].startswith("| camera | rotation ° | centre mm (depth σ) |")
        True
    """
    head = ("| camera | rotation ° | centre mm (depth σ) | translation mm | focal % | "
            "principal point px | time offset frames | median px before → after | "
            "not determined |")
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for e in report["cameras"]:
        centre = _pm(e.get("centre_change_mm"), e.get("centre_change_std_mm"), ".1f")
        if e.get("depth_std_mm") is not None:
            centre += f" ({e['depth_std_mm']:.1f})"
        focal = _pm(e.get("focal_change_percent"), e.get("focal_std_percent"), ".2f")
        if e.get("focal_y_change_percent") is not None:
            focal += " / " + _pm(e["focal_y_change_percent"], e.get("focal_y_std_percent"),
                                 ".2f")
        pp = e.get("principal_point_change_px")
        pps = e.get("principal_point_std_px") or [None, None]
        ppt = "–" if pp is None else ", ".join(_pm(a, b, ".1f") for a, b in zip(pp, pps))
        trans = e.get("translation_change_mm")
        before, after = e.get("residual_median_px_before"), e.get("residual_median_px_after")
        res = "–" if before is None else f"{before:.1f} → {after:.1f}"
        lines.append("| " + " | ".join([
            str(e["name"]),
            _pm(e.get("rotation_change_deg"), e.get("rotation_change_std_deg"), ".2f"),
            centre, "–" if trans is None else f"{trans:.1f}", focal, ppt,
            _pm(e.get("time_offset_frames"), e.get("time_offset_std_frames"), ".3f"),
            res, ", ".join(e.get("poorly_determined", [])) or "–"]) + " |")
    s = report["solver"]
    lines.append("")
    lines.append(f"{s['iterations']} iterations, converged: {s['converged']}; objective "
                 f"{s['cost_initial']:.6g} → {s['cost_final']:.6g}; noise σ "
                 f"{s['noise_px']:.2f} px; frames {s['frames'][0]}–{s['frames'][1] - 1}, "
                 f"{s['detections']} detections. ± one standard deviation (Gauss–Newton at "
                 "the solution; correlated detector errors are not in it).")
    return "\n".join(lines) + "\n"
