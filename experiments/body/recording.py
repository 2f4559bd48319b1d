"""The fitted Anny body on the real recording (pose2sim_balancing): the table of the tracking
runs and what limits the silhouette IoU — the computed masks measured on their own.

    python experiments/body/recording.py table RUNS          # RUNS/<name>/metrics.json
    python experiments/body/recording.py masks RUNS/<anny run> [--every 4]

``table`` writes ``results/recording.md`` from the runs of the README's commands (held-out cam,
capsules vs fitted body, silhouette weight 0 vs the preset's). ``masks`` loads the recording as
that run did (the same masks: the tracked views' computed without the held-out camera, the
held-out view's from every view), poses the run's fitted Anny mesh at its track and measures, in
every view and every ``--every``-th frame:

* ``mesh``: the IoU of the fitted mesh's projection (rasterised triangles) with the mask;
* ``hull``: the IoU of the mask with the projection of the visual hull of the *other* views'
  masks (2 cm voxels around the body): how far the masks agree with each other in 3D, without
  any body model;
* ``mesh_hull``: the IoU of the fitted mesh's projection with that hull's;
* ``fg_outside``: the fraction of the mask's foreground farther than 10 px from the mesh's
  projection (mask pixels no body near the track explains: shadows, background), and
  ``mesh_missed``: the fraction of the mesh's projection off the mask (holes, missed limbs).

It writes ``results/recording_masks_<run>.md``.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

RECORDING = Path(__file__).resolve().parents[3] / "shared/data/multiview/pose2sim_balancing"
OUT = Path(__file__).resolve().parent / "results"


def _row(name: str, m: dict) -> str:
    h = m.get("heldout") or {}
    fit = m.get("body_fit") or {}
    sil = (m.get("silhouette_iou") or {}).get("mean")
    phen = fit.get("phenotype")
    return (f"| {name} | {h.get('camera')} | {m.get('body')} | {m.get('term')} | "
            f"{m.get('weight')} | "
            f"{h.get('silhouette_iou', math.nan):.3f} | {h.get('median_px', math.nan):.1f} | "
            f"{h.get('mean_px', math.nan):.1f} | {h.get('pck_05', math.nan):.3f} | "
            f"{sil if sil is None else round(sil, 3)} | "
            f"{'' if not fit else round(fit.get('iou_before', math.nan), 3)} | "
            f"{'' if not fit else round(fit.get('iou_after', math.nan), 3)} | "
            f"{'' if not phen else fit.get('height')} | {m['seconds_per_frame']:.2f} |")


def table(runs: Path) -> str:
    rows = ["| run | held-out | body | silhouette term | weight | held-out IoU | held-out "
            "median px | mean px | PCK@5% | tracked views' IoU | fit IoU before | after | "
            "fitted height m "
            "| s / frame |", "|" + "---|" * 14]
    for d in sorted(p for p in runs.iterdir() if (p / "metrics.json").is_file()):
        m = json.loads((d / "metrics.json").read_text())
        m["body"] = "Anny fitted" if m.get("body_fit") else "capsules"
        m["weight"] = 0 if "_w0" in d.name else 100
        m["term"] = "surface points" if "_surf" in d.name else "capsules"
        rows.append(_row(d.name, m))
    return "\n".join(rows)


def _splat(pix: torch.Tensor, W: int, H: int, r: int) -> torch.Tensor:
    """``(H, W)`` bool: pixels within ``r`` (a square) of the projected points ``(N, 2)``."""
    uv = pix.round().long()
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    hit = torch.zeros(H, W)
    hit[uv[ok, 1], uv[ok, 0]] = 1.0
    return F.max_pool2d(hit[None, None], 2 * r + 1, 1, r)[0, 0] > 0


def _iou(a: torch.Tensor, b: torch.Tensor) -> float:
    u = int((a | b).sum())
    return float((a & b).sum()) / u if u else math.nan


def masks(run: Path, every: int) -> str:
    from torchmocap.assembly import Runtime
    from torchmocap.body import ParametricBody
    from torchmocap.cameras import visual_hull
    from torchmocap.data.recordings.loader import load_recording
    from torchmocap.data.synthetic.render import rasterize_mask

    m = json.loads((run / "metrics.json").read_text())
    cam = m["heldout"]["camera"]
    phen_d = m["body_fit"]["phenotype"]
    T = m["frames"]
    seq = load_recording(RECORDING, stop=T, heldout_camera=cam,
                         mask_cache=os.environ.get("MASK_CACHE", "outputs/mask_cache"))
    rt = Runtime.from_sequence(seq, dtype=torch.float64)
    sk, rig = rt.skeleton, seq.rig.double()
    theta = torch.from_numpy(np.load(run / "track.npz")["theta"]).double()
    from torchmocap.body.anny_model import PHENOTYPE_NAMES

    phen = torch.tensor([phen_d[n] for n in PHENOTYPE_NAMES], dtype=torch.float64)
    pb = ParametricBody(sk).double()
    faces = pb.faces
    names = list(rig.names)
    C = rig.num_cameras
    # the hull's rig: every view at the padded size (views of different sizes share one padded
    # image tensor; the padding is background)
    padded = copy.deepcopy(rig)
    padded.image_size[:] = torch.tensor([seq.silhouettes.shape[-1], seq.silhouettes.shape[-2]])
    per = {n: {k: [] for k in ("mesh", "hull", "mesh_hull", "fg_outside", "mesh_missed")}
           for n in names}
    for t in range(0, T, every):
        with torch.no_grad():
            v = pb(theta[t], phen, offsets=sk.offsets).vertices  # (V, 3)
        pix, depth, _ = rig.project(v)                          # (C, V, 2), (C, V)
        sil = seq.silhouettes[t].bool()
        lo, hi = v.min(0).values - 0.3, v.max(0).values + 0.3
        bounds = torch.stack([lo, hi], 1)
        for c in range(C):
            W, H = (int(x) for x in rig.image_size[c].tolist())
            mask = sil[c, :H, :W]
            mesh = rasterize_mask(pix[c:c + 1], depth[c:c + 1], faces, W, H)[0]
            others = [o for o in range(C) if o != c]
            hull = visual_hull(padded.subset(others), sil[others], bounds, 0.02)
            pts = hull.centers().double()
            r = 1
            if pts.shape[0]:
                d = float(rig.subset([c]).project(pts.mean(0, keepdim=True))[1][0, 0])
                r = max(1, round(float(rig.K[c, 0, 0]) * 0.02 / max(d, 1e-6) / 2))
                hp = _splat(rig.subset([c]).project(pts)[0][0], W, H, r)
            else:
                hp = torch.zeros(H, W, dtype=torch.bool)
            near = F.max_pool2d(mesh[None, None].float(), 21, 1, 10)[0, 0] > 0
            e = per[names[c]]
            e["mesh"].append(_iou(mesh, mask))
            e["hull"].append(_iou(mask, hp))
            e["mesh_hull"].append(_iou(mesh, hp))
            e["fg_outside"].append(float((mask & ~near).sum()) / max(1, int(mask.sum())))
            e["mesh_missed"].append(float((mesh & ~mask).sum()) / max(1, int(mesh.sum())))
    rows = [f"Run `{run.name}` (held out: {cam}), frames 0, {every}, ... of {T}; the held-out "
            "view's masks are computed from every view, the others' without it.", "",
            "| view | fitted mesh vs mask IoU | mask vs hull of the other views IoU | "
            "mesh vs that hull IoU | mask farther than 10 px from the mesh | mesh off the mask |",
            "|---|---|---|---|---|---|"]
    for n in names:
        e = {k: float(np.nanmean(x)) for k, x in per[n].items()}
        rows.append(f"| {n}{' (held out)' if n == cam else ''} | {e['mesh']:.3f} | "
                    f"{e['hull']:.3f} | {e['mesh_hull']:.3f} | {e['fg_outside']:.3f} | "
                    f"{e['mesh_missed']:.3f} |")
    return "\n".join(rows)


def _write(name: str, title: str, text: str) -> None:
    from torchmocap.atomic import write_text_atomic

    write_text_atomic(OUT / name, f"# {title}\n\n{text}\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("what", choices=["table", "masks"])
    p.add_argument("path", type=Path)
    p.add_argument("--every", type=int, default=4)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    if a.what == "table":
        text = table(a.path)
        _write("recording.md", "The fitted Anny body on pose2sim_balancing (40 frames)", text)
    else:
        text = masks(a.path, a.every)
        _write(f"recording_masks_{a.path.name}.md", "The masks on their own", text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
