"""The files of a finished ``torchmocap-track`` run and its printed summary: ``track.npz``,
``tracked.bvh``, ``errors.png``, the overlay grids, the overlay video and the animated GLB, each
written atomically; :func:`validate_outputs` checks their settings before a track starts."""

from __future__ import annotations

import json
import math
from pathlib import Path

__all__ = ["GLB_BODIES", "print_summary", "validate_outputs", "write_outputs"]

#: ``glb.body``: the fitted surface body when the tracker fitted one, else the bundled mesh
#: (``auto``); the fitted body (``fitted``); the bundled CC0 mesh; a stick figure
GLB_BODIES = ("auto", "fitted", "skinned", "stick")


def write_outputs(out: Path, cfg, seq, runtime, theta, arrays: dict, fitted_mesh=None) -> None:
    """``track.npz`` (``arrays``), ``tracked.bvh`` (the track ``theta (T, D)``), a
    self-calibrated recording's ``calibration/`` (the refined calibration and its report) and
    the plots, overlays, video and GLB the output settings of ``cfg`` ask for, into ``out``;
    ``fitted_mesh``: the body fit's ``(body, phenotype)``
    (:meth:`~torchmocap.filters.BodyFit.fitted_mesh`) for ``glb.body: auto``/``fitted``."""
    import numpy as np
    import torch

    from torchmocap.io import MotionClip, write_bvh

    sk = runtime.skeleton
    record = seq.meta.calibration_refinement
    if record is not None:  # the self-calibrated rig in the recording's format, its report
        from torchmocap.cameras import rig_from_dict
        from torchmocap.data.recordings.self_calibration import write_refinement

        write_refinement(out, rig_from_dict(record["rig"]), record, seq.meta.calibration,
                         record.get("unit"))
    np.savez_compressed(out / "track.npz", **arrays)
    write_bvh(out / "tracked.bvh", MotionClip.from_skeleton(sk.double(), theta.double(),
                                                            fps=seq.fps))
    sk.float()
    with torch.no_grad():
        _write_plots(out, seq, runtime, theta, arrays, cfg, fitted_mesh)


def validate_outputs(cfg) -> None:
    """The output settings (``overlays``, ``overlay_scale``, ``video.*``, ``glb.*``), checked
    before the track so that a typo does not fail a long run at its end."""
    from torchmocap.viz.video import VIDEO_FORMATS

    def number(key, value, none=False):
        if none and value is None:
            return
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                not (math.isfinite(value) and value > 0):
            raise ValueError(f"{key}: expected a finite number > 0{' or null' if none else ''}, "
                             f"got {value!r}")

    n = cfg.get("overlays", 3)
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"overlays: expected an integer >= 0, got {n!r}")
    number("overlay_scale", cfg.get("overlay_scale", 1.0))
    video = cfg.get("video") or {}
    if video.get("format", "mp4") not in VIDEO_FORMATS:
        raise ValueError(f"video.format: expected one of {list(VIDEO_FORMATS)}, got "
                         f"{video.get('format')!r}")
    number("video.max_fps", video.get("max_fps"), none=True)
    number("video.scale", video.get("scale", 1.0))
    glb = cfg.get("glb") or {}
    if glb.get("body", "auto") not in GLB_BODIES:
        raise ValueError(f"glb.body: expected one of {list(GLB_BODIES)}, got "
                         f"{glb.get('body')!r}")
    if glb.get("up", "y") not in ("y", "z"):
        raise ValueError(f"glb.up: expected 'y' or 'z', got {glb.get('up')!r}")


