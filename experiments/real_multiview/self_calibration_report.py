"""Self-calibration on the real recording: every method with the recording's calibration and
with the one refined from the subject on other frames, scored by one protocol.

Two splits: (a) refine on frames 0–59, reconstruct and score 60–99; (b) refine on 40–99,
reconstruct and score 0–39. The refinement (``data.calibration`` of the runs, and here for the
peers: :func:`torchmocap.cameras.bundle_adjust` with the same settings — rotation and
translation, Cauchy 20 px, detections of confidence > 0.3 weighted by confidence, the default
priors, the mean gauge) sees all four cameras on its frames; each camera is then held out in
turn on the scored frames.

* Peers (``peers.py``: weighted DLT, + view dropping, aniposelib triangulate / ransac /
  optim) run on the scored frames with the given and with the refined rig; each is scored
  against the held-out view's detections through the rig it used.
* torchmocap: the runs of ``self_calibration.sh`` (``runs_selfcal/<split>/<given|refined>/
  <preset>/<cam>``), their tracks rescored by the protocol through the rig of the run (the
  refined rig is recomputed here; the runs' own ``heldout`` scores are listed beside).
* The model objective (``data.calibration.objective=model``): its refined rig scored by the
  weighted DLT like the bundle adjustment's (calibration quality alone).

Writes ``results/self_calibration.md`` (tables), ``results/self_calibration.json`` (every
number) and ``results/self_calibration.png`` (mean held-out median per method, given vs
refined, both splits). Command (from the repository root, after ``self_calibration.sh``)::

    OMP_NUM_THREADS=1 python experiments/real_multiview/self_calibration_report.py
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from peers import PEERS, _aniposelib, dlt, machine, run_peer  # noqa: E402
from protocol import KEYPOINTS, load_detections  # noqa: E402
from report import RunError, read_run  # noqa: E402

from torchmocap.cameras import bundle_adjust  # noqa: E402
from torchmocap.evaluation import leave_one_camera_out  # noqa: E402

RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
RESULTS = HERE / "results"
RUNS = HERE / "runs_selfcal"
#: split -> (refined frames, scored frames)
SPLITS = {"a": ((0, 60), (60, 100)), "b": ((40, 100), (0, 40))}
GROUPS = ("rotation", "translation")
PRESETS = ("real_local", "real_mixture", "real_keypoints", "real_sir")
CALIBS = ("given", "refined")


def refined_rig(det, frames: tuple[int, int]):
    res = bundle_adjust(det.points, det.rig, groups=GROUPS, frames=frames, fps=det.fps)
    return res.rig.double(), res


def model_rig(det, frames: tuple[int, int], bundle) -> tuple:
    """The model objective's rig (the loader's code path)."""
    from torchmocap.data.recordings.self_calibration import calibration_settings, refine_rig

    s = calibration_settings({"refine": True, "objective": "model", "frames": list(frames),
                              "progress": False})
    t0 = time.perf_counter()
    rig, rec = refine_rig(det.points[frames[0]:frames[1]], det.rig, list(KEYPOINTS),
                          "body_25b", s, det.fps, range(*frames))
    return rig.double(), rec, time.perf_counter() - t0


def dlt_medians(det, rig) -> list[float]:
    scores = leave_one_camera_out(det.points, rig, 0.3, triangulate=dlt)
    return [float(s.median_px) for s in scores]


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


def summary(rows: dict) -> dict:
    """Mean over the held-out cameras of a method's rows."""
    cams = sorted(rows)
    return {"median_px": _mean([rows[c]["median_px"] for c in cams]),
            "per_camera": {c: rows[c]["median_px"] for c in cams},
            "pck_05": _mean([rows[c]["pck_05"] for c in cams]),
            "pck_10": _mean([rows[c]["pck_10"] for c in cams]),
            "missing_percent": _mean([100 * rows[c]["missing"] /
                                      max(1, rows[c]["compared"] + rows[c]["missing"])
                                      for c in cams]),
            "bone_cv_percent": _mean([rows[c]["bone_cv_mean"] for c in cams]),
            "jitter": _mean([rows[c]["jitter"] for c in cams]),
            "seconds_per_frame": _mean([rows[c].get("seconds_per_frame") for c in cams]),
            "cameras": cams}


def run_split(split: str, runs: Path, log=print) -> dict:
    refine, scored = SPLITS[split]
    full = load_detections(RECORDING)
    t0 = time.perf_counter()
    rig_ref, res = refined_rig(full, refine)
    seconds = time.perf_counter() - t0
    given = load_detections(RECORDING, *scored)
    dets = {"given": given, "refined": dataclasses.replace(given, rig=rig_ref)}
    out: dict = {"refined_frames": list(refine), "scored_frames": list(scored),
                 "refinement_seconds": round(seconds, 2), "refinement": res.report(),
                 "methods": {}}
    anipose = _aniposelib()
    for peer in PEERS:
        if peer.needs_aniposelib and anipose is None:
            out.setdefault("skipped", []).append(peer.key)
            continue
        for calib in CALIBS:
            log(f"{split}: {peer.key} {calib}")
            rows = run_peer(peer, dets[calib])
            out["methods"][f"{peer.key}/{calib}"] = {"label": peer.label, "calibration": calib,
                                                     "summary": summary(rows), "rows": rows}
    for preset in PRESETS:
        for calib in CALIBS:
            rows, reported, missing = {}, {}, []
            for cam in given.cameras:
                run = runs / split / calib / preset / cam
                try:
                    r = read_run(run, dets[calib])
                except RunError as e:
                    missing.append(f"{cam}: {e}")
                    continue
                rows[cam] = r["row"]
                reported[cam] = r["reported"]["heldout"]["median_px"]
            if not rows:
                continue
            out["methods"][f"torchmocap_{preset}/{calib}"] = {
                "label": f"torchmocap `{preset}`", "calibration": calib,
                "summary": summary(rows), "rows": rows, "reported_median_px": reported,
                "missing_runs": missing}
    # the model objective: the calibration alone, scored by the weighted DLT
    rig_model, rec, sec = model_rig(full, refine, res)
    out["calibration_by_dlt"] = {
        "given": dlt_medians(given, given.rig), "bundle": dlt_medians(given, rig_ref),
        "model": dlt_medians(given, rig_model), "model_seconds": round(sec, 2),
        "model_report": rec["report"]}
    return out


