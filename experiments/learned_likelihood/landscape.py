"""Energy along perturbation directions from the true pose: hand-crafted vs learned.

    python experiments/learned_likelihood/landscape.py [--weights FILE] [--frame 20]

A held-out clip (CMU 131 walk, outdoor scenario, synthesis seed 0) at frame ``--frame``: the
true pose is moved along single DoFs and the root translation; each curve is the energy minus
its value at the truth, divided by its range over the plot (the annealer's ESS-adaptive beta
makes the scale irrelevant: what matters is where the minimum lies and how the energy rises
around it). Writes ``landscape.png`` and ``landscape.json`` beside this file.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
DIRECTIONS = [("l_elbow_flex", 0.8, "rad"), ("r_shoulder_flex", 0.8, "rad"),
              ("r_hip_flex", 0.6, "rad"), ("pelvis_tx", 0.2, "m")]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--weights", default="torchmocap/assets/learned/learned_features.pt")
    ap.add_argument("--frame", type=int, default=20)
    ap.add_argument("--steps", type=int, default=41)
    args = ap.parse_args()

    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.synthetic.clips import synthesized_sequence
    from torchmocap.likelihoods import FrameEnergy

    clip = {"name": "walking", "path": "../shared/data/mocap/cmu/131_02.bvh", "fps": 25,
            "start": 1.0, "frames": 40}
    seq = synthesized_sequence(clip, "outdoor", {"depth.enabled": False,
                                                 "joints2d.enabled": False}, seed=0)
    rt = Runtime.from_sequence(seq)
    sk = rt.skeleton
    def lik(name, *extra):
        return build_tracker(tracker_config("p", [f"likelihood@tracker.likelihood={name}",
                                                  *extra]), rt).likelihood

    frame = seq.frame(args.frame)
    truth = seq.ground_truth.theta[args.frame].float()
    curves = {}
    for label, L in (
            ("P's hand-crafted cost (2 V_silh + 40 V_app)", lik("image")),
            ("hand-crafted silhouette (2 V_silh)", lik("silhouette")),
            ("2 V_silh + learned", lik("silhouette_learned",
                                       "tracker.likelihood.terms.learned.weights="
                                       f"{Path(args.weights).absolute()}"))):
        curves[label] = FrameEnergy(L, L.prepare(frame), sk)
    names = sk.dof_names
    out = {}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(DIRECTIONS), figsize=(4 * len(DIRECTIONS), 3.4))
    for ax, (dof, span, unit) in zip(axes, DIRECTIONS):
        if dof not in names:
            continue
        k = names.index(dof)
        t = torch.linspace(-span, span, args.steps)
        x = truth[None].repeat(args.steps, 1)
        x[:, k] += t
        lo, hi = sk.lower[k], sk.upper[k]
        keep = (x[:, k] >= lo) & (x[:, k] <= hi)  # within the joint limits
        x, t = x[keep], t[keep]
        i0 = int(t.abs().argmin())
        res = {}
        for lab, V in curves.items():
            with torch.no_grad():
                e = V(x)
            z = e - e[i0]
            z = z / (e.max() - e.min()).clamp_min(1e-12)
            ax.plot(t.numpy(), z.numpy(), label=lab)
            inner = (e[1:-1] < e[:-2]) & (e[1:-1] < e[2:])  # strict local minima
            res[lab] = {"offset": t.tolist(), "energy": e.tolist(),
                        "argmin_offset": float(t[int(e.argmin())]),
                        "local_minima": int(inner.sum())}
        ax.axvline(0.0, color="k", lw=0.6, ls=":")
        ax.set_xlabel(f"{dof} offset from the truth ({unit})")
        ax.set_title(dof)
        out[dof] = res
    axes[0].set_ylabel("(V - V(truth)) / range")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"energy along single DoFs, held-out CMU 131 walk, outdoor, frame {args.frame}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(HERE / "landscape.png", dpi=110)
    (HERE / "landscape.json").write_text(json.dumps(out, indent=1))
    for dof, r in out.items():
        print(dof, {k: (round(v["argmin_offset"], 3), v["local_minima"]) for k, v in r.items()})


if __name__ == "__main__":
    main()
