"""Forward kinematics speed: torchmocap.Skeleton vs pytorch-kinematics on the same skeleton.

Run:  python experiments/benchmarks/fk.py [--threads 2] [--repeats 15] [--markdown]

Both libraries evaluate the human31 skeleton (31 DoF) on the same random poses within joint
limits, in float32 on the CPU, in one process. pytorch-kinematics gets a chain built from our URDF
export (one-DoF joints with dummy links: its only way to express 3-DoF joints). "forward" times
FK producing every joint's global rotation and position; "fwd+bwd" adds a backward pass of the
sum of all joint positions w.r.t. theta. Reported: median milliseconds and ours/peer speed ratios.
"""

from __future__ import annotations

import argparse
import platform

import torch
from timing import median_ms

from torchmocap.skeleton import human31, pk_theta, to_pytorch_kinematics_chain


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--sizes", type=int, nargs="+", default=[200, 3000, 30000])
    ap.add_argument("--markdown", action="store_true", help="print a markdown table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sk = human31()
    chain = to_pytorch_kinematics_chain(sk)
    names = sk.joint_names
    gen = torch.Generator().manual_seed(0)
    lo, hi = sk.lower.clamp(min=-torch.pi), sk.upper.clamp(max=torch.pi)
    rows = []
    for n in args.sizes:
        theta = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen)
        tpk = pk_theta(chain, sk, theta)

        def ours_fwd(theta=theta):
            k = sk(theta, check_finite=False)
            return k.rotations, k.positions

        def pk_fwd(tpk=tpk):
            fr = chain.forward_kinematics(tpk)
            return [fr[j].get_matrix() for j in names]

        def ours_bwd(theta=theta):
            th = theta.clone().requires_grad_(True)
            sk(th, check_finite=False).positions.sum().backward()

        def pk_bwd(tpk=tpk):
            th = tpk.clone().requires_grad_(True)
            fr = chain.forward_kinematics(th)
            sum(fr[j].get_matrix()[:, :3, 3].sum() for j in names).backward()

        f_o, f_p = median_ms(ours_fwd, args.repeats), median_ms(pk_fwd, args.repeats)
        b_o, b_p = median_ms(ours_bwd, args.repeats), median_ms(pk_bwd, args.repeats)
        rows.append((n, f_o, f_p, f_p / f_o, b_o, b_p, b_p / b_o))
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}, float32")
    hdr = ("| poses | ours fwd ms | pk fwd ms | fwd speed-up | ours fwd+bwd ms | pk fwd+bwd ms "
           "| fwd+bwd speed-up |")
    print(hdr)
    print("|" + "---|" * 7)
    for r in rows:
        print(f"| {r[0]} | {r[1]:.2f} | {r[2]:.2f} | {r[3]:.1f}x | {r[4]:.2f} | {r[5]:.2f} "
              f"| {r[6]:.1f}x |")


if __name__ == "__main__":
    main()