def _write_plots(out, seq, runtime, theta, arrays, cfg, fitted_mesh=None):
    """``errors.png``, the overlay grids, the video and the GLB (each file atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchmocap.atomic import atomic_path
    from torchmocap.evaluation import validation_bones

    T = theta.shape[0]
    if "orientation_error_deg" in arrays:
        ori, mp = arrays["orientation_error_deg"], arrays["mpjpe_mm"]
        t_axis = np.arange(1, T) / seq.fps
        fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
        for k, b in enumerate(validation_bones(seq)):
            ax[0].plot(t_axis, ori[:, k], label=b, lw=1)
        ax[0].plot(t_axis, ori.mean(1), "k", lw=2, label="mean")
        ax[0].set_ylabel("orientation error (deg)")
        ax[0].legend(fontsize=7, ncol=3)
        ax[1].plot(t_axis, mp, "k")
        ax[1].set_ylabel("MPJPE (mm)")
        ax[1].set_xlabel("time (s)")
        fig.tight_layout()
        with atomic_path(out / "errors.png") as tmp:
            fig.savefig(tmp, dpi=100, format="png")
        plt.close(fig)
    _write_overlays(out, seq, runtime, theta, cfg)
    glb = cfg.get("glb") or {}
    if glb.get("enabled", False):
        _write_glb(out / "track.glb", seq, runtime, theta, glb, fitted_mesh)


def _write_overlays(out, seq, runtime, theta, cfg) -> None:
    """Overlay grids (``overlay_XXXX.png``: every view of ``seq`` — a held-out camera too,
    labelled so —, the estimate, the truth or the detections, a legend) at ``overlays`` evenly
    spaced tracked frames (the only frame of a one-frame sequence); with ``video.enabled`` an
    animation of the grids over the whole track."""
    import logging

    import numpy as np

    from torchmocap.viz.overlays import track_overlay_frames, write_overlay_grid
    from torchmocap.viz.video import decimation, write_video

    n = int(cfg.get("overlays", 3))
    video = cfg.get("video") or {}
    if runtime.rig is None or seq.rig is None or (seq.silhouettes is None and seq.images is None):
        if video.get("enabled", False):
            logging.getLogger(__name__).warning("video: the sequence has no camera views; "
                                                "no video written")
        return
    T = int(theta.shape[0])
    held = seq.meta.heldout_camera
    labels = None if held is None else [f"{c} (held out)" if c == held else c
                                        for c in seq.rig.names]
    kw = dict(rig=seq.rig.to(runtime.rig.K.dtype), body=runtime.body, labels=labels,
              scale=float(cfg.get("overlay_scale", 1.0)))
    if n > 0:
        frames = ([0] if T == 1 else sorted({int(round(x)) for x in np.linspace(1, T - 1, n)}))
        for t, grid in track_overlay_frames(seq, runtime.skeleton, theta, frames, **kw):
            write_overlay_grid(out / f"overlay_{t:04d}.png", grid)
    if video.get("enabled", False):
        fps = float(seq.fps)
        max_fps = video.get("max_fps")
        step = decimation(fps, None if max_fps is None else float(max_fps))
        kw["scale"] = float(video.get("scale", kw["scale"]))
        grids = (g for _, g in track_overlay_frames(seq, runtime.skeleton, theta,
                                                     range(0, T, step), **kw))
        path = write_video(out / "overlays", grids, fps / step, format=str(video.get("format",
                                                                                     "mp4")))
        logging.getLogger(__name__).info("video: wrote %s (%d frames at %g fps)", path,
                                         len(range(0, T, step)), fps / step)


def _write_glb(path, seq, runtime, theta, glb, fitted_mesh=None) -> None:
    """``track.glb`` following the estimate, keyframes at the sequence's frame times: the body
    fit's Anny mesh (``glb.body: fitted``; ``auto`` when the tracker fitted one), the bundled
    skinned body (``skinned``; ``auto`` otherwise) or a stick figure (``stick``)."""
    import logging

    from torchmocap.export import write_glb

    kind = glb.get("body", "auto")
    mesh = phenotype = None
    if kind in ("auto", "fitted") and fitted_mesh is not None:
        mesh, phenotype = fitted_mesh
    elif kind == "fitted":
        logging.getLogger(__name__).warning(
            "glb.body: fitted, but the tracker fitted no surface body (tracker.body_fit with "
            "a mesh, e.g. body_fit=anny): writing the bundled skinned body")
    if mesh is None and kind != "stick":
        from torchmocap.body import SkinnedBody

        mesh = SkinnedBody()
    write_glb(path, runtime.skeleton, theta, float(seq.fps), body_mesh=mesh,
              up=str(glb.get("up", "y")), phenotype=phenotype)


def _recording_rows(m: dict) -> list[tuple[str, str]]:
    """Summary rows of a track without ground truth: the scores in the held-out view (and of
    the first pose held), in the tracked views, bone-length CV and jitter."""
    def px(d: dict) -> str:
        iou = "" if "silhouette_iou" not in d else ", IoU -" if d["silhouette_iou"] is None \
            else f", IoU {d['silhouette_iou']:.3f}"
        if "median_px" not in d:
            return iou[2:] or "-"
        if d["median_px"] is None:
            return "no detections to compare" + iou
        return (f"{d['median_px']:.1f} px median, {d['mean_px']:.1f} mean, PCK@5% "
                f"{d['pck_05']:.3f}, @10% {d['pck_10']:.3f}{iou}")

    rows = [("tracker", m["tracker"]), ("frames", m["frames"]),
            _search_row(m),
            ("seconds / frame", f"{m['seconds_per_frame']:.3f}")]
    r = m.get("calibration_refinement")
    if r:  # the self-calibration: each camera's residual before -> after
        cams = r["report"]["cameras"]
        rows.append((f"calibration refined ({r['objective']}, frames {r['frames'][0]}-"
                     f"{r['frames'][1] - 1})", ", ".join(
                         f"{c['name']} {c['residual_median_px_before']:.1f}->"
                         f"{c['residual_median_px_after']:.1f} px" for c in cams)))
    h = m.get("heldout")
    if h:
        rows += [(f"held-out {h['camera']}", px(h)),
                 ("  holding the first pose", px(h["hold_first_pose"]))]
    for cam, d in (m.get("tracked_views") or {}).items():
        rows.append((f"tracked {cam}", "no detections to compare" if d["median_px"] is None
                     else f"{d['median_px']:.1f} px median, PCK@10% {d['pck_10']:.3f}"))
    c = m.get("consistency")
    if c:
        cv = c["bone_length_cv_percent"]
        if cv:
            rows.append((f"bone-length CV ({c['points']})", f"{cv['mean']:.2f} % mean"))
        rows.append((f"jitter ({c['points']})", f"{c['jitter_m_s2']['mean']:.1f} m/s^2"))
    return rows


def _search_row(m: dict) -> tuple[str, str]:
    """The summary's particles (x annealing layers, for an inference that has layers)."""
    if m.get("layers") is None:
        return "particles", f"{m['num_particles']}"
    return "particles x layers", f"{m['num_particles']} x {m['layers']}"


