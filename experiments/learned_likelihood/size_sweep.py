"""Model-size sweep: candidate-set metrics on the validation clips (HDM05 bk) and energy cost.

    torchmocap-train -m training_set=mocap term.hidden=4,8,16 epochs=6 progress=false \
        hydra.sweep.dir=outputs/train/size_sweep 'hydra.sweep.subdir=h${term.hidden}'
    python experiments/learned_likelihood/size_sweep.py outputs/train/size_sweep/h*/weights.pt

For every weights file: parameters; on the validation frames (truth + 32 negatives each) the
Spearman correlation of energy and pose error over the negatives, and the error of the
ESS-0.5 weighted mean of the negatives (what one annealing layer's estimate does with the
energy); the hand-crafted base (2 V_silh) alone for reference; and the learned term's time for
200 particles on one frame. Writes ``size_sweep.md`` beside this file.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent


def main(files: list[str]) -> None:
    from omegaconf import OmegaConf

    from torchmocap.assembly import build_tracker, tracker_config
    from torchmocap.filters.optim.schedules import ess_target_beta
    from torchmocap.learning import NegativeSettings, load_clip_set, pose_errors
    from torchmocap.likelihoods import LearnedFeatureLikelihood, Poses
    from torchmocap.likelihoods.learned import read_weights

    conf = Path(__import__("torchmocap").__file__).parent / "conf"
    cfg = OmegaConf.load(conf / "train.yaml")
    clips = OmegaConf.load(conf / "training_set" / "mocap.yaml")
    n = OmegaConf.to_container(cfg.data.negatives)
    n["scales"] = tuple(n["scales"])
    n["overrides"] = tuple(n.get("overrides") or ())
    val = load_clip_set(OmegaConf.to_container(clips.val_clips), ["outdoor"], [0],
                        NegativeSettings(**n), "outputs/train_cache", progress=False)

    def rank(a):
        return a.argsort().argsort().float()

    rows = []
    for w in ["<base>", *files]:
        sp, werr, secs, params = [], [], [], 0
        for c in val:
            rt = c.runtime
            base = build_tracker(tracker_config("p", [
                "likelihood@tracker.likelihood=silhouette"]), rt).likelihood
            term = None
            if w != "<base>":
                conf = read_weights(w)["config"]
                conf = {k: v for k, v in conf.items() if k != "num_capsules"}
                term = LearnedFeatureLikelihood(rt.body, rt.rig, weights=w, **conf)
                params = sum(p.numel() for p in term.net.parameters())
            for f in c.frames:
                x = f.negatives
                with torch.no_grad():
                    err = pose_errors(rt.skeleton, x, f.truth)
                    e = base.energy(Poses(x, rt.skeleton), base.prepare(f.frame))
                    if term is not None:
                        obs = term.prepare(f.frame)
                        e = e + term.energy(Poses(x, rt.skeleton), obs)
                sp.append(float(torch.corrcoef(torch.stack([rank(e), rank(err)]))[0, 1]))
                beta = ess_target_beta(e.double(), 0.5).beta.float()
                wt = torch.softmax(-beta * e, 0)
                est = (wt[:, None] * x).sum(0)
                werr.append(1000 * float(pose_errors(rt.skeleton, est[None], f.truth)[0]))
            if term is not None and not secs:
                f = c.frames[0]
                xx = f.truth[None] + 0.05 * torch.randn(200, f.truth.shape[0],
                                                        generator=torch.Generator().manual_seed(0))
                obs = term.prepare(f.frame)
                with torch.no_grad():
                    for _ in range(5):
                        p = Poses(xx, rt.skeleton)
                        p.endpoints(rt.body)
                        t0 = time.perf_counter()
                        term.energy(p, obs)
                        secs.append(time.perf_counter() - t0)
        name = "hand-crafted 2 V_silh" if w == "<base>" else str(Path(w).parent.name)
        rows.append((name, params, sum(sp) / len(sp), sum(werr) / len(werr),
                     1000 * min(secs) if secs else float("nan")))
    out = ["| model | parameters | Spearman(energy, error) | weighted-mean error (mm) | "
           "learned term ms / 200 particles |", "|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.1f} | {r[4]:.1f} |")
    (HERE / "size_sweep.md").write_text("\n".join(out) + "\n")
    print("\n".join(out))


if __name__ == "__main__":
    main(sys.argv[1:])
