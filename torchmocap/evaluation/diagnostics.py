"""Per-run summaries of a track's per-frame diagnostics (:class:`~torchmocap.filters.FrameInfo`):
ESS, proposal and refinement statistics, energies, frames without evidence, the first frame's
body fit, a smoother's report, and the hypotheses of multi-hypothesis inferences as arrays.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

from torchmocap.evaluation.warnings import EvaluationWarning

__all__ = ["hypothesis_arrays", "smoother_report", "summarize_diagnostics"]


def _number(v) -> float | None:
    """A float for JSON (``None`` for a missing or non-finite value)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def summarize_diagnostics(infos: list) -> dict[str, Any]:
    """Per-run summaries of the per-frame diagnostics ``infos`` (``Track.infos``).

    Returns a JSON-ready dict: ``ess_mean`` / ``ess_final_mean`` and ``ess_per_frame`` (the
    ESS each frame ends with), ``proposal_mean`` (per-frame means of the proposal's
    statistics), ``refine_mean``, ``acceptance_rate_mean``, ``energy_mean`` (per term),
    ``frames_without_evidence`` (per term), ``seconds_first_frame`` (and ``seconds_per_round``)
    and ``body_fit`` (IoU and energy before/after, scales of the last pass and over all passes,
    passes kept, seconds, offsets, hull statistics). Warns (:class:`EvaluationWarning`) about
    frames without evidence and data-driven proposals that fell back to their prior.
    """
    out: dict[str, Any] = {}
    tracked = infos[1:]
    ess = [i.ess[-1] for i in tracked if i.ess]
    if ess:  # the ESS of the weights each frame ends with (an SIR filter's only one)
        out["ess_final_mean"] = out["ess_mean"] = sum(ess) / len(ess)
        out["ess_per_frame"] = [round(float(v), 3) for v in ess]
    props = [i.proposal for i in tracked if isinstance(i.proposal, dict)]
    keys = sorted({k for p in props for k, v in p.items()
                   if isinstance(v, (int, float)) and not isinstance(v, bool)})
    if keys:  # proposal statistics (rejections, per-joint tries, fallbacks): per-frame means
        out["proposal_mean"] = {k: sum(float(p.get(k, 0.0)) for p in props) / len(props)
                                for k in keys}
        fell = {k[len("fallback_"):]: sum(1 for p in props if p.get(k)) for k in keys
                if k.startswith("fallback_")}
        if any(fell.values()):
            warnings.warn("the data-driven proposal fell back to its prior (no usable data) in "
                          "frames: " + ", ".join(f"{k} {n}" for k, n in fell.items() if n),
                          EvaluationWarning, stacklevel=2)
    refine = [i.refine for i in tracked if isinstance(i.refine, dict)]
    if refine:  # a refine stage after the annealing: energies before / after, the start kept
        keys = sorted({k for r in refine for k in r})
        out["refine_mean"] = {k: sum(float(r.get(k, 0.0)) for r in refine) / len(refine)
                              for k in keys}
    rates = [i.proposal["acceptance_rate"] for i in tracked
             if "acceptance_rate" in (i.proposal or {})]
    if rates:
        out["acceptance_rate_mean"] = sum(rates) / len(rates)
    energies = [i.energy for i in tracked if i.energy]
    if energies:
        out["energy_mean"] = {k: sum(e[k] for e in energies) / len(energies)
                              for k in energies[0]}
    missing: dict[str, int] = {}
    for i in tracked:
        for k in i.no_evidence:
            missing[k] = missing.get(k, 0) + 1
    out["frames_without_evidence"] = missing
    if missing:
        warnings.warn("frames without usable evidence (uninformative): "
                      + ", ".join(f"{k} {n}" for k, n in missing.items()), EvaluationWarning,
                      stacklevel=2)
    if infos and infos[0].seconds is not None:
        out["seconds_first_frame"] = infos[0].seconds
        if "seconds_per_round" in infos[0].inference:
            out["seconds_per_round"] = infos[0].inference["seconds_per_round"]
    if infos and isinstance(infos[0].body_fit, dict):
        out["body_fit"] = _body_fit_summary(infos[0])
    return out


