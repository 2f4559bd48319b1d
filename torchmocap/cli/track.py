"""``torchmocap-track``: track a sequence with a tracker assembled from config (Hydra CLI).

Default: the bundled 3 s CMU walk, the ``studio`` scenario, tracker ``p`` (Pons-Moll et al.).
The sequence comes from the ``data`` node (a ``_target_`` source: synthesised from a clip, or a
real recording such as ``data=bodytrack``); the tracker is built from the ``tracker`` node by
:func:`torchmocap.assembly.build_tracker` — the command line never reaches into components.

Writes into the Hydra run directory: ``metrics.json`` (last, atomically), ``track.npz``,
``tracked.bvh``, overlay grids (every view, estimate and truth), ``errors.png``, and on request
an animation of the overlays (``video.enabled``) and an animated skinned body (``glb.enabled``);
the images, videos and GLB are written atomically too. A failure prints one line on stderr, writes
``failure.json`` and exits with status 2; in a multirun the other jobs go on and the command
exits with status 2 at the end if any job failed. A run directory whose ``metrics.json`` has the
same fingerprint (config, code, data files) is skipped as up to date.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from torchmocap.cli.runs import (
    config_fingerprint,
    load_sequence,
    read_json,
    sweep_failed,
    write_failure,
    write_json_atomic,
)

__all__ = ["main", "run"]

#: Validation bones when the sequence has no validation IMUs (Pons-Moll's five).
VALIDATION_BONES_FALLBACK = ["spine", "l_shoulder", "r_shoulder", "l_hip", "r_hip"]


def _sequence_fingerprint(seq) -> str:
    import hashlib

    import torch

    h = hashlib.sha256()
    for x in (seq.silhouettes, seq.images, None if seq.imu is None else seq.imu.quaternions,
              None if seq.depth is None else seq.depth.points, seq.joints2d):
        if isinstance(x, torch.Tensor):
            h.update(x.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def run(cfg: DictConfig, out: Path) -> dict:
    """Run the configured job; returns the metrics written to ``out/metrics.json``."""
    from torchmocap.assembly import Runtime, build_tracker

    if cfg.get("batch_seeds"):  # several seeds in one process: one run dir per seed
        from torchmocap.cli.batch import run_batch

        return run_batch(cfg, out)
    fingerprint = config_fingerprint(cfg)
    done = read_json(out / "metrics.json")
    if isinstance(done, dict) and done.get("fingerprint") == fingerprint and \
            cfg.get("skip_completed", True):
        print(f"torchmocap-track: {out} is complete and up to date (fingerprint {fingerprint}); "
              "skipped", file=sys.stderr)
        return done
    # a rerun in place: the old records must not outlive this run's config
    for stale in ("failure.json", "metrics.json"):
        (out / stale).unlink(missing_ok=True)
    governor = thread_policy(cfg)
    _validate_tracker(cfg)  # settings errors before any loading, fitting or synthesis
    _validate_outputs(cfg)
    seq = load_sequence(cfg, min_frames=2)
    runtime = Runtime.from_sequence(seq)
    try:
        tracker = build_tracker(cfg.tracker, runtime, seed=cfg.seed)
        tracker.check_sequence(seq)
    except ValueError as e:
        hint = seq.meta.get("suggested_tracker")
        if hint and cfg.tracker.get("name") != hint:
            raise type(e)(f"{e} (this data is tracked with tracker={hint})") from e
        raise
    ckpt = cfg.get("checkpoint")
    if ckpt:  # relative: to the working directory of a single run, to each job's directory
        ckpt = Path(str(ckpt)).expanduser()
        if not ckpt.is_absolute():
            ckpt = (out if _multirun() else Path.cwd()) / ckpt
        ckpt = str(ckpt)
    track = tracker.run(seq, progress=bool(cfg.get("progress", True)), checkpoint=ckpt,
                        checkpoint_every=int(cfg.get("checkpoint_every", 10)),
                        fingerprint=f"{fingerprint}-{_sequence_fingerprint(seq)}",
                        callbacks=[governor])
    return finish(cfg, out, seq, runtime, tracker, track, fingerprint,
                  {"threads": governor.summary()})


def thread_policy(cfg):
    """Set torch's thread count by the ``threads`` setting (:mod:`torchmocap.threads`: ``auto``
    stays off cores that other processes or parallel jobs of the sweep use); returns the
    governor that re-checks between frames."""
    from torchmocap.threads import ThreadGovernor

    launcher = None
    if _multirun():
        from hydra.core.hydra_config import HydraConfig

        launcher = HydraConfig.get().launcher
    return ThreadGovernor.start(cfg.get("threads", "auto"), launcher)


def finish(cfg, out: Path, seq, runtime, tracker, track, fingerprint: str,
           extra: dict | None = None) -> dict:
    """Metrics and output files of a finished track (``extra`` joins the metrics)."""
    import numpy as np
    import torch

    from torchmocap.io import MotionClip, write_bvh

    sk = runtime.skeleton
    metrics: dict[str, Any] = {
        "tracker": tracker.name,
        "frames": int(track.theta.shape[0]),
        "tracked_frames": int(track.theta.shape[0] - 1),
        "seconds_per_frame": track.seconds_per_frame,
        "num_particles": tracker.num_particles,
        "layers": getattr(tracker.inference, "layers", None),
        "scenario": seq.scenario,
        "seed": int(cfg.seed),
        "clip": seq.meta.get("clip", {}),
        "fingerprint": fingerprint,
        **_diagnostics(track.infos),
        **(extra or {}),
    }
    arrays = {"theta": track.theta.numpy(), "dof_names": np.array(sk.dof_names),
              **hypothesis_arrays(track.infos, sk.num_dofs)}
    smoothing = track.infos[0].get("smoother") if isinstance(track.infos[0], dict) else None
    if track.filtered is not None:  # theta is smoothed; the filter's own estimates beside it
        arrays["theta_filtered"] = track.filtered.numpy()
        if smoothing:
            metrics["smoother"] = _smoother_report(smoothing)
    if seq.ground_truth is not None:
        errors = _errors(seq, sk, track.theta)
        metrics.update(errors.pop("summary"))
        arrays.update({k: v.numpy() for k, v in errors.items()})
        held_dofs = _held_dofs(seq, sk, track.theta)
        if held_dofs:
            metrics["held_dofs"] = held_dofs
        # the do-nothing tracker: the first frame's pose (every tracker's start) held throughout
        held = _errors(seq, sk, track.theta[:1].expand_as(track.theta))["summary"]
        metrics["hold_first_pose"] = {
            "orientation_error_deg": held["orientation_error_deg"]["mean"],
            "mpjpe_mm": held["mpjpe_mm"]["mean"],
            "mpjpe_root_relative_mm": held["mpjpe_root_relative_mm"]["mean"]}
        if track.filtered is not None:
            f = _errors(seq, sk, track.filtered)["summary"]
            metrics["filtered"] = {"orientation_error_deg": f["orientation_error_deg"]["mean"],
                                   "mpjpe_mm": f["mpjpe_mm"]["mean"],
                                   "mpjpe_root_relative_mm": f["mpjpe_root_relative_mm"]["mean"]}
            # a chain of smoothers: the errors after each stage (an ablation in one run); the
            # last stage's are the top-level ones
            stages = (smoothing or {}).get("stages") or []
            for k, rep in enumerate(stages):
                if not (isinstance(rep, dict) and isinstance(rep.get("theta"), torch.Tensor)):
                    continue
                e = (metrics if k == len(stages) - 1
                     else _errors(seq, sk, rep["theta"].cpu())["summary"])
                metrics["smoother"]["stages"][k]["errors"] = {
                    key: e[key]["mean"] for key in ("orientation_error_deg", "mpjpe_mm",
                                                    "mpjpe_root_relative_mm")}
        if seq.ground_truth.markers is not None:
            metrics["marker_error_mm"] = _marker_error(seq, runtime, track.theta)
            if track.filtered is not None:
                metrics["filtered"]["marker_error_mm"] = _marker_error(
                    seq, runtime, track.filtered)["mean"]
        hyp = _hypotheses(seq, sk, track.infos)
        if hyp:
            metrics["hypotheses"] = hyp
        if cfg.get("diagnostics", {}).get("energy_vs_truth", False):
            metrics["estimate_energy_below_truth"] = _energy_vs_truth(tracker, seq, track.theta)
    else:
        metrics["silhouette_iou"] = _iou(runtime, seq, track.theta)
    if seq.joints2d is not None and runtime.rig is not None:
        metrics["reprojection_px"] = _reprojection(seq, sk, runtime.rig, track.theta)
    for k in ("hull_top_m", "skeleton_scale", "source"):
        if k in seq.meta:
            metrics[k] = seq.meta[k]
    np.savez_compressed(out / "track.npz", **arrays)
    write_bvh(out / "tracked.bvh", MotionClip.from_skeleton(sk.double(), track.theta.double(),
                                                            fps=seq.fps))
    sk.float()
    with torch.no_grad():
        _write_plots(out, seq, runtime, track.theta, arrays, cfg)
    write_json_atomic(metrics, out / "metrics.json")
    return metrics


def _multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def _validate_tracker(cfg) -> None:
    """Build the tracker once against a stand-in subject (human31, four cameras, the paper's
    five tracking IMUs): a bad setting fails in a fraction of a second, before the data is
    loaded, fitted and synthesised."""
    from torchmocap.assembly import Runtime, build_tracker
    from torchmocap.body import CapsuleBody
    from torchmocap.cameras import make_ring_rig
    from torchmocap.ik import SensorManifold
    from torchmocap.skeleton import human31

    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed: expected an integer, got {seed!r}")
    sk = human31()
    stand_in = Runtime(skeleton=sk, body=CapsuleBody(sk).float(), rig=make_ring_rig(4).float(),
                       manifold=SensorManifold(sk))
    build_tracker(cfg.tracker, stand_in, seed=seed)


def _smoother_report(report: dict) -> dict:
    """A smoother's report for ``metrics.json``: without the per-frame mode indices (kept in
    ``track.npz``'s hypotheses) and a chain stage's output track (``theta``; its errors are
    reported instead), also inside the stages of a chain."""
    out = {k: v for k, v in report.items() if k not in ("modes", "theta")}
    if isinstance(out.get("stages"), list):
        out["stages"] = [_smoother_report(r) if isinstance(r, dict) else r
                         for r in out["stages"]]
    return out


def _validation_bones(seq) -> list[str]:
    if seq.imu is not None:
        val = [b for b, t in zip(seq.imu.bones, seq.imu.tracking.tolist()) if not t]
        if val:
            return val
    return VALIDATION_BONES_FALLBACK


def _errors(seq, sk, theta) -> dict:
    """Validation orientation error (eq. 19) and MPJPE of frames 1..T-1 against the truth."""
    from torchmocap.metrics import mpjpe_mm, orientation_error_deg, summarize_errors

    gt = seq.ground_truth
    val = _validation_bones(seq)
    kin = sk(theta)
    vb = [sk.joint_index(b) for b in val]
    ori = orientation_error_deg(kin.rotations[1:, vb], gt.rotations[1:, vb].float())
    mp = mpjpe_mm(kin.positions[1:], gt.positions[1:].float())
    mp_root = mpjpe_mm(kin.positions[1:], gt.positions[1:].float(), root=_root_joint(sk))
    summary = {"validation_bones": val, **summarize_errors(ori, val, mp, mp_root)}
    summary["orientation_error_deg"]["per_frame"] = [round(float(v), 4) for v in ori.mean(1)]
    summary["orientation_error_deg"]["per_bone_frame"] = {
        b: [round(float(v), 4) for v in ori[:, k]] for k, b in enumerate(val)}
    summary["mpjpe_mm"]["per_frame"] = [round(float(v), 3) for v in mp]
    summary["mpjpe_root_relative_mm"]["per_frame"] = [round(float(v), 3) for v in mp_root]
    return {"summary": summary, "theta_gt": gt.theta, "orientation_error_deg": ori,
            "mpjpe_mm": mp}


#: the truth's motion of the DoFs a tracker holds that makes the run warn (metres, degrees)
HELD_WARN_TRANSLATION, HELD_WARN_ROTATION = 0.25, 30.0


def _root_joint(sk) -> int:
    """Index of the skeleton's root joint (the one without a parent)."""
    return next(j for j, p in enumerate(sk.parents) if p < 0)


