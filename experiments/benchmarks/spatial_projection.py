"""Projection onto the skeleton (Hauberg & Pedersen eqs. 6-7): ours vs the batched LM prototype.

Run:  python experiments/benchmarks/spatial_projection.py [--threads 2] [--particles 200]
                                                         [--repeats 15] [--poses walk uniform]

The problem of the projected spatial prior: human31 (31 DoF, 21 joints), ``--particles`` poses
whose 21 joint positions plus 3 cm Gaussian noise per coordinate are the targets, each projected
from its unperturbed pose as the warm start (prior weight 1e-3), float32, CPU, one process.
Poses: ``walk`` = frames of the bundled CMU 131_01 walk fitted to human31 (what a tracker sees);
``uniform`` = uniform within the joint limits (many shoulders near gimbal lock; harder).

Measured, for ``project_to_skeleton`` (ours) and ``fit_pose_lm`` (the batched LM prototype) on the
identical problems: the fewest iterations after which the 99th percentile over particles of the
largest per-joint residual change ``max_j | |x_j - F_j(theta_k)| - |x_j - F_j(theta*)| |`` is
below 1 mm, ``theta*`` being the solver's own converged result (float64, 500 iterations), and
the median time of a run with that many iterations. ``worse minima``: particles whose converged
cost exceeds the best of both solvers by more than 1e-6 m^2 (a different local minimum, or a
stall). pytorch-kinematics is asked for what it can do with the same targets.

Result (this machine, 2 threads; see experiments/benchmarks/README.md for the conditions):

    walk poses: ours 8 iterations to p99 < 1 mm in 26.8 ms (3/200 worse minima);
    fit_pose_lm not within 60 iterations (625 ms, p99 28 mm, 175/200 worse minima): >= 23x.
    uniform poses: ours 23 iterations, 59.1 ms; fit_pose_lm not within 60 (750 ms): >= 12.7x.

    (2 threads, idle machine; the full table with pytorch-kinematics and the uniform poses is
    in experiments/benchmarks/README.md. Target <= 15 ms: not met.)
"""

from __future__ import annotations

import argparse
import platform
import warnings

import torch
from timing import median_ms

from torchmocap.ik import project_to_skeleton
from torchmocap.ik.lm import fit_pose_lm
from torchmocap.skeleton import human31, to_pytorch_kinematics_chain

MM = 1e3



def walk_poses() -> torch.Tensor:
    """Every frame of the bundled CMU 131_01 walk, fitted to human31 ``(T, 31)`` float64."""
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.io import bundled_clip_path, load_motion

    return fit_subject(load_motion(bundled_clip_path())).theta.detach()


def uniform_poses(sk, n: int, gen: torch.Generator) -> torch.Tensor:
    lo, hi = sk.lower.double().clamp(min=-torch.pi), sk.upper.double().clamp(max=torch.pi)
    th = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen, dtype=torch.float64)
    th[:, sk.translation_dofs] = 0.1 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return th