def _body_fit_summary(first) -> dict[str, Any]:
    """The subject's body fitted at the first frame: silhouette IoU and energy before/after
    (after the last refit pass, when there were any), fitted scale per segment."""
    fits = [first.body_fit] + [p["body_fit"] for p in (first.refit or [])
                               if isinstance(p.get("body_fit"), dict)]
    out = {
        "iou_before": _number(fits[0].get("iou_before")),
        "iou_after": _number(fits[-1].get("iou_after")),
        "energy_before": _number(fits[0].get("energy_before")),
        "energy_after": _number(fits[-1].get("energy_after")),
        "scales": {str(k): _number(v) for k, v in dict(fits[-1].get("scales", {})).items()},
        "passes": len(fits)}
    if isinstance(fits[-1].get("total_scales"), dict):  # all passes together
        out["total_scales"] = {str(k): _number(v) for k, v in fits[-1]["total_scales"].items()}
    if all("kept" in f for f in fits):  # per pass: False where a fit was undone
        out["kept"] = [bool(f["kept"]) for f in fits]
    if all(f.get("seconds") is not None for f in fits):  # the fits alone
        out["seconds"] = _number(sum(f["seconds"] for f in fits))
    if isinstance(fits[-1].get("offsets"), dict):  # capsules moved off their bones (m)
        out["offsets"] = {str(k): [_number(x) for x in v]
                          for k, v in fits[-1]["offsets"].items()}
    for k in ("phenotype", "phenotype_joints", "girths"):  # the Anny shape fitted
        if isinstance(fits[-1].get(k), dict):
            out[k] = {str(n): _number(v) for n, v in fits[-1][k].items()}
    if fits[-1].get("height") is not None:  # its standing height (m)
        out["height"] = _number(fits[-1]["height"])
    if isinstance(fits[-1].get("hull"), dict):  # the masks the fit saw (hull-filtered)
        out["hull"] = {str(k): (_number(v) if isinstance(v, float) else v)
                       for k, v in fits[-1]["hull"].items()}
    return out


def smoother_report(report: dict) -> dict:
    """A smoother's report (``Track.smoother``) for JSON: without the per-frame mode indices
    (kept in ``track.npz``'s hypotheses) and a chain stage's output track (``theta``; its
    errors are reported instead), also inside the stages of a chain."""
    out = {k: v for k, v in report.items() if k not in ("modes", "theta")}
    if isinstance(out.get("stages"), list):
        out["stages"] = [smoother_report(r) if isinstance(r, dict) else r
                         for r in out["stages"]]
    return out


def hypothesis_arrays(infos: list, num_dofs: int) -> dict:
    """What a multi-hypothesis inference kept per frame, as arrays for ``track.npz``:
    ``hypotheses (T, K, D)`` (the modes, radians / metres), ``hypothesis_weights (T, K)`` and
    ``hypothesis_energy (T, K)`` (each mode's likelihood energy), ``K`` the most modes of any
    frame; frames with fewer modes (and frame 0, the given start) are padded with NaN. Empty
    when no frame keeps hypotheses."""
    import numpy as np

    rows = [i.hypotheses for i in infos]
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
            raise ValueError(f"infos[{t}].hypotheses: expected (K, {num_dofs}), got {H.shape}")
        hyp[t, : len(H)] = H
        for v, arr in ((info.hypothesis_weights, w), (info.mode_energy, e)):
            if v is not None and len(v) == len(H):
                arr[t, : len(H)] = np.asarray(v, dtype=np.float32)
    return {"hypotheses": hyp, "hypothesis_weights": w, "hypothesis_energy": e}