def _held_dofs(seq, sk, theta) -> dict | None:
    """The DoFs the track never moved from the first frame (an upper-body tracker's torso and
    legs, say) and how far the truth moves them over the clip; warns when it is far: the
    errors of such a run measure the held DoFs, not the tracker."""
    import torch

    # (a weighted mean of equal values may differ from them in the last bits)
    held = torch.isclose(theta, theta[:1], rtol=1e-5, atol=1e-6).all(0)
    if not bool(held.any()):
        return None
    gt = seq.ground_truth.theta.to(theta.dtype).cpu()
    trans = [d for d in sk.translation_dofs if held[d]]
    rot = [d for d in range(sk.num_dofs) if held[d] and d not in sk.translation_dofs]
    move = float((gt[:, trans] - gt[:1, trans]).norm(dim=-1).amax()) if trans else 0.0
    turn = torch.remainder(gt[:, rot] - gt[:1, rot] + math.pi, 2 * math.pi) - math.pi
    turn = turn.abs().amax(0) if rot else torch.zeros(0)
    deg = [math.degrees(float(v)) for v in turn]
    worst = sorted((k for k in range(len(rot)) if deg[k] > HELD_WARN_ROTATION),
                   key=lambda k: -deg[k])[:3]
    out = {"count": int(held.sum()), "truth_max_translation_m": move,
           "truth_max_rotation_deg": max(deg, default=0.0)}
    if move > HELD_WARN_TRANSLATION or worst:
        what = [f"the root moves {move:.2f} m"] if move > HELD_WARN_TRANSLATION else []
        what += [f"{sk.dof_names[rot[k]]} turns {deg[k]:.0f} deg" for k in worst]
        hint = "a Hauberg preset tracks the whole body with tracker.proposal.joints=all"
        if move > HELD_WARN_TRANSLATION:
            hint += "; data.clip.in_place=true keeps the subject at its start"
        print(f"torchmocap-track: warning: the tracker held {out['count']} DoFs at the first "
              f"frame's pose (e.g. an upper-body tracker's torso), but in this clip "
              f"{', '.join(what)}; the errors measure that, not the tracking ({hint})",
              file=sys.stderr)
    return out


