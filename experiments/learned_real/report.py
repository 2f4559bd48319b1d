"""The tables and plots of the experiment: the hand-set and the learned keypoint likelihood on
pose2sim_balancing, each camera held out in turn, scored on the frames not trained on.

Inputs (folders of run directories named by the held-out camera, ``cam01`` ... ``cam04``):

* ``--train``: ``torchmocap-train --config-name train_keypoints`` runs (``summary.json``: the
  training's seconds and history, the learned parameters, the frame-by-frame fits' scores);
* ``--hand`` and ``--learned``: ``torchmocap-track`` runs of the same preset with the hand-set
  term and with ``term@tracker.likelihood.terms.keypoints=keypoints_learned`` and that
  camera's weights (``metrics.json``, ``track.npz``, ``tracked.bvh``);
* ``--shipped``: the weights file trained on all four cameras (the offsets table and plot).

Every track is scored by the protocol of ``experiments/real_multiview`` (``protocol.py``: the
held-out view's detections of confidence > 0.3, full-resolution pixels, PCK at 5 % / 10 % of
the box height, bone-length CV and jitter of the limb keypoints) on the test frames only
(``--test-start`` on), with the keypoints of the run's own keypoint map (the hand-set run: the
subject's fitted map; the learned run: the learned offsets — ``metrics.json``'s
``heldout.keypoint_mapping``).

Writes ``results/table.md``, ``results/offsets.md``, ``results/summary.json``,
``results/heldout_error.png`` (median error per frame over time in each held-out view),
``results/offsets.png`` (the keypoints on the skeleton, hand-set and learned) and
``results/calibration.png`` (the learned confidence calibrations).

Usage (from the repository root)::

    python experiments/learned_real/report.py --train experiments/learned_real/runs/train \\
        --hand experiments/learned_real/runs/hand --learned experiments/learned_real/runs/learned
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
PEERS = HERE.parent / "real_multiview"
if str(PEERS) not in sys.path:
    sys.path.insert(0, str(PEERS))

from protocol import KEYPOINTS, heldout_scores, load_detections, score_row  # noqa: E402


def _peers_report():
    """``experiments/real_multiview/report.py`` (its run reader), imported by path."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("real_multiview_report", PEERS / "report.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod

RESULTS = HERE / "results"
RUNS = HERE / "runs"
RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
CAMERAS = ("cam01", "cam02", "cam03", "cam04")
SHIPPED = HERE.parents[1] / "torchmocap" / "assets" / "learned" / \
    "keypoints_pose2sim_balancing.pt"

#: the anatomical point each BODY_25B keypoint marks (the map's template,
#: torchmocap/conf/keypoint_map/body_25b.yaml)
ANATOMY = {
    "Nose": "nose tip (pronasale)", "LEye": "left pupil", "REye": "right pupil",
    "LEar": "left tragion", "REar": "right tragion",
    "LShoulder": "left acromion", "RShoulder": "right acromion",
    "LElbow": "left elbow centre (epicondyles)", "RElbow": "right elbow centre (epicondyles)",
    "LWrist": "left wrist centre (styloids)", "RWrist": "right wrist centre (styloids)",
    "LHip": "left greater trochanter region", "RHip": "right greater trochanter region",
    "LKnee": "left knee centre (femoral epicondyles)",
    "RKnee": "right knee centre (femoral epicondyles)",
    "LAnkle": "left ankle centre (malleoli)", "RAnkle": "right ankle centre (malleoli)",
    "Neck": "upper neck (MPII)", "Head": "head top (MPII)",
    "LBigToe": "left big toe tip", "LSmallToe": "left small toe",
    "LHeel": "left heel (calcaneus)", "RBigToe": "right big toe tip",
    "RSmallToe": "right small toe", "RHeel": "right heel (calcaneus)",
}


