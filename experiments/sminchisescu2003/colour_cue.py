"""Does a monocular colour cue tell a limb from its mirror image? (a probe, not a tracker)

The paper's likelihood adds edges and intensity to the 2D joints; the mirror-image ambiguity of
a monocular 2D-joint cost is what the kinematic jumps expose. Before building an intensity term
this probe asks whether the colour images our synthesis renders (per-part albedo, Lambertian
shading, textured background; the skinned mesh) separate the true pose from its kinematic flips
at all. For every second frame of the three tracking clips (``monocular`` scenario with colour
images, synthesis seed 0), the true pose and every kept flip of each limb that moves a joint by
more than 5 cm (closed-form limb IK within the limits) are scored by three colour energies of
the capsule body's camera-facing surface points (6 x 8 per capsule, occluded points dropped by
the capsules' own z-order, grazing points with a facing cosine < 0.3 dropped):

- ``coherence``: the pooled within-part colour variance (no model of the colours; a pose that
  puts a part where the image shows another part's colour pays);
- ``part colour``: squared distance of each visible point's colour to its part's mean colour in
  frame 0 (seen at the true pose — the tracker's starting pose);
- ``point colour``: squared distance to the same surface point's colour in frame 0 (a texture
  map from the first frame, points unseen then skipped).

Printed (and written to ``results/colour_cue.md`` with ``--write``): per clip and energy, the
fraction of (frame, flip) pairs in which the true pose has the lower energy — 50 % is no
information.

Run:  python experiments/sminchisescu2003/colour_cue.py [--write]      # ~1 CPU-min
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from torchmocap.assembly import Runtime
from torchmocap.body.capsules import rays_blocked_by_capsules
from torchmocap.data.synthetic.clips import synthesized_sequence
from torchmocap.likelihoods.appearance import _per_bone, body_surface_pattern
from torchmocap.proposals.jumps import limb_flips

HERE = Path(__file__).resolve().parent
MOCAP = HERE.parents[1].parent / "shared" / "data" / "mocap" / "cmu"
CLIPS = {  # the excerpts of conf/data/clip/{dance_cmu21,salsa,boxing}.yaml
    "dance": dict(path=MOCAP / "cmu21_dance.bvh", start=3.0, skip_frames=0),
    "salsa": dict(path=MOCAP / "60_12_scaled.bvh", start=2.0, skip_frames="auto"),
    "boxing": dict(path=MOCAP / "cmu21_box-1.bvh", start=5.0, skip_frames=0),
}
LIMBS = ("l_arm", "r_arm", "l_leg", "r_leg")
ENERGIES = ("coherence", "part colour", "point colour")


def surface_colours(rt, pattern, theta, image, min_facing=0.3):
    """Colours ``(P, B, k, 3)`` in [0, 1] of the body-fixed surface points of poses ``theta``
    and their visibility ``(P, B, k)`` (in the image, facing the camera, not behind a capsule)."""
    sk, body, rig = rt.skeleton, rt.body, rt.rig
    t, radial = _per_bone(pattern, body.num_bones)
    t, radial = t.to(theta), radial.to(theta)
    kin = sk(theta)
    ep = body.endpoints(kin)
    P, B, k = theta.shape[0], body.num_bones, t.shape[1]
    n = torch.einsum("pbij,bkj->pbki", kin.rotations[:, body.parent_index], radial)
    a = ep[:, :, 0, None]
    pts = a + t[None, :, :, None] * (ep[:, :, 1, None] - a) + body.radii[None, :, None, None] * n
    own = torch.arange(B).repeat_interleave(k)
    hidden = rays_blocked_by_capsules(rig.camera_centers(), pts.reshape(P, -1, 3), ep,
                                      body.radii, own).reshape(P, B, k)
    u, v, _, vis = rig.project_planar(pts.reshape(-1, 3))
    u, v, vis = (x[0].reshape(P, B, k) for x in (u, v, vis))
    to_cam = rig.camera_centers()[0] - pts
    facing = (to_cam * n).sum(-1) > min_facing * to_cam.norm(dim=-1)
    H, W = image.shape[:2]
    x = (u + 0.5).clamp(0, W - 1).floor().long()
    y = (v + 0.5).clamp(0, H - 1).floor().long()
    return image[y, x].to(theta) / 255, vis & facing & ~hidden


def energies(col, ok, ref_col, ref_ok):
    """The three colour energies ``(P,)`` of ``col, ok`` against frame 0's ``ref_col, ref_ok``."""
    w = ok.to(col.dtype)[..., None]
    nb = w.sum(2)
    mean = (col * w).sum(2) / nb.clamp_min(1)
    coherence = (((col - mean[:, :, None]) ** 2) * w).sum((2, 3)).sum(1) / nb[..., 0].sum(
        1).clamp_min(1)
    rw = ref_ok.to(col.dtype)[..., None]
    part_mean = (ref_col * rw).sum(1) / rw.sum(1).clamp_min(1)  # (B, 3)
    okf = ok.to(col.dtype)
    part = (((col - part_mean[None, :, None]) ** 2).sum(-1) * okf).sum((1, 2)) / okf.sum(
        (1, 2)).clamp_min(1)
    both = (ok & ref_ok[None]).to(col.dtype)
    point = (((col - ref_col[None]) ** 2).sum(-1) * both).sum((1, 2)) / both.sum(
        (1, 2)).clamp_min(1)
    return {"coherence": coherence, "part colour": part, "point colour": point}