def _marker_error(seq, runtime, theta) -> dict:
    """Eq. 16 of Hauberg & Pedersen: distance (mm) of the skin markers to the estimated
    capsule skin, frames 1..T-1."""
    from torchmocap.metrics import marker_skin_distance

    body = runtime.body
    d = marker_skin_distance(seq.ground_truth.markers[1:],
                             body.endpoints(runtime.skeleton(theta[1:])), body.radii) * 1000
    per_part: dict[str, list] = {}
    for k, p in enumerate(seq.ground_truth.marker_parts):
        per_part.setdefault(p, []).append(k)
    return {"mean": float(d.mean()), "per_frame": [round(float(v), 3) for v in d.mean(1)],
            "per_part": {p: float(d[:, ks].mean()) for p, ks in per_part.items()}}


def hypothesis_arrays(infos: list, num_dofs: int) -> dict:
    """What a multi-hypothesis inference kept per frame, as arrays for ``track.npz``:
    ``hypotheses (T, K, D)`` (the modes, radians / metres), ``hypothesis_weights (T, K)`` and
    ``hypothesis_energy (T, K)`` (each mode's likelihood energy), ``K`` the most modes of any
    frame; frames with fewer modes (and frame 0, the given start) are padded with NaN. Empty
    when no frame holds ``info["hypotheses"]``."""
    import numpy as np

    rows = [i.get("hypotheses") if isinstance(i, dict) else None for i in infos]
    K = max((len(r) for r in rows if r), default=0)
    if not K:
        return {}
    T = len(infos)
    hyp = np.full((T, K, num_dofs), np.nan, dtype=np.float32)
    w = np.full((T, K), np.nan, dtype=np.float32)
    e = np.full((T, K), np.nan, dtype=np.float32)
    for t, (info, r) in enumerate(zip(infos, rows)):
        if not r:
            continue
        H = np.asarray(r, dtype=np.float32)
        if H.ndim != 2 or H.shape[1] != num_dofs:
            raise ValueError(f"infos[{t}]['hypotheses']: expected (K, {num_dofs}), got "
                             f"{H.shape}")
        hyp[t, : len(H)] = H
        for key, arr in (("hypothesis_weights", w), ("mode_energy", e)):
            v = info.get(key)
            if v is not None and len(v) == len(H):
                arr[t, : len(H)] = np.asarray(v, dtype=np.float32)
    return {"hypotheses": hyp, "hypothesis_weights": w, "hypothesis_energy": e}


