"""Kinematic Jacobians of every joint: torchmocap.Skeleton.jacobian vs pytorch-kinematics and
vs autograd.

Run:  python experiments/benchmarks/jacobian.py [--threads 2] [--repeats 21] [--sizes 200 3000]

human31 (31 DoF, 21 joints), float32, CPU, random poses within the joint limits. Ours:
``Skeleton.jacobian`` — the position Jacobian ``(B, 21, 3, 31)`` and the angular one of every
joint in one call (what the Gauss-Newton / Levenberg-Marquardt fits of the monocular trackers and
the subject fit use). pytorch-kinematics: ``SerialChain(chain, joint).jacobian`` gives the 6 x n
geometric Jacobian of one frame, so all 21 joints take one serial chain each (chains built once,
outside the timing); its result is checked equal to ours first. Autograd:
``torch.autograd.functional.jacobian`` (vectorised backward passes) of our forward kinematics
(positions only). Median milliseconds, both in one process; ratios are the peer's time / ours.
"""

from __future__ import annotations

import argparse
import platform
from importlib.metadata import version

import torch
from timing import median_ms

from torchmocap.skeleton import human31, pk_theta, to_pytorch_kinematics_chain


def main() -> None:
    import pytorch_kinematics as pk

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--sizes", type=int, nargs="+", default=[200, 3000])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sk = human31()
    chain = to_pytorch_kinematics_chain(sk)
    pk_names = chain.get_joint_parameter_names()
    serial = []  # (joint index, chain, columns of pk's theta)
    for j, name in enumerate(sk.joint_names):
        sc = pk.SerialChain(chain, name)
        cols = [pk_names.index(n) for n in sc.get_joint_parameter_names()]
        serial.append((j, sc, torch.tensor(cols)))
    ours_cols = [sk.dof_names.index(n) if n in sk.dof_names else None for n in pk_names]
    gen = torch.Generator().manual_seed(0)
    lo, hi = sk.lower.clamp(min=-torch.pi), sk.upper.clamp(max=torch.pi)

    # the peer computes the same thing: its columns equal ours on a few poses
    theta = lo + (hi - lo) * torch.rand(8, sk.num_dofs, generator=gen)
    _, Jp, Jr = sk.jacobian(theta)
    tpk = pk_theta(chain, sk, theta)
    worst = 0.0
    for j, sc, cols in serial:
        Jpk = sc.jacobian(tpk[:, cols])  # (B, 6, n)
        mine = torch.cat([Jp[:, j], Jr[:, j]], 1)[:, :, [ours_cols[c] for c in cols.tolist()]]
        worst = max(worst, float((Jpk - mine).abs().max()))
    assert worst < 1e-4, f"pytorch-kinematics and ours disagree by {worst}"

    def jac_autograd(t):  # poses are independent: d(sum over poses)/d theta_b = J_b
        return torch.autograd.functional.jacobian(
            lambda x: sk(x, check_finite=False).positions.sum(0), t, vectorize=True)
    rows = []
    for n in args.sizes:
        theta = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen)
        tpk = pk_theta(chain, sk, theta)
        subsets = [(sc, tpk[:, cols].contiguous()) for _, sc, cols in serial]
        t_ours = median_ms(lambda theta=theta: sk.jacobian(theta), args.repeats)
        t_pk = median_ms(lambda subsets=subsets: [sc.jacobian(t) for sc, t in subsets],
                          max(3, args.repeats // 3))
        t_ag = median_ms(lambda theta=theta: jac_autograd(theta), max(3, args.repeats // 3))
        rows.append((n, t_ours, t_pk, t_ag))
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}, float32; pytorch-kinematics "
          f"{version('pytorch-kinematics')} agrees with ours to {worst:.1e}")
    print("| poses | ours: positions + rotations, all 21 joints (ms) | pytorch-kinematics, 21 "
          "serial chains (ms) | speed-up | autograd jacobian, positions only (ms) "
          "| speed-up |")
    print("|" + "---|" * 6)
    for n, o, p, a in rows:
        print(f"| {n} | {o:.2f} | {p:.1f} | {p / o:.1f}x | {a:.1f} | {a / o:.1f}x |")


if __name__ == "__main__":
    main()