def probe(name: str, spec: dict, frames: int = 100, stride: int = 2) -> dict:
    clip = {"name": name, "path": str(spec["path"]), "fps": 25, "frames": frames,
            "start": spec["start"], "skip_frames": spec["skip_frames"]}
    seq = synthesized_sequence(clip, "monocular", {"images.enabled": True}, seed=0)
    rt = Runtime.from_sequence(seq)
    pattern = body_surface_pattern(rt.body, 6, 8)
    gt = seq.ground_truth.theta.to(torch.float32)
    centre = rt.rig.camera_centers()[0]
    ref_col, ref_ok = (x[0] for x in surface_colours(rt, pattern, gt[:1], seq.images[0, 0]))
    wins = {e: [] for e in ENERGIES}
    for f in range(0, gt.shape[0], stride):
        th = gt[f:f + 1]
        flips = []
        for limb in LIMBS:
            lf = limb_flips(rt.skeleton, th, limb, centre)
            for leaf in range(1, lf.theta.shape[1]):
                moved = (lf.positions[0, leaf] - lf.positions[0, 0]).norm(dim=-1).amax()
                if bool(lf.kept[0, leaf]) and float(moved) > 0.05:
                    flips.append(lf.theta[0, leaf])
        if not flips:
            continue
        poses = torch.cat([th, torch.stack(flips)])
        col, ok = surface_colours(rt, pattern, poses, seq.images[f, 0])
        for e, v in energies(col, ok, ref_col, ref_ok).items():
            wins[e] += (v[1:] > v[0]).tolist()
    return {e: (sum(w) / len(w), len(w)) for e, w in wins.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="write results/colour_cue.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = {name: probe(name, spec) for name, spec in CLIPS.items()}
    lines = ["# Colour cue vs mirror images (probe)", "",
             "Fraction of (frame, limb flip) pairs in which the true pose has the lower colour "
             "energy (50 % = no information); every second frame of the 100-frame excerpts, "
             "flips moving a joint by > 5 cm.", "",
             "| clip | pairs | " + " | ".join(ENERGIES) + " |",
             "|---|---:|" + "---:|" * len(ENERGIES)]
    for name, r in rows.items():
        n = r[ENERGIES[0]][1]
        lines.append(f"| {name} | {n} | " + " | ".join(f"{100 * r[e][0]:.0f} %"
                                                     for e in ENERGIES) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write:
        (HERE / "results" / "colour_cue.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
