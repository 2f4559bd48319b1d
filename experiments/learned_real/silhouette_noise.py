"""The mask noise model learned on the training views, scored on the held-out view's masks.

For each camera in turn: every frame is fitted to the other three cameras' keypoints (the
hand-set keypoint term, frame by frame — no mask used); the noise model
(:class:`torchmocap.likelihoods.SilhouetteNoiseLikelihood`: per view a false-positive rate, a
false-negative rate and a boundary width) is fitted to the three views' computed masks on
every 10th of the training frames (0–59) under those poses; then the held-out camera's masks on
every 5th test frame (60–99) are scored (negative log-likelihood per pixel, the track's poses)
with the hand-set model (rates 0.05, width 1 px) and with the learned one (the training views'
parameters averaged: the held-out camera's own rates are unknown). Also: each training view's
learned rates.

Writes ``results/silhouette_noise.md`` and ``.json``.

Usage (from the repository root; the masks are computed once and cached)::

    OMP_NUM_THREADS=1 python experiments/learned_real/silhouette_noise.py
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"


def main(argv: list[str] | None = None) -> int:
    from torchmocap.assembly import Runtime
    from torchmocap.data import split_heldout
    from torchmocap.data.recordings.loader import load_recording
    from torchmocap.filters.tracking.tracker import start_pose
    from torchmocap.learning.keypoints import stack_detections, track_poses
    from torchmocap.likelihoods import (
        LearnedKeypointLikelihood,
        Poses,
        SilhouetteNoiseLikelihood,
        fit_noise_model,
    )

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", type=Path, default=RECORDING)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--stride", type=int, default=8, help="pixel stride of the scored grid")
    ap.add_argument("--train-frames", type=int, default=60)
    ap.add_argument("--mask-cache", type=Path, default=Path("outputs/mask_cache"))
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    out = {}
    for cam in ("cam01", "cam02", "cam03", "cam04"):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*codec's crop")
            seq = load_recording(args.recording, scale=args.scale, masks="compute",
                                 mask_cache=str(args.mask_cache), heldout_camera=cam)
        tracked, held = split_heldout(seq)
        rt = Runtime.from_sequence(tracked)
        sk = rt.skeleton
        theta0 = start_pose(tracked).to(sk.offsets.dtype)
        kp = LearnedKeypointLikelihood(tracked.rig, sk, tracked.joint_names, rt.keypoint_map,
                                       min_confidence=0.1)
        theta = track_poses(kp, sk, stack_detections(kp, tracked), theta0, 30)
        train = list(range(0, min(args.train_frames, seq.num_frames), 10))
        test = list(range(args.train_frames, seq.num_frames, 5))
        model = SilhouetteNoiseLikelihood(rt.body, tracked.rig, stride=args.stride)
        train_nll = fit_noise_model(model, sk, [tracked.frame(t) for t in train],
                                    theta[train])
        fp, fn, width = model.rates()
        mean = model.mean_parameters()
        scores = {}
        for name, kw in (("hand_set", {}), ("learned", mean)):
            h = SilhouetteNoiseLikelihood(rt.body, held.rig, stride=args.stride, **kw)
            with torch.no_grad():
                nll = [float(h.energy(Poses(theta[t:t + 1], sk), h.prepare(held.frame(t))))
                       for t in test]
                pixels = sum(int(h.prepare(held.frame(t))["masks"][0].numel()) for t in test)
            scores[name] = sum(nll) / pixels
        out[cam] = {"train_nll_per_pixel": train_nll, "heldout_nll_per_pixel": scores,
                    "learned": {n: {"false_positive": round(float(a), 4),
                                    "false_negative": round(float(b), 4),
                                    "width_px": round(float(w), 2)}
                                for n, a, b, w in zip(tracked.rig.names, fp, fn, width)},
                    "heldout_parameters": mean}
        print(cam, scores, out[cam]["learned"], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "silhouette_noise.json").write_text(json.dumps(out, indent=1))
    text = ("| held out | NLL/pixel hand-set | NLL/pixel learned | learned rates of the training "
            "views: false positive / false negative / width px |\n|---|---:|---:|---|\n")
    for cam, r in out.items():
        rates = "; ".join(f"{n} {v['false_positive']:.3f} / {v['false_negative']:.3f} / "
                          f"{v['width_px']:.1f}" for n, v in r["learned"].items())
        text += (f"| {cam} | {r['heldout_nll_per_pixel']['hand_set']:.4f} | "
                 f"{r['heldout_nll_per_pixel']['learned']:.4f} | {rates} |\n")
    (args.out / "silhouette_noise.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