def print_summary(m: dict) -> None:
    """The run's summary table on stdout: the errors against the truth, or the scores without
    it (held-out view, tracked views, consistency) when the run has them, else the metrics as
    JSON (without the clip and the input files' digests)."""
    if "orientation_error_deg" not in m:
        if "heldout" in m or "consistency" in m:
            _print_rows(_recording_rows(m))
            return
        print(json.dumps({k: v for k, v in m.items() if k not in ("clip", "inputs")}, indent=2))
        return
    o = m["orientation_error_deg"]
    rows = [("tracker", m["tracker"]), ("scenario", m.get("scenario")), ("frames", m["frames"]),
            _search_row(m),
            ("seconds / frame", f"{m['seconds_per_frame']:.3f}"),
            ("orientation error (deg)", f"{o['mean']:.2f} +- {o['std']:.2f}"),
            ("MPJPE (mm)", f"{m['mpjpe_mm']['mean']:.1f} +- {m['mpjpe_mm']['std']:.1f}")]
    r = m.get("mpjpe_root_relative_mm")
    if r:
        rows.append(("MPJPE, root-aligned (mm)", f"{r['mean']:.1f} +- {r['std']:.1f}"))
    f = m.get("filtered")
    if f and m.get("smoother"):  # the errors above are the smoothed track's
        rows.append((f"filtered (before {m['smoother'].get('name', 'smoothing')})",
                     f"{f['orientation_error_deg']:.2f} deg, {f['mpjpe_mm']:.1f} mm"))
    held = m.get("hold_first_pose")
    if held:
        rows.append(("holding the first pose", f"{held['orientation_error_deg']:.2f} deg, "
                                               f"{held['mpjpe_mm']:.1f} mm"))
    rows += [(f"  {b}", f"{v:.2f}") for b, v in o["per_bone"].items()]
    _print_rows(rows)


def _print_rows(rows: list[tuple[str, object]]) -> None:
    w = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
