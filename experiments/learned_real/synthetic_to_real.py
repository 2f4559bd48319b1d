"""Synthetic to real: does the image term trained on synthesised clips (the bundled
``term/learned_features``) rank poses on this recording's real views as well as the
hand-crafted silhouette cost?

For each camera, in every 5th frame, the reference pose is the fit to all four cameras'
keypoints (the hand-set keypoint term, frame by frame) — it uses no image; around it 24 poses are
drawn (Gaussian on every DoF, 8 at each of 0.03, 0.08 and 0.2 rad — metres / 4 for the root
translation). Each term scores the 25 poses in that one camera's computed mask and image
(``data.masks=compute`` at half resolution): the hand-crafted silhouette term
(``term/silhouette``), the learned feature term alone, and the combination the bundled weights
were trained for (``2 V_silh + V_learned``, ``likelihood/silhouette_learned``). Scores per term:
how often the reference has the lowest energy, and the mean Spearman correlation between a
pose's energy and its mean joint distance from the reference (1: the energy orders the poses
by their error).

Writes ``results/synthetic_to_real.md`` and ``.json``.

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python experiments/learned_real/synthetic_to_real.py
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
SCALES = (0.03, 0.08, 0.2)
PER_SCALE = 8


def _terms(runtime):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from torchmocap.assembly import build

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        cfg = compose(config_name="track", overrides=["+term@silh=silhouette",
                                                      "+term@learned=learned_features"])
    return build(cfg.silh, runtime, _path="silh"), build(cfg.learned, runtime, _path="learned")


def _spearman(a: torch.Tensor, b: torch.Tensor) -> float:
    ra = a.argsort().argsort().double()
    rb = b.argsort().argsort().double()
    ra, rb = ra - ra.mean(), rb - rb.mean()
    return float((ra * rb).sum() / (ra.norm() * rb.norm()))


def main(argv: list[str] | None = None) -> int:
    from torchmocap.assembly import Runtime
    from torchmocap.data.recordings.loader import load_recording
    from torchmocap.filters.tracking.tracker import start_pose
    from torchmocap.learning.keypoints import stack_detections, track_poses
    from torchmocap.likelihoods import FrameEnergy, LearnedKeypointLikelihood

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", type=Path, default=RECORDING)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--stride", type=int, default=5)
    ap.add_argument("--mask-cache", type=Path, default=Path("outputs/mask_cache"))
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args(argv)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        seq = load_recording(args.recording, scale=args.scale, masks="compute",
                             mask_cache=str(args.mask_cache))
    rt = Runtime.from_sequence(seq)
    sk = rt.skeleton
    theta0 = start_pose(seq).to(sk.offsets.dtype)
    kp = LearnedKeypointLikelihood(seq.rig, sk, seq.joint_names, rt.keypoint_map,
                                   min_confidence=0.1)
    ref = track_poses(kp, sk, stack_detections(kp, seq), theta0, 30)
    g = torch.Generator().manual_seed(0)
    D = sk.num_dofs
    step = torch.ones(D)
    step[:3] = 0.25  # root translation (m) per radian of the rotations
    frames = list(range(0, seq.num_frames, args.stride))
    out = {}
    for c, cam in enumerate(seq.rig.names):
        view = seq.select_cameras([c])
        vrt = Runtime.from_sequence(view, skeleton=sk)
        silh, learned = _terms(vrt)
        res = {k: {"best": 0, "spearman": []} for k in ("silhouette", "learned", "combined")}
        for t in frames:
            noise = torch.cat([s * torch.randn(PER_SCALE, D, generator=g) for s in SCALES])
            poses = torch.cat([ref[t:t + 1], sk.clamp(ref[t] + noise * step)]).to(ref)
            err = (sk(poses).positions - sk(ref[t:t + 1]).positions).norm(dim=-1).mean(-1)
            frame = view.frame(t)
            with torch.no_grad():
                vs = FrameEnergy(silh, silh.prepare(frame), sk)(poses).double()
                vl = FrameEnergy(learned, learned.prepare(frame), sk)(poses).double()
            for k, v in (("silhouette", vs), ("learned", vl), ("combined", 2 * vs + vl)):
                res[k]["best"] += int(int(v.argmin()) == 0)
                res[k]["spearman"].append(_spearman(v, err.double()))
        out[cam] = {k: {"reference_lowest": r["best"] / len(frames),
                        "spearman": sum(r["spearman"]) / len(r["spearman"])}
                    for k, r in res.items()}
        print(cam, out[cam], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "synthetic_to_real.json").write_text(json.dumps(out, indent=1))
    text = ("| camera | term | reference lowest | Spearman (energy vs error) |\n"
            "|---|---|---:|---:|\n")
    for cam, r in out.items():
        for k, v in r.items():
            text += f"| {cam} | {k} | {v['reference_lowest']:.2f} | {v['spearman']:.2f} |\n"
    (args.out / "synthetic_to_real.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