def _load_json(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (run the commands of the README first)")
    return json.loads(path.read_text())


def run_keypoints(run: Path) -> torch.Tensor:
    """``(T, 25, 3)`` BODY_25B keypoints of a track with the run's own keypoint map."""
    metrics = _load_json(run / "metrics.json")
    mapping = metrics["heldout"]["keypoint_mapping"]
    return _peers_report().track_keypoints(run, {"format": "body_25b",
                                                 "keypoints": list(KEYPOINTS), "map": mapping})


def score_run(run: Path, det, camera: int, test_start: int) -> dict:
    """The protocol's scores of a track on its test frames, with the run's seconds per frame."""
    X = run_keypoints(run)
    test = dataclasses.replace(det, points=det.points[test_start:],
                               frames=det.frames[test_start:])
    row = score_row(heldout_scores(X[test_start:], test, camera), X[test_start:], det.fps)
    full = score_row(heldout_scores(X, det, camera), X, det.fps)
    row["frame_median_px_all"] = full["frame_median_px"]
    row["seconds_per_frame"] = _load_json(run / "metrics.json")["seconds_per_frame"]
    return row


def _pct(a: float, b: float) -> str:
    return f"{100.0 * (b - a) / a:+.1f} %"


def table(rows: dict, train: dict) -> str:
    keys = (("median_px", ".1f"), ("mean_px", ".1f"), ("pck_05", ".3f"), ("pck_10", ".3f"),
            ("bone_cv_mean", ".2f"), ("jitter", ".1f"), ("seconds_per_frame", ".3f"))
    head = ("| held out | term | median px | mean px | PCK@5 % | PCK@10 % | bone CV % | "
            "jitter m/s² | s/frame |\n|---|---|---:|---:|---:|---:|---:|---:|---:|\n")
    out = head
    for cam in rows:
        for term in ("hand", "learned"):
            r = rows[cam][term]
            out += f"| {cam} | {term} | " + " | ".join(format(r[k], f) for k, f in keys) + " |\n"
    mean = {t: {k: float(np.mean([rows[c][t][k] for c in rows])) for k, _ in keys}
            for t in ("hand", "learned")}
    for t in ("hand", "learned"):
        out += f"| **mean** | {t} | " + " | ".join(format(mean[t][k], f) for k, f in keys) \
            + " |\n"
    out += ("\nChange of the mean (learned vs hand-set): median "
            f"{_pct(mean['hand']['median_px'], mean['learned']['median_px'])}, mean "
            f"{_pct(mean['hand']['mean_px'], mean['learned']['mean_px'])}, time per frame × "
            f"{mean['learned']['seconds_per_frame'] / mean['hand']['seconds_per_frame']:.2f}.\n")
    out += ("\nTraining (first frames of the three other cameras): seconds "
            + ", ".join(f"{c} {train[c]['seconds_training']:.0f}" for c in train)
            + "; frame-by-frame fits of every frame with each term, scored in the held-out view "
              "on the test frames (the training command's own cross-validation, no tracker): "
            + "; ".join(f"{c} {train[c]['scores']['hand_set']['test']['median_px']:.1f} → "
                        f"{train[c]['scores']['learned']['test']['median_px']:.1f} px"
                        for c in train) + ".\n")
    return out, mean


def offsets_table(shipped: dict, train: dict) -> str:
    p = shipped["parameters"]["keypoints"]
    out = ("| keypoint | anatomical point | bone frame | hand-set offset (cm) | learned offset "
           "(cm) | change (cm) | |change| cm, per held-out run |\n"
           "|---|---|---|---|---|---|---|\n")
    for n, k in p.items():
        hand = [o - d for o, d in zip(k["offset_cm"], k["change_cm"])]
        per = " / ".join(f"{train[c]['parameters']['keypoints'][n]['change_norm_cm']:.1f}"
                         for c in train)
        out += (f"| {n} | {ANATOMY.get(n, '')} | {k['frame']} | "
                f"{', '.join(f'{v:.1f}' for v in hand)} | "
                f"{', '.join(f'{v:.1f}' for v in k['offset_cm'])} | "
                f"{', '.join(f'{v:+.1f}' for v in k['change_cm'])} | {per} |\n")
    return out


def plot_heldout(rows: dict, test_start: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 1, figsize=(8, 2.2 * len(rows)), sharex=True)
    for ax, cam in zip(np.atleast_1d(axes), rows):
        for term, colour in (("hand", "tab:grey"), ("learned", "tab:blue")):
            y = np.array([np.nan if v is None else v
                          for v in rows[cam][term]["frame_median_px_all"]])
            ax.plot(y, color=colour, label=f"{term}")
        ax.axvline(test_start - 0.5, color="k", lw=0.8, ls="--")
        ax.set_ylabel(f"{cam} held out\nmedian px")
        ax.legend(loc="upper right", fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel(f"frame (training frames < {test_start})")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_offsets(path: Path, shipped_weights: Path) -> None:
    """human31 at its zero pose, front and side, with the BODY_25B keypoints of the hand-set
    map and with the shipped learned changes (arrows)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchmocap.likelihoods.learned import read_weights
    from torchmocap.skeleton import human31, keypoint_positions, load_keypoint_map

    sk = human31().double()
    kin = sk(sk.zero_pose((1,)).double())
    kmap = load_keypoint_map("body_25b", sk)
    delta = read_weights(shipped_weights)["state_dict"]["offset_delta"].double()
    a = keypoint_positions(kin.positions, kin.rotations, kmap)[0]
    b = keypoint_positions(kin.positions, kin.rotations, kmap, kmap.offsets + delta)[0]
    P = kin.positions[0]
    fig, axes = plt.subplots(1, 2, figsize=(9, 8))
    for ax, (i, name) in zip(axes, ((0, "front (x: subject's left)"),
                                    (1, "side (y: backwards)"))):
        for j, p in enumerate(sk.parents):
            if p >= 0:
                ax.plot([P[p, i], P[j, i]], [P[p, 2], P[j, 2]], color="0.6", lw=2)
        ax.scatter(a[:, i], a[:, 2], s=14, color="tab:grey", label="hand-set map", zorder=3)
        ax.scatter(b[:, i], b[:, 2], s=14, color="tab:red", label="learned", zorder=4)
        for k in range(a.shape[0]):
            ax.annotate("", xy=(float(b[k, i]), float(b[k, 2])),
                        xytext=(float(a[k, i]), float(a[k, 2])),
                        arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 0.8})
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xlabel("m")
    axes[0].legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_calibration(train: dict, shipped: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot([0, 1], [0, 1], color="0.6", ls="--", label="hand-set (the confidence)")
    for c, s in train.items():
        cal = s["parameters"]["calibration"]
        ax.plot(cal["confidence"], cal["weight"], label=f"{c} held out")
    cal = shipped["parameters"]["calibration"]
    ax.plot(cal["confidence"], cal["weight"], color="k", lw=2, label="all cameras (shipped)")
    ax.set_xlabel("detector confidence")
    ax.set_ylabel("learned weight g(c)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train", type=Path, default=RUNS / "train")
    ap.add_argument("--hand", type=Path, default=RUNS / "hand")
    ap.add_argument("--learned", type=Path, default=RUNS / "learned")
    ap.add_argument("--shipped", type=Path, default=RUNS / "shipped")
    ap.add_argument("--recording", type=Path, default=RECORDING)
    ap.add_argument("--test-start", type=int, default=60)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    det = load_detections(args.recording)
    rows, train = {}, {}
    for cam in CAMERAS:
        c = det.camera_index(cam)
        train[cam] = _load_json(args.train / cam / "summary.json")
        rows[cam] = {t: score_run(d / cam, det, c, args.test_start)
                     for t, d in (("hand", args.hand), ("learned", args.learned))}
    shipped = _load_json(args.shipped / "summary.json")
    args.out.mkdir(parents=True, exist_ok=True)
    text, mean = table(rows, train)
    (args.out / "table.md").write_text(text)
    (args.out / "offsets.md").write_text(offsets_table(shipped, train))
    summary = {"test_start": args.test_start, "mean": mean,
               "rows": {c: {t: {k: v for k, v in r.items() if not k.startswith("frame_")}
                            for t, r in rows[c].items()} for c in rows},
               "training": {c: {k: train[c][k] for k in ("seconds_training", "scores",
                                                          "history")} for c in train}}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    plot_heldout(rows, args.test_start, args.out / "heldout_error.png")
    plot_offsets(args.out / "offsets.png", args.shipped / "keypoints.pt")
    plot_calibration(train, shipped, args.out / "calibration.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
