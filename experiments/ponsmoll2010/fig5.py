"""Pons-Moll et al. (2010), Fig. 5: Gaussian noise on the passive parameters vs vMF sensor noise.

500 inverse-kinematics samples of the left shoulder for a fixed vector of active coordinates,
with (a) Gaussian noise added to the passive (shoulder) parameters after g^{-1} and (b) vMF noise
on the forearm sensor's quaternion (eq. 16) before g^{-1} (only the forearm sensor / shoulder is
perturbed, so the shoulder joint itself stays put), at equivalent dispersion
(kappa = 1000 <-> sigma = 2/sqrt(kappa) = 3.6 deg per parameter). The shoulder is posed with a
middle (abduction) angle of 89 deg, one degree from the decomposition's gimbal lock, where the
first and third axes nearly coincide: Gaussian noise on the three Euler-type parameters then
spreads the upper arm (and the elbow) along one direction only.

Outputs (in ``--out``, default ``experiments/ponsmoll2010/results``): ``fig5.png`` (3D scatter of
the elbow positions, both models), ``fig5.md`` (principal spreads), ``fig5.json``.

    OMP_NUM_THREADS=1 python experiments/ponsmoll2010/fig5.py
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from torchmocap.distributions import VonMisesFisher, add_parameter_noise, kappa_to_tangent_std
from torchmocap.geometry import so3_log
from torchmocap.ik import SensorManifold
from torchmocap.skeleton import human31

HERE = Path(__file__).resolve().parent


def principal_spreads(x: torch.Tensor) -> torch.Tensor:
    """Standard deviations along the principal axes of ``x (N, k)``, descending."""
    xc = x - x.mean(0)
    return torch.linalg.svdvals(xc) / math.sqrt(x.shape[0] - 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--kappa", type=float, default=1000.0)
    ap.add_argument("--middle-deg", type=float, default=89.0,
                    help="shoulder abduction (middle axis) angle")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    sk = human31().double()
    m = SensorManifold(sk).double()
    theta = torch.zeros(sk.num_dofs, dtype=torch.float64)
    sh = sk.joint_dofs("l_shoulder")
    theta[sh] = torch.tensor([math.radians(20.0), math.radians(args.middle_deg),
                              math.radians(10.0)], dtype=torch.float64)
    theta[sk.joint_dofs("l_elbow")] = math.radians(60.0)
    sensors = m.sensor_orientations(theta)
    sigma = kappa_to_tangent_std(args.kappa)
    el = sk.joint_index("l_elbow")
    ua = sk.joint_index("l_shoulder")
    R0 = sk(theta).rotations[ua]
    out = {}
    i_fa = m.sensor_names.index("l_forearm")
    xa = m(theta).expand(args.samples, -1)
    for noise in ("gaussian", "vmf"):
        g = torch.Generator().manual_seed(args.seed)
        if noise == "gaussian":  # GN: g^{-1} with the measured sensors, then N(0, s^2) on the
            # passive parameters of the shoulder (the joint the forearm sensor determines)
            th = m.inverse(xa, sensors, reference=theta).theta
            th = add_parameter_noise(th, sh, sigma, generator=g)
        else:  # vMF on the forearm sensor's quaternion only (eq. 16), then g^{-1}
            q = torch.zeros(args.samples, m.num_sensors, 4, dtype=torch.float64)
            q[..., 0] = 1
            e1 = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
            q[:, i_fa] = VonMisesFisher(e1, torch.tensor(args.kappa, dtype=torch.float64)).sample(
                (args.samples,), generator=g)
            th = m.inverse(xa, sensors, noise=q, reference=theta).theta
        kin = sk(th)
        elbow = kin.positions[:, el]
        rotvec = so3_log(R0.expand(args.samples, 3, 3).transpose(-1, -2)
                         @ kin.rotations[:, ua])  # upper-arm perturbation, bone frame
        sp_pos = principal_spreads(elbow) * 100  # cm
        sp_rot = torch.rad2deg(principal_spreads(rotvec))
        ang = torch.rad2deg(rotvec.norm(dim=-1))
        out[noise] = {
            "elbow": elbow,
            "elbow_spreads_cm": [round(float(v), 3) for v in sp_pos],
            "rotation_spreads_deg": [round(float(v), 3) for v in sp_rot],
            "elbow_spread_ratio": float(sp_pos[0] / sp_pos[1]),
            "median_angle_deg": float(ang.median()),
        }
    res = {k: {kk: vv for kk, vv in v.items() if kk != "elbow"} for k, v in out.items()}
    res["setup"] = {"samples": args.samples, "kappa": args.kappa,
                    "gaussian_std_deg": math.degrees(sigma), "middle_deg": args.middle_deg,
                    "seed": args.seed}
    (args.out / "fig5.json").write_text(json.dumps(res, indent=2))

    lines = [
        "# Fig. 5 — Gaussian noise on passive parameters vs vMF sensor noise",
        "",
        f"{args.samples} samples, kappa = {args.kappa:g}, Gaussian std = 2/sqrt(kappa) = "
        f"{math.degrees(sigma):.2f} deg per parameter, left shoulder at (flex 20, abd "
        f"{args.middle_deg:g}, int 10) deg, elbow 60 deg; seed {args.seed}.",
        "",
        "| noise model | upper-arm rotation spreads (deg, principal) | elbow spreads (cm, "
        "principal) | elbow spread ratio 1st/2nd | median angle (deg) |",
        "|---|---|---|---:|---:|",
    ]
    for k, name in (("gaussian", "Gaussian on passive parameters (GN)"), ("vmf", "vMF (eq. 16)")):
        r = res[k]
        lines.append(
            f"| {name} | {', '.join(f'{v:.2f}' for v in r['rotation_spreads_deg'])} | "
            f"{', '.join(f'{v:.2f}' for v in r['elbow_spreads_cm'])} | "
            f"{r['elbow_spread_ratio']:.2f} | {r['median_angle_deg']:.2f} |")
    (args.out / "fig5.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(10, 4.8))
    sh_pos = sk(theta).positions[ua]
    lim = max(float((out[k]["elbow"] - out[k]["elbow"].mean(0)).abs().max()) for k in out)
    for i, (k, title) in enumerate((("gaussian", "(a) Gaussian on passive parameters"),
                                    ("vmf", "(b) von Mises–Fisher sensor noise"))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        e = (out[k]["elbow"] - out[k]["elbow"].mean(0)) * 100
        ax.scatter(e[:, 0], e[:, 1], e[:, 2], s=4, alpha=0.6,
                   color="tab:red" if k == "gaussian" else "tab:blue")
        d = (out[k]["elbow"].mean(0) - sh_pos)
        d = d / d.norm() * lim * 100
        ax.plot([0, -d[0]], [0, -d[1]], [0, -d[2]], color="k", lw=1)  # towards the shoulder
        L = lim * 100
        ax.set_xlim(-L, L)
        ax.set_ylim(-L, L)
        ax.set_zlim(-L, L)
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("y (cm)")
        ax.set_zlabel("z (cm)")
        r = res[k]
        ax.set_title(f"{title}\nspread ratio {r['elbow_spread_ratio']:.1f}", fontsize=9)
    fig.suptitle(f"Elbow positions of {args.samples} IK samples (middle shoulder angle "
                 f"{args.middle_deg:g} deg; black: direction to the shoulder)", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out / "fig5.png", dpi=120)
    print(f"wrote {args.out / 'fig5.png'}")


if __name__ == "__main__":
    main()