def _hypotheses(seq, sk, infos) -> dict:
    """MPJPE (global and root-aligned) of the top-weighted and of the best of the hypotheses a
    multi-hypothesis inference keeps per frame (``info["hypotheses"]``,
    ``info["hypothesis_weights"]``), and their count."""
    import torch

    from torchmocap.metrics import mpjpe_mm

    top, best, top_root, best_root, modes = [], [], [], [], []
    root = _root_joint(sk)
    for t, info in enumerate(infos):
        if t == 0 or not isinstance(info, dict) or not info.get("hypotheses"):
            continue
        H = torch.as_tensor(info["hypotheses"], dtype=torch.float32)
        w = torch.as_tensor(info.get("hypothesis_weights") or [1.0] * H.shape[0])
        truth = seq.ground_truth.positions[t].float()
        pos, ref = sk(H).positions, truth.expand(H.shape[0], -1, -1)
        err = mpjpe_mm(pos, ref)
        err_root = mpjpe_mm(pos, ref, root=root)
        k = int(torch.argmax(w))
        top.append(float(err[k]))
        best.append(float(err.min()))
        top_root.append(float(err_root[k]))
        best_root.append(float(err_root.min()))
        modes.append(int(H.shape[0]))
    if not top:
        return {}

    def stats(v):
        return {"mean": sum(v) / len(v), "per_frame": [round(x, 3) for x in v]}

    return {"mpjpe_top_mm": stats(top), "mpjpe_best_mm": stats(best),
            "mpjpe_root_relative_top_mm": stats(top_root),
            "mpjpe_root_relative_best_mm": stats(best_root),
            "modes": {"mean": sum(modes) / len(modes), "per_frame": modes}}


