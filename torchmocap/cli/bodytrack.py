"""``torchmocap-track data=bodytrack``: fit human31 to the real 4-camera bodytrack frame.

Reads the PARSEC bodytrack frame (``CAM1..4`` grey images, ``FG1..4`` foreground masks, Bouguet
calibrations in millimetres), carves the masks' visual hull, stands a human31 (scaled to the hull's
height) at the hull's centre, picks the best of 12 headings, then refines the pose with the
annealed particle optimiser on the real silhouettes alone, in ``rounds`` passes of
``tracker.num_particles x tracker.layers`` with a shrinking initial spread. Writes per-view
overlays of the fitted capsule body, ``fit.npz`` and ``metrics.json`` (per-view silhouette IoU,
and the time of one annealing pass, the workload PARSEC's C++ filter needs 0.086 s for).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import hydra

__all__ = ["load_bodytrack", "run_bodytrack", "fit_static_frame"]


def load_bodytrack(root: Path, scale: float = 1.0):
    """``(rig, images (C, H, W) uint8, masks (C, H, W) bool)`` of a bodytrack frame folder."""
    import numpy as np
    import torch
    from PIL import Image

    from torchmocap.cameras import read_bouguet_rig

    root = Path(root)
    cals = sorted((root / "CALIB").glob("Camera*.cal"))
    if not cals:
        raise FileNotFoundError(f"data.path: no CALIB/Camera*.cal under {root}")
    rig = read_bouguet_rig(cals, unit="mm")
    imgs, masks = [], []
    for i in range(1, len(cals) + 1):
        img = root / f"CAM{i}" / "image0000.bmp"
        fg = root / f"FG{i}" / "image0000.bmp"
        if not img.is_file() or not fg.is_file():
            raise FileNotFoundError(f"data.path: camera {i} image or mask missing in {root}")
        a = Image.open(img).convert("L")
        m = Image.open(fg).convert("L")
        if scale != 1.0:
            size = (round(a.width * scale), round(a.height * scale))
            a = a.resize(size, Image.BILINEAR)
            m = m.resize(size, Image.NEAREST)
        imgs.append(torch.from_numpy(np.asarray(a).copy()))
        masks.append(torch.from_numpy(np.asarray(m) > 127))
    if scale != 1.0:
        rig = rig.scaled_images(scale)
    return rig, torch.stack(imgs), torch.stack(masks)


def fit_static_frame(rig, masks, num_particles=200, layers=15, rounds=4, seed=0,
                     fg_samples=150):
    """Fit human31 to one multi-view silhouette set; returns ``(skeleton, body, theta, info)``."""
    import torch

    from torchmocap.body import CapsuleBody
    from torchmocap.cameras import visual_hull
    from torchmocap.filters.annealed import anneal, default_diffusion
    from torchmocap.likelihoods.silhouette import prepare_silhouettes, silhouette_energy
    from torchmocap.skeleton import human31

    hull = visual_hull(rig.double(), masks, [[-3, 3], [-3, 3], [-0.1, 2.3]], 0.04)
    hull = hull.largest_component()
    pts = hull.centers()
    if pts.shape[0] == 0:
        raise ValueError("masks: the visual hull is empty (calibration or masks wrong)")
    top = float(pts[:, 2].max())
    centre = pts.mean(0)
    scale = min(max(top / 1.75, 0.85), 1.15)
    sk = human31().with_bone_lengths(scale=scale).float()
    body = CapsuleBody(sk)
    rig = rig.float()
    obs = prepare_silhouettes(masks, fg_samples)

    def energy(th):
        return silhouette_energy(body.endpoints(sk(th, check_finite=False)), body.radii, rig, obs)

    base = sk.zero_pose()
    base[0], base[1] = float(centre[0]), float(centre[1])
    base[2] = float(pts[:, 2].min().clamp(max=0.1))  # feet on the hull's floor
    cands = base.repeat(12, 1)
    cands[:, sk.dof_index("pelvis_rz")] = torch.arange(12) * (2 * math.pi / 12)
    theta = cands[int(energy(cands).argmin())].clone()
    g = torch.Generator().manual_seed(int(seed))
    lo, hi = sk.lower.clone(), sk.upper.clone()
    lo[3], hi[3] = theta[3] - math.pi, theta[3] + math.pi
    timings = []
    for r in range(rounds):
        sig = torch.full((sk.num_dofs,), math.radians(40.0 / (2.0 ** r)))
        sig[:3] = 0.08 / (2.0 ** r)
        x0 = theta + sig * torch.randn(num_particles, sk.num_dofs, generator=g)
        t0 = time.perf_counter()
        res = anneal(energy, x0, layers=layers, diffusion=default_diffusion(layers), lower=lo,
                     upper=hi, generator=g)
        timings.append(time.perf_counter() - t0)
        cand = res.best if float(res.best_energy) < float(energy(res.estimate[None])) \
            else res.estimate
        if float(energy(cand[None])) <= float(energy(theta[None])):
            theta = cand
    info = {"hull_centre": centre.tolist(), "hull_top_m": top, "skeleton_scale": scale,
            "energy": float(energy(theta[None])), "seconds_per_anneal": min(timings),
            "seconds_total": sum(timings)}
    return sk, body, theta, info


def run_bodytrack(cfg, out: Path) -> dict:
    """The ``data=bodytrack`` job of ``torchmocap-track``."""
    import numpy as np

    from torchmocap.cli.track import write_json_atomic
    from torchmocap.likelihoods.silhouette import render_capsule_silhouettes, silhouette_iou
    from torchmocap.viz import overlay_on_image

    root = Path(hydra.utils.to_absolute_path(str(cfg.data.path)))
    if not root.is_dir():
        raise FileNotFoundError(f"data.path: no such folder: {root}")
    rig, images, masks = load_bodytrack(root, float(cfg.data.get("scale", 1.0)))
    t = cfg.tracker
    sk, body, theta, info = fit_static_frame(rig, masks, int(t.num_particles), int(t.layers),
                                             int(cfg.data.get("rounds", 4)), int(cfg.seed),
                                             int(t.get("fg_samples", 150)))
    rig = rig.float()
    model = render_capsule_silhouettes(body, rig, theta)
    iou = silhouette_iou(model, masks)
    kin = sk(theta)
    for c in range(rig.num_cameras):
        overlay_on_image(images[c], rig, c, kin, out / f"overlay_cam{c + 1}.png", skeleton=sk,
                         capsules=body, mask=masks[c], title=f"camera {c + 1}: IoU {iou[c]:.2f}")
    np.savez_compressed(out / "fit.npz", theta=theta.numpy(), dof_names=np.array(sk.dof_names))
    metrics = {
        "data": "bodytrack",
        "frames": 1,
        "image_size": [int(v) for v in rig.image_size[0].tolist()],
        "num_particles": int(t.num_particles),
        "layers": int(t.layers),
        "silhouette_iou": {"per_view": [float(v) for v in iou], "mean": float(iou.mean())},
        "parsec_seconds_per_anneal": 0.086,
        **info,
    }
    write_json_atomic(metrics, out / "metrics.json")
    return metrics