def _f(x, fmt=".1f"):
    return "–" if x is None else format(x, fmt)


def markdown(result: dict) -> str:
    lines = ["# pose2sim_balancing — self-calibration: every method with the given and the "
             "refined calibration", "",
             "Command: `experiments/real_multiview/self_calibration.sh` (the torchmocap runs), "
             "then `OMP_NUM_THREADS=1 python experiments/real_multiview/"
             "self_calibration_report.py`.", "",
             "Refined: rotation and translation of every camera (bundle adjustment from the "
             "subject's detections on the refined frames, all four cameras; Cauchy 20 px, "
             "confidence > 0.3, default priors, mean gauge). Scored: each camera held out in "
             "turn on the other frames, the method reconstructing from the other three views; "
             "median px of its detections of confidence > 0.3 (full-resolution pixels), each "
             "method through the rig it used. torchmocap: seed 0, `data.scale=0.5`.", ""]
    for split, r in result["splits"].items():
        a, b = r["refined_frames"], r["scored_frames"]
        lines += [f"## Split {split}: refined on {a[0]}–{a[1] - 1}, scored on {b[0]}–{b[1] - 1}",
                  "", "| method | calibration | median px | cam01 | cam02 | cam03 | cam04 | "
                  "PCK@5 % | missing % | bone CV % | jitter m/s² | s/frame |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        order = sorted(r["methods"].items(), key=lambda kv: (
            not kv[0].startswith("torchmocap"), kv[0].split("/")[0], kv[1]["calibration"]))
        for _, m in order:
            s = m["summary"]
            cams = [s["per_camera"].get(c) for c in ("cam01", "cam02", "cam03", "cam04")]
            pck = None if s["pck_05"] is None else 100 * s["pck_05"]
            lines.append(
                f"| {m['label']} | {m['calibration']} | **{_f(s['median_px'])}** | " +
                " | ".join(_f(c) for c in cams) +
                f" | {_f(pck)} | {_f(s['missing_percent'])} | {_f(s['bone_cv_percent'], '.2f')}"
                f" | {_f(s['jitter'])} | {_f(s['seconds_per_frame'], '.3g')} |")
        c = r["calibration_by_dlt"]
        lines += ["", "Calibration quality alone (weighted DLT held-out median px, "
                  "cam01..04, mean): " + "; ".join(
                      f"{k} {', '.join(_f(v) for v in c[k])} (**{_f(sum(c[k]) / 4)}**)"
                      for k in ("given", "bundle", "model")) +
                  f". Bundle adjustment {r['refinement_seconds']:.1f} s, model objective "
                  f"{c['model_seconds']:.1f} s.", ""]
        reported = {k: m.get("reported_median_px") for k, m in r["methods"].items()
                    if m.get("reported_median_px")}
        if reported:
            lines.append("The runs' own held-out medians (metrics.json, their refined rig): " +
                         "; ".join(f"{k} " + ", ".join(_f(v) for v in d.values())
                                   for k, d in reported.items()) + ".")
            lines.append("")
    return "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(result["splits"]), figsize=(12, 4.5), sharey=True,
                             squeeze=False)
    for ax, r in zip(axes[0], result["splits"].values()):
        names = sorted({k.split("/")[0] for k in r["methods"]})
        x = range(len(names))
        for i, calib in enumerate(CALIBS):
            vals = [r["methods"].get(f"{n}/{calib}", {}).get("summary", {}).get("median_px")
                    for n in names]
            ax.bar([j + 0.4 * i - 0.2 for j in x], [v or 0 for v in vals], width=0.4,
                   label=calib)
        ax.axhline(13.0, color="k", lw=0.8, ls="--")
        ax.set_xticks(list(x))
        ax.set_xticklabels([n.replace("torchmocap_", "") for n in names], rotation=40,
                           ha="right", fontsize=8)
        a, b = r["refined_frames"], r["scored_frames"]
        ax.set_title(f"refined {a[0]}–{a[1] - 1}, scored {b[0]}–{b[1] - 1}")
        ax.set_ylabel("held-out median px (mean of 4 cameras)")
        ax.legend()
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    from torchmocap.atomic import write_json_atomic, write_text_atomic

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=Path, default=RUNS)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--splits", default="a,b")
    args = ap.parse_args(argv)
    result = {"machine": machine(), "splits": {}}
    for split in args.splits.split(","):
        result["splits"][split] = run_split(split, args.runs)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(result, args.out / "self_calibration.json")
    write_text_atomic(args.out / "self_calibration.md", markdown(result))
    plot(result, args.out / "self_calibration.png")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