def _reprojection(seq, sk, rig, theta) -> dict:
    """2D error (pixels) of the estimate's projected joints against the detections of
    confidence >= 0.5 (``vs_detections``) and, with ground truth, against the true joints'
    projections (``vs_truth``), over frames 1..T-1 and every camera."""

    pos = sk(theta[1:]).positions  # (T-1, J, 3)
    pix, _, vis = rig.project(pos.to(rig.K.dtype))  # (T-1, C, J, 2)
    det = seq.joints2d[1:].to(pix.dtype)
    if det.shape[-2] != pix.shape[-2]:
        return {}
    ok = (det[..., 2] >= 0.5) & vis
    out = {}
    if bool(ok.any()):
        out["vs_detections"] = float((pix - det[..., :2]).norm(dim=-1)[ok].mean())
    if seq.ground_truth is not None:
        tp, _, tvis = rig.project(seq.ground_truth.positions[1:].to(pix.dtype))
        m = vis & tvis
        if bool(m.any()):
            out["vs_truth"] = float((pix - tp).norm(dim=-1)[m].mean())
    return out


def _energy_vs_truth(tracker, seq, theta) -> float:
    """Fraction of frames whose estimate has a lower energy (the tracker's own likelihood)
    than the true pose: > 0 means the likelihood's optimum is not the truth there."""
    import torch

    from torchmocap.likelihoods import FrameEnergy

    tracking = None if seq.imu is None else seq.imu.tracking.nonzero()[:, 0]
    below = []
    for t in range(1, seq.num_frames):
        frame = tracker.observe(seq.frame(t), tracking)
        energy = FrameEnergy(tracker.likelihood, tracker.likelihood.prepare(frame),
                             tracker.skeleton)
        with torch.no_grad():
            v = energy(torch.stack([seq.ground_truth.theta[t].to(theta.dtype), theta[t]]))
        below.append(bool(v[1] < v[0]))
    return sum(below) / max(len(below), 1)


def _iou(runtime, seq, theta) -> dict:
    """Per-view silhouette IoU of the model capsules against the masks (frames without truth)."""
    from torchmocap.likelihoods import render_capsule_silhouettes, silhouette_iou

    if seq.silhouettes is None or runtime.rig is None:
        return {}
    per = []
    for t in range(seq.num_frames):
        model = render_capsule_silhouettes(runtime.body, runtime.rig, theta[t])
        per.append([float(v) for v in silhouette_iou(model, seq.silhouettes[t])])
    last = per[-1]
    return {"per_view": last, "mean": sum(last) / len(last),
            "mean_over_frames": sum(sum(p) / len(p) for p in per) / len(per)}