def residual_change(res: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """``(P,)`` largest per-joint change of the residual distance (metres)."""
    return (res.double() - ref.double()).abs().amax(1)


def first_within(run, ref_res, k_max: int, target: float = 1e-3):
    """Fewest iterations k with p99 residual change < target, and that p99 (or k_max's)."""
    p99 = float("inf")
    for k in range(1, k_max + 1):
        p99 = float(residual_change(run(k), ref_res).quantile(0.99))
        if p99 < target:
            return k, p99
    return None, p99


def pk_row(sk, theta, x, repeats):
    """What pytorch-kinematics' PseudoInverseIK does with these targets (one end effector per
    serial chain; a shared start configuration; limits)."""
    import pytorch_kinematics as pk

    chain = to_pytorch_kinematics_chain(sk)
    serial = pk.SerialChain(chain, "l_hand")
    names = serial.get_joint_parameter_names()
    idx = torch.tensor([sk.dof_index(n) for n in names])
    q0 = theta[:, idx].float()
    hand = x[:, sk.joint_index("l_hand")].float()
    rot = serial.forward_kinematics(q0, end_only=True).get_matrix()[:, :3, :3]
    target = pk.Transform3d(pos=hand, rot=rot)
    lim = torch.tensor(serial.get_joint_limits()).T.float()
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for enforce in (True, False):
            ik = pk.PseudoInverseIK(serial, retry_configs=q0[:1], joint_limits=lim,
                                    max_iterations=30, orientation_weight=0.0,
                                    enforce_joint_limits=enforce)
            sol = ik.solve(target)
            q = sol.solutions[:, 0]
            nan = int(torch.isnan(q).any(1).sum())
            t = median_ms(lambda ik=ik: ik.solve(target), max(3, repeats // 3))
            err = None
            outside = None
            if nan < q.shape[0]:
                ok = ~torch.isnan(q).any(1)
                fk = serial.forward_kinematics(q[ok], end_only=True).get_matrix()[:, :3, 3]
                err = float((fk - hand[ok]).norm(dim=-1).quantile(0.99))
                lo, hi = sk.lower[idx], sk.upper[idx]
                outside = int(((q[ok] < lo - 1e-6) | (q[ok] > hi + 1e-6)).any(1).sum())
            out[enforce] = dict(nan=nan, ms=t, err=err, outside=outside, dofs=len(names))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--noise", type=float, default=0.03, help="metres per coordinate")
    ap.add_argument("--poses", nargs="+", default=["walk", "uniform"],
                    choices=["walk", "uniform"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lm-max-iterations", type=int, default=60)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    P = args.particles
    sk, sk64 = human31(), human31().double()
    joints = list(range(sk.num_joints))
    rows, pk_out = [], None
    for poses in args.poses:
        gen = torch.Generator().manual_seed(args.seed)
        if poses == "walk":
            frames = walk_poses()
            theta = frames[torch.randint(0, frames.shape[0], (P,), generator=gen)]
        else:
            theta = uniform_poses(sk64, P, gen)
        x64 = sk64(theta).positions
        x64 = x64 + args.noise * torch.randn(x64.shape, generator=gen, dtype=torch.float64)
        x, th = x64.float(), theta.float()

        # each solver's own converged result, and the best of both (float64)
        ours_opt = project_to_skeleton(sk64, x64, theta, tol=1e-10, iterations=500)
        lm_opt = fit_pose_lm(sk64, theta, x64, joints, iterations=400, tol=0.0)
        best = torch.minimum(ours_opt.cost, lm_opt.cost)

        def ours(k, x=x, th=th):
            return project_to_skeleton(sk, x, th, iterations=k).residual

        def lm(k, x=x, th=th):
            return fit_pose_lm(sk, th, x, joints, iterations=k, tol=0.0).position_error

        for name, run, opt, k_max in (("ours", ours, ours_opt.residual, 40),
                                      ("fit_pose_lm", lm, lm_opt.position_error,
                                       args.lm_max_iterations)):
            k, p99 = first_within(run, opt, k_max)
            kk = k if k is not None else k_max
            ms = median_ms(lambda run=run, kk=kk: run(kk), args.repeats)
            worse = int(((ours_opt.cost if name == "ours" else lm_opt.cost) > best + 1e-6).sum())
            rows.append((poses, name, k, kk, p99, ms, worse))
        t_def = median_ms(lambda x=x, th=th: project_to_skeleton(sk, x, th), args.repeats)
        r_def = project_to_skeleton(sk, x, th)
        p_def = float(residual_change(r_def.residual, ours_opt.residual).quantile(0.99))
        rows.append((poses, "ours, default stop", None, r_def.iterations, p_def, t_def,
                     int(r_def.converged.sum())))
        if pk_out is None:
            pk_out = pk_row(sk, theta, x64, args.repeats)

    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}, float32, {P} particles, "
          f"noise {args.noise * 100:g} cm")
    print("| poses | solver | iterations to p99 < 1 mm | time (ms) | p99 residual change (mm) "
          "| worse minima | speed-up vs fit_pose_lm |")
    print("|---|---|---:|---:|---:|---:|---:|")
    lm = {r[0]: r for r in rows if r[1] == "fit_pose_lm"}
    for poses, name, k, kk, p99, ms, worse in rows:
        lm_k, lm_ms = lm[poses][2], lm[poses][5]
        ratio = f"{lm_ms / ms:.1f}x" if lm_k is not None else f">= {lm_ms / ms:.1f}x"
        if name == "ours, default stop":
            print(f"| {poses} | ours, default stopping (tol 1e-4 m, {kk} iterations) | all: "
                  f"{worse}/{P} converged | {ms:.1f} | {p99 * MM:.3f} | | {ratio} |")
            continue
        its = str(k) if k is not None else f"not within {kk} (time of {kk})"
        print(f"| {poses} | {name} | {its} | {ms:.1f} | {p99 * MM:.3f} | {worse}/{P} | "
              f"{'1.0x' if name == 'fit_pose_lm' else ratio} |")
    if pk_out is not None:
        pk_poses, e, f = args.poses[0], pk_out[True], pk_out[False]
        print(f"| {pk_poses} | pytorch-kinematics PseudoInverseIK, joint limits enforced "
              f"(its default) | cannot pose: {e['nan']}/{P} solutions NaN (the root's "
              f"continuous joints) | {e['ms']:.1f} | - | - | - |")
        print(f"| {pk_poses} | pytorch-kinematics PseudoInverseIK, limits off | cannot fit "
              f"21 joints: one end effector (l_hand, {f['dofs']}-DoF chain), one shared start, "
              f"no limits | {f['ms']:.1f} | hand only: p99 {f['err'] * MM:.3f} mm | - | - |")


if __name__ == "__main__":
    main()