def _diagnostics(infos: list) -> dict:
    """Per-run summaries of the per-frame diagnostics (ESS, proposal statistics, energy)."""
    out: dict[str, Any] = {}
    tracked = [i for i in infos[1:] if isinstance(i, dict)]
    ess = [i["ess"][-1] for i in tracked if i.get("ess")]
    if ess:  # the ESS of the weights each frame ends with (an SIR filter's only one)
        out["ess_final_mean"] = out["ess_mean"] = sum(ess) / len(ess)
        out["ess_per_frame"] = [round(float(v), 3) for v in ess]
    props = [i["proposal"] for i in tracked if isinstance(i.get("proposal"), dict)]
    keys = sorted({k for p in props for k, v in p.items()
                   if isinstance(v, (int, float)) and not isinstance(v, bool)})
    if keys:  # proposal statistics (rejections, per-joint tries, fallbacks): per-frame means
        out["proposal_mean"] = {k: sum(float(p.get(k, 0.0)) for p in props) / len(props)
                                for k in keys}
        fell = {k[len("fallback_"):]: sum(1 for p in props if p.get(k)) for k in keys
                if k.startswith("fallback_")}
        if any(fell.values()):
            print("torchmocap-track: warning: the data-driven proposal fell back to its prior "
                  "(no usable data) in frames: "
                  + ", ".join(f"{k} {n}" for k, n in fell.items() if n), file=sys.stderr)
    refine = [i["refine"] for i in tracked if isinstance(i.get("refine"), dict)]
    if refine:  # a refine stage after the annealing: energies before / after, the start kept
        keys = sorted({k for r in refine for k in r})
        out["refine_mean"] = {k: sum(float(r.get(k, 0.0)) for r in refine) / len(refine)
                              for k in keys}
    rates = [i["proposal"]["acceptance_rate"] for i in tracked
             if "acceptance_rate" in i.get("proposal", {})]
    if rates:
        out["acceptance_rate_mean"] = sum(rates) / len(rates)
    energies = [i["energy"] for i in tracked if isinstance(i.get("energy"), dict)]
    if energies:
        out["energy_mean"] = {k: sum(e[k] for e in energies) / len(energies)
                              for k in energies[0]}
    missing: dict[str, int] = {}
    for i in tracked:
        for k in i.get("no_evidence", []):
            missing[k] = missing.get(k, 0) + 1
    out["frames_without_evidence"] = missing
    if missing:
        print("torchmocap-track: warning: frames without usable evidence (uninformative): "
              + ", ".join(f"{k} {n}" for k, n in missing.items()), file=sys.stderr)
    if infos and infos[0].get("seconds") is not None:
        out["seconds_first_frame"] = infos[0]["seconds"]
        if "seconds_per_round" in infos[0]:
            out["seconds_per_round"] = infos[0]["seconds_per_round"]
    if infos and isinstance(infos[0].get("body_fit"), dict):
        # the subject's body fitted at the first frame: silhouette IoU and energy before/after
        # (after the last refit pass, when there were any), fitted scale per segment
        fits = [infos[0]["body_fit"]] + [p["body_fit"] for p in infos[0].get("refit", [])
                                         if isinstance(p.get("body_fit"), dict)]
        out["body_fit"] = {
            "iou_before": _number(fits[0].get("iou_before")),
            "iou_after": _number(fits[-1].get("iou_after")),
            "energy_before": _number(fits[0].get("energy_before")),
            "energy_after": _number(fits[-1].get("energy_after")),
            "scales": {str(k): _number(v) for k, v in dict(fits[-1].get("scales", {})).items()},
            "passes": len(fits)}
        if isinstance(fits[-1].get("total_scales"), dict):  # all passes together
            out["body_fit"]["total_scales"] = {str(k): _number(v)
                                               for k, v in fits[-1]["total_scales"].items()}
        if all("kept" in f for f in fits):  # per pass: False where a fit was undone
            out["body_fit"]["kept"] = [bool(f["kept"]) for f in fits]
        if all(f.get("seconds") is not None for f in fits):  # the fits alone
            out["body_fit"]["seconds"] = _number(sum(f["seconds"] for f in fits))
        if isinstance(fits[-1].get("offsets"), dict):  # capsules moved off their bones (m)
            out["body_fit"]["offsets"] = {str(k): [_number(x) for x in v]
                                          for k, v in fits[-1]["offsets"].items()}
        if isinstance(fits[-1].get("hull"), dict):  # the masks the fit saw (hull-filtered)
            out["body_fit"]["hull"] = {str(k): (_number(v) if isinstance(v, float) else v)
                                       for k, v in fits[-1]["hull"].items()}
    return out


def _number(v):
    """A float for JSON (``None`` for a missing or non-finite value)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _validate_outputs(cfg) -> None:
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
    if glb.get("body", "skinned") not in ("skinned", "stick"):
        raise ValueError(f"glb.body: expected 'skinned' or 'stick', got {glb.get('body')!r}")
    if glb.get("up", "y") not in ("y", "z"):
        raise ValueError(f"glb.up: expected 'y' or 'z', got {glb.get('up')!r}")


def _write_plots(out, seq, runtime, theta, arrays, cfg):
    """``errors.png``, the overlay grids, the video and the GLB (each file atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchmocap.io.atomic import atomic_path

    T = theta.shape[0]
    if "orientation_error_deg" in arrays:
        ori, mp = arrays["orientation_error_deg"], arrays["mpjpe_mm"]
        t_axis = np.arange(1, T) / seq.fps
        fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
        for k, b in enumerate(_validation_bones(seq)):
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
        _write_glb(out / "track.glb", seq, runtime, theta, glb)


def _write_overlays(out, seq, runtime, theta, cfg) -> None:
    """Overlay grids (``overlay_XXXX.png``: every view, the estimate and the truth, a legend) at
    ``overlays`` evenly spaced frames, or of the last frame when there is no ground truth; with
    ``video.enabled`` an animation of the grids over the whole track."""
    import logging

    import numpy as np

    from torchmocap.viz.overlays import track_overlay_frames, write_overlay_grid
    from torchmocap.viz.video import decimation, write_video

    n = int(cfg.get("overlays", 3))
    video = cfg.get("video") or {}
    if runtime.rig is None or (seq.silhouettes is None and seq.images is None):
        if video.get("enabled", False):
            logging.getLogger(__name__).warning("video: the sequence has no camera views; "
                                                "no video written")
        return
    T = int(theta.shape[0])
    kw = dict(rig=runtime.rig, body=runtime.body, scale=float(cfg.get("overlay_scale", 1.0)))
    if n > 0:
        frames = ([T - 1] if seq.ground_truth is None else
                  sorted({int(round(x)) for x in np.linspace(1, T - 1, n)}))
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


def _write_glb(path, seq, runtime, theta, glb) -> None:
    """``track.glb``: the bundled skinned body (``glb.body: skinned``) or a stick figure
    (``stick``) following the estimate, keyframes at the sequence's frame times."""
    from torchmocap.export import write_glb

    mesh = None
    if glb.get("body", "skinned") == "skinned":
        from torchmocap.body import SkinnedBody

        mesh = SkinnedBody()
    write_glb(path, runtime.skeleton, theta, float(seq.fps), body_mesh=mesh,
              up=str(glb.get("up", "y")))


_KNOWN_ERRORS: tuple[type[BaseException], ...] = (ValueError, LookupError, OSError, TypeError)


@hydra.main(config_path="../conf", config_name="track", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    try:
        metrics = run(cfg, out)
    except Exception as e:
        try:
            fp = config_fingerprint(cfg)
        except Exception:
            fp = None
        line = write_failure(out, e, fp, "torchmocap-track")
        if not isinstance(e, _KNOWN_ERRORS) and not multirun:
            raise  # a bug: show the traceback
        print(f"torchmocap-track: error: {line}", file=sys.stderr)
        if multirun:
            return math.nan
        sys.exit(2)
    _print_summary(metrics)
    return float(metrics.get("orientation_error_deg", {}).get("mean", math.nan))


def _print_summary(m: dict) -> None:
    if "orientation_error_deg" not in m:
        print(json.dumps({k: v for k, v in m.items() if k != "clip"}, indent=2))
        return
    o = m["orientation_error_deg"]
    rows = [("tracker", m["tracker"]), ("scenario", m.get("scenario")), ("frames", m["frames"]),
            ("particles x layers", f"{m['num_particles']} x {m['layers']}"),
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
    w = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")


def main() -> None:
    """Console entry point (exit status 2 when the run, or any job of a sweep, failed)."""
    import warnings

    # the repository's conf/ is on the search path only when run from the repository root
    warnings.filterwarnings("ignore", message=r".*provider=hydra\.searchpath in main.*")
    _hydra_main()
    if sweep_failed():
        sys.exit(2)


if __name__ == "__main__":
    main()
