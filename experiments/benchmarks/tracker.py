"""Tracker throughput: likelihood evaluations per second and frames per second of preset ``p``,
and the real-frame annealing beside PARSEC bodytrack's C++ one.

Run:  python experiments/benchmarks/tracker.py [--threads 2] [--frames 12] [--compile]
                                               [--repeats 7] [--baseline DIR]

1. Silhouette (+ appearance) likelihood throughput: particle-view evaluations per second for
   200 particles x 4 views at 320x240 (the energy of one annealing layer), through the
   assembled likelihood (:class:`~torchmocap.likelihoods.FrameEnergy`).
2. Tracker ``p`` as built from ``conf/tracker/p.yaml`` (Pons-Moll: manifold sampling + vMF,
   200 particles x 15 layers, 4 views at 320x240, silhouettes + appearance) on the bundled CMU
   walk in the ``studio`` scenario: frames per second (target >= 10 on 2 CPU cores), also with
   the appearance term switched off (``tracker.likelihood.weights.appearance=0``). With
   ``--compile`` every row also for the compiled components (:data:`COMPILED`), the two
   trackers' frames in alternation.
3. The real bodytrack frame at full resolution (4 views, 640x480): our annealing on its
   silhouettes beside PARSEC bodytrack's C++ annealed particle filter, built from its sources
   (``../shared/peers/parsec_bodytrack`` or ``--peer``) into a temporary folder and run on the
   same frame with 1 and 2 threads, 200 x 15 and 4000 x 5, interleaved with ours (``--repeats``
   rounds, medians; see :func:`real_frame`). Without a C++ compiler or without ``../shared``
   these rows are skipped with the reason.

``--baseline DIR`` instead times tracker ``p`` of another checkout (e.g. a ``git worktree`` of an
older commit) beside this one: each in a worker process driven by this script, one frame at a time
in alternation (``--rounds`` frames each), and prints both medians and the median per-frame ratio —
a before/after measured in one run, robust to the host's drift.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch
from timing import median_ms

REPO = Path(__file__).resolve().parents[2]


def _median(fn, repeats):
    """Median seconds of ``fn()`` after one untimed call."""
    return median_ms(fn, repeats, warmup=1) / 1e3


#: the overrides of the compiled variant of tracker p (every compile option of its components)
COMPILED = ["tracker.likelihood.terms.silhouette.compile=true",
            "tracker.likelihood.terms.appearance.compile=true", "tracker.proposal.compile=true"]


def measure(frames: int, compiled: bool = False) -> list[str]:
    """The benchmark rows (markdown) of this checkout; ``compiled`` adds the compiled variant
    (:data:`COMPILED`) of every row, its frames interleaved with the eager ones."""
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import synthesize
    from torchmocap.io import bundled_clip_path, load_motion
    from torchmocap.likelihoods import FrameEnergy

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, frames + 1)
    seq = synthesize(fit_subject(clip), "studio", seed=0)
    rt = Runtime.from_sequence(seq)
    sk, rig = rt.skeleton, rt.rig
    tracking = seq.imu.tracking.nonzero()[:, 0]
    g = torch.Generator().manual_seed(0)
    theta = seq.ground_truth.theta[1].float() + 0.05 * torch.randn(200, sk.num_dofs,
                                                                    generator=g)
    rows = []
    C = rig.num_cameras
    variants = [("", [])] + ([(", compiled", COMPILED)] if compiled else [])
    from torchmocap.filters import Tracker

    frame = Tracker.observe(seq.frame(1), tracking)
    for name, ov in variants:
        image = build_tracker(tracker_config("p", ov), rt).likelihood
        silh = build_tracker(tracker_config("p", ov + ["tracker.likelihood.weights.appearance=0"]),
                             rt).likelihood
        for label, lik in (("silhouette likelihood", silh), ("silhouette + appearance", image)):
            V = FrameEnergy(lik, lik.prepare(frame), sk)
            with torch.no_grad():
                t = _median(lambda V=V: V(theta), 20)
            rows.append(f"| {label}{name}, 200 particles x {C} views | {1e3 * t:.1f} ms | "
                        f"{200 * C / t:,.0f} particle-views/s |")
    obs = [Tracker.observe(seq.frame(t), tracking) for t in range(seq.num_frames)]
    for overrides, label in (([], "silhouette + appearance"),
                             (["tracker.likelihood.weights.appearance=0"], "silhouette only")):
        runs = []
        for name, ov in variants:
            tr = build_tracker(tracker_config("p", overrides + ov), Runtime.from_sequence(seq),
                               seed=0)
            st = tr.init(seq.ground_truth.theta[0].float(), obs[0])
            st, _, _ = tr.step(st, obs[1])  # warm-up (and compilation)
            runs.append([name, tr, st, []])
        for t in range(2, seq.num_frames):  # the variants' frames in alternation
            for r in (runs if t % 2 == 0 else runs[::-1]):
                t0 = time.perf_counter()
                r[2], _, _ = r[1].step(r[2], obs[t])
                r[3].append(time.perf_counter() - t0)
        for name, _, _, ts in runs:
            dt = statistics.median(ts)
            rows.append(f"| tracker p, 200 x 15, {C} views 320x240, {label}{name} | "
                        f"{dt:.3f} s/frame (median of {len(ts)}) | {1 / dt:.2f} frames/s "
                        "(target >= 10 with appearance) |")
    return rows


def _real_frame_anneal(root: Path, particles: int, layers: int, compiled: bool):
    """``(run, load_and_run)`` of our real-frame annealing: ``run()`` anneals ``particles x
    layers`` on the prepared frame (the timed region of the "annealing" rows: the energy — forward
    kinematics, capsules, silhouette term — and the annealing loop: selection, diffusion,
    bounds, β, weights, estimate); ``load_and_run()`` also reads the frame (calibration, grey
    images and masks) and prepares its silhouettes first. Starts: the zero pose at the subject's
    place plus 5 cm / 0.05 rad of Gaussian noise per DoF (seed 0); annealing seed 1."""
    from torchmocap.body import CapsuleBody
    from torchmocap.data.recordings.bodytrack import load_bodytrack
    from torchmocap.filters.optim.anneal import anneal, default_diffusion
    from torchmocap.likelihoods import FrameEnergy, SilhouetteLikelihood
    from torchmocap.skeleton import human31

    sk = human31()
    body = CapsuleBody(sk)
    x0 = sk.zero_pose() + 0.05 * torch.randn(particles, sk.num_dofs,
                                             generator=torch.Generator().manual_seed(0))
    x0[:, 0] += 0.15
    x0[:, 1] += 0.9
    lik = {}

    def load():
        rig, _, masks = load_bodytrack(root)
        if "term" not in lik:  # the term (and its compiled energy) is built once
            lik["term"] = SilhouetteLikelihood(body, rig.float(), fg_samples=64,
                                               compile=compiled)
        frame = SimpleNamespace(silhouettes=masks, view_dropped=None)
        return FrameEnergy(lik["term"], lik["term"].prepare(frame), sk)

    energy = load()

    def run(V=None):
        return anneal(V or energy, x0, layers=layers, diffusion=default_diffusion(layers),
                      lower=sk.lower, upper=sk.upper,
                      generator=torch.Generator().manual_seed(1))

    return run, lambda: run(load())


def _timed(fn) -> tuple[float, float]:
    """Wall and CPU (all threads of this process) seconds of ``fn()``."""
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    return time.perf_counter() - t0, time.process_time() - c0


def real_frame(repeats: int, threads: int, peer_dir: Path, frame_dir: Path,
               compiled: bool = False) -> list[str]:
    """Our real-frame annealing and PARSEC bodytrack's, interleaved, as markdown lines.

    Per workload (200 x 15, 4000 x 5) and round: PARSEC with 1 thread (serial code) and with 2
    (OpenMP), each with the workload's layers and with one layer (for its annealing-only
    estimate, :func:`bodytrack_peer.anneal_only`), then our annealing and our load + prepare +
    annealing on ``threads`` threads (eager, and with ``compiled`` also the compiled energy);
    every other round in the reverse order, so both sides see the same load. Medians over the
    rounds. PARSEC's times are whole processes (start, calibration and image loading, edge
    maps, the initial weighting, the layers, the pose file); ours are in-process (the
    interpreter's start and imports excluded), see :func:`_real_frame_anneal`."""
    import bodytrack_peer as bp

    med = statistics.median
    try:
        peer = bp.Peer(peer_dir, frame_dir)
    except bp.PeerUnavailable as e:
        return [f"PARSEC bodytrack rows skipped: {e}"]
    variants = ["eager"] + (["compiled"] if compiled else [])
    lines = []
    with peer:
        lines.append(f"PARSEC bodytrack built from {peer_dir} in {peer.build_seconds:.1f} s; "
                     f"load average at the start {os.getloadavg()[0]:.2f}; {repeats} rounds")
        for particles, layers in ((200, 15), (4000, 5)):
            steps = [(f"p{n}_{k}", functools.partial(peer.run, particles, k, n))
                     for n in (1, 2) for k in (layers, 1)]
            for v in variants:
                run, load_and_run = _real_frame_anneal(frame_dir, particles, layers,
                                                       v == "compiled")
                t0 = time.perf_counter()
                run()  # warm-up (and compilation)
                if v == "compiled":
                    lines.append(f"(compiling and a first {particles} x {layers} pass: "
                                 f"{time.perf_counter() - t0:.1f} s)")
                steps += [(v, functools.partial(_timed, run)),
                          (f"{v}_load", functools.partial(_timed, load_and_run))]
            got: dict[str, list[tuple[float, float]]] = {name: [] for name, _ in steps}
            for i in range(repeats):
                for name, fn in (steps if i % 2 == 0 else steps[::-1]):
                    r = fn()
                    got[name].append((r.wall, r.cpu) if isinstance(r, bp.PeerRun) else r)
            wall = {k: med(w for w, _ in v) for k, v in got.items()}
            cpu = {k: med(c for _, c in v) for k, v in got.items()}
            est = {n: bp.anneal_only(wall[f"p{n}_{layers}"], wall[f"p{n}_1"], layers)
                   for n in (1, 2)}
            est_cpu = {n: bp.anneal_only(cpu[f"p{n}_{layers}"], cpu[f"p{n}_1"], layers)
                       for n in (1, 2)}
            lines += ["", f"| {particles} x {layers}, 4 views 640x480 | wall s (median) | "
                          "CPU s (median) |", "|---|---|---|"]
            for v in variants:
                lines += [f"| ours ({v} energy, {threads} threads): annealing | {wall[v]:.3f} | "
                          f"{cpu[v]:.3f} |",
                          f"| ours ({v}): load + prepare + annealing | {wall[v + '_load']:.3f} | "
                          f"{cpu[v + '_load']:.3f} |"]
            for n in (1, 2):
                th = f"{n} thread{'s' * (n > 1)}"
                lines += [f"| PARSEC {th}: whole process | {wall[f'p{n}_{layers}']:.3f} | "
                          f"{cpu[f'p{n}_{layers}']:.3f} |",
                          f"| PARSEC {th}: annealing (est.) | {est[n]:.3f} | {est_cpu[n]:.3f} |"]
            best = min((1, 2), key=lambda n: wall[f"p{n}_{layers}"])
            for n, which in ((best, "its faster configuration"),
                             (threads, "the same number of threads")):
                if n not in (1, 2) or (n == best and which != "its faster configuration"):
                    continue  # no second list when the same-threads one is the faster one
                whole = wall[f"p{n}_{layers}"]
                lines.append(f"\nratios PARSEC / ours (> 1: ours faster), wall medians, PARSEC "
                             f"with {which} ({n} thread{'s' * (n > 1)}):")
                for v in variants:
                    lines.append(f"- {v}: whole process vs our load + prepare + annealing "
                                 f"{whole / wall[v + '_load']:.2f}x; whole process vs our "
                                 f"annealing {whole / wall[v]:.2f}x; annealing (est.) vs our "
                                 f"annealing {est[n] / wall[v]:.2f}x")
        lines.append(f"\nload average at the end {os.getloadavg()[0]:.2f}")
    return lines


#: the parts of a frame :func:`profile` reports: (label, file, function) of cProfile entries
PARTS = [("annealing, all layers", "anneal.py", "anneal"),
         ("energy (FrameEnergy)", "base.py", "__call__"),
         ("- forward kinematics (Poses.kinematics)", "base.py", "kinematics"),
         ("- capsule ends incl. kinematics (Poses.endpoints)", "base.py", "endpoints"),
         ("- silhouette term (after its capsule ends)", "silhouette.py", "energy"),
         ("- appearance term", "appearance.py", "energy"),
         ("proposal draws (ManifoldProposal.sample)", "manifold.py", "sample"),
         ("diffusion (CovarianceDiffusion)", "anneal.py", "__call__"),
         ("ESS-targeted beta (ess_target_beta)", "schedules.py", "ess_target_beta"),
         ("selection (resampler)", "resampling.py", "__call__")]


def profile(frames: int, compiled: bool, frame_dir: Path) -> list[str]:
    """cProfile of tracker ``p`` (``frames`` frames after a warm-up) and of the real-frame
    200 x 15 annealing (5 passes): the cumulative time of each part of :data:`PARTS` and its
    share of the total (the parts nest: the energy holds its terms; the term that asks for the
    capsule ends first pays for them, so the terms are given without them)."""
    import cProfile
    import pstats

    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import synthesize
    from torchmocap.filters import Tracker
    from torchmocap.io import bundled_clip_path, load_motion

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, frames + 1)
    seq = synthesize(fit_subject(clip), "studio", seed=0)
    tracking = seq.imu.tracking.nonzero()[:, 0]
    obs = [Tracker.observe(seq.frame(t), tracking) for t in range(seq.num_frames)]
    tr = build_tracker(tracker_config("p", COMPILED if compiled else []),
                       Runtime.from_sequence(seq), seed=0)

    def track():
        st = tr.init(seq.ground_truth.theta[0].float(), obs[0])
        for t in range(1, seq.num_frames):
            st = tr.step(st, obs[t])[0]

    variant = "compiled" if compiled else "eager"
    jobs = [(f"tracker p ({variant}), {frames} frames", track)]
    if (frame_dir / "CALIB").is_dir():
        run, _ = _real_frame_anneal(frame_dir, 200, 15, compiled)
        jobs.append((f"real frame, 200 x 15 ({variant}), 5 passes",
                     lambda: [run() for _ in range(5)]))
    lines = []
    for label, fn in jobs:
        fn()  # warm-up (and compilation)
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.runcall(fn)
        total = time.perf_counter() - t0
        stats = pstats.Stats(prof).stats
        cum = {}
        for (file, _, name), v in stats.items():
            key = (Path(file).name, name)
            cum[key] = cum.get(key, 0.0) + v[3]
        ends = cum.get(("base.py", "endpoints"), 0.0)
        lines += ["", f"| {label} (profiled {total:.2f} s) | cumulative s | share |",
                  "|---|---|---|"]
        for part, file, name in PARTS:
            if (file, name) not in cum:
                continue
            t = cum[(file, name)]
            if file == "silhouette.py":
                t -= ends  # the first term asked for the capsule ends
            lines.append(f"| {part} | {t:.3f} | {100 * t / total:.1f}% |")
    return lines


def _worker(threads: int, frames: int, appearance: bool) -> None:
    """Serve one tracker ``p`` of the checkout on ``sys.path``: build it, print ``ready``, then
    time one frame per ``step`` line read from stdin (wall seconds, one line each). The frames
    cycle through the clip; each cycle restarts from the truth at frame 0 (untimed), so every
    cycle does the same work. Drives the pre-redesign API (``Tracker(body, rig,
    TrackerConfig)``) as well as the assembled one."""
    torch.set_num_threads(threads)
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import synthesize
    from torchmocap.io import bundled_clip_path, load_motion

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, frames + 1)
    seq = synthesize(fit_subject(clip), "studio", seed=0)
    tracking = seq.imu.tracking.nonzero()[:, 0]
    import torchmocap

    # an editable install's import hook would find this checkout's modules by name, so look
    if not (Path(torchmocap.__file__).parent / "assembly.py").is_file():
        # before the components redesign (e8e4446 and older)
        from torchmocap.body import CapsuleBody
        from torchmocap.filters.tracking.tracker import Tracker, TrackerConfig, frame_observation

        sk = seq.ground_truth.build_skeleton().float()
        sensors = {n: b for n, b, t in zip(seq.imu.names, seq.imu.bones,
                                            seq.imu.tracking.tolist()) if t}
        tr = Tracker(CapsuleBody(sk), seq.rig.float(),
                     TrackerConfig(method="p", w_app=40.0 if appearance else 0.0),
                     sensors=sensors, seed=0)
        observe = frame_observation
    else:
        from torchmocap.assembly import Runtime, build_tracker, tracker_config

        ov = [] if appearance else ["tracker.likelihood.weights.appearance=0"]
        tr = build_tracker(tracker_config("p", ov), Runtime.from_sequence(seq), seed=0)
        observe = tr.observe
    obs = [observe(seq.frame(t), tracking) for t in range(seq.num_frames)]
    theta0 = seq.ground_truth.theta[0].float()

    def restart():
        st = tr.init(theta0, obs[0])
        return tr.step(st, obs[1])[0]

    st, t = restart(), 2
    print("ready", flush=True)
    for line in sys.stdin:
        if not line.strip():
            break
        if t >= len(obs):
            st, t = restart(), 2
        t0 = time.perf_counter()
        st = tr.step(st, obs[t])[0]
        print(time.perf_counter() - t0, flush=True)
        t += 1


class _Worker:
    """A :func:`_worker` subprocess running this script with ``checkout`` on its path."""

    def __init__(self, checkout: Path, threads: int, frames: int, appearance: bool):
        env = dict(os.environ, PYTHONPATH=str(checkout), OMP_NUM_THREADS=str(threads))
        args = [sys.executable, str(Path(__file__).resolve()), "--worker", "--threads",
                str(threads), "--frames", str(frames)]
        self.proc = subprocess.Popen(args + ([] if appearance else ["--no-appearance"]),
                                     cwd=checkout, env=env, text=True, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        if self.proc.stdout.readline().strip() != "ready":
            raise SystemExit(f"worker in {checkout} failed:\n{self.proc.stderr.read()[-2000:]}")

    def step(self) -> float:
        self.proc.stdin.write("step\n")
        self.proc.stdin.flush()
        return float(self.proc.stdout.readline())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def before_after(baseline: Path, threads: int, frames: int, rounds: int) -> None:
    """Tracker ``p`` of ``baseline`` and of this checkout, frame by frame in alternation.

    Both run in worker processes with the same harness; the frames are interleaved ``A B B A``
    so the two share the host's drift (on a shared machine the speed of a core changes by up to
    2x within minutes, which made separate runs of each checkout disagree by more than the
    difference being measured). Prints each side's median s/frame and the median of the
    per-frame ratios with its interquartile range."""
    here = Path(__file__).resolve().parents[2]
    print(f"| tracker p, 200 x 15 ({rounds} frames each, interleaved) | baseline {baseline.name} "
          f"s/frame | this checkout s/frame | speed ratio (baseline / this), IQR |")
    print("|---|---|---|---|")
    for appearance, label in ((True, "silhouette + appearance"), (False, "silhouette only")):
        a = _Worker(baseline, threads, frames, appearance)
        b = _Worker(here, threads, frames, appearance)
        ta, tb = [], []
        for i in range(rounds):
            order = (a, b) if i % 2 == 0 else (b, a)
            for w in order:
                (ta if w is a else tb).append(w.step())
        a.close()
        b.close()
        q = statistics.quantiles([x / y for x, y in zip(ta, tb)], n=4)
        print(f"| {label} | {statistics.median(ta):.3f} | {statistics.median(tb):.3f} | "
              f"{statistics.median([x / y for x, y in zip(ta, tb)]):.2f}x "
              f"({q[0]:.2f}-{q[2]:.2f}) |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--baseline", type=Path, default=None,
                    help="another checkout to time in the same run (before/after)")
    ap.add_argument("--rounds", type=int, default=60,
                    help="frames timed per checkout with --baseline")
    ap.add_argument("--no-bodytrack", action="store_true", help="skip the real-frame rows")
    ap.add_argument("--only-bodytrack", action="store_true",
                    help="only the real-frame rows (ours beside PARSEC)")
    ap.add_argument("--repeats", type=int, default=7,
                    help="interleaved rounds of the real-frame rows")
    ap.add_argument("--compile", action="store_true",
                    help="also the compiled variants: tracker p with every compile option of "
                         "its components, the real-frame energy with the silhouette term's")
    ap.add_argument("--peer", type=Path, default=REPO.parent / "shared" / "peers" /
                    "parsec_bodytrack", help="PARSEC bodytrack's sources (with build.sh)")
    ap.add_argument("--frame", type=Path, default=REPO.parent / "shared" / "data" /
                    "multiview" / "bodytrack_sequenceB_1", help="the bodytrack frame folder")
    ap.add_argument("--profile", action="store_true",
                    help="only cProfile tables of tracker p and the real-frame annealing")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--no-appearance", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(args.threads, args.frames, not args.no_appearance)
        return
    torch.set_num_threads(args.threads)
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}")
    if args.profile:
        print("\n".join(profile(args.frames, args.compile, args.frame.resolve())))
        return
    if args.baseline is None:
        if not args.only_bodytrack:
            print("| workload | time | throughput |")
            print("|---|---|---|")
            print("\n".join(measure(args.frames, args.compile)))
        if not args.no_bodytrack:
            print("\n".join(real_frame(args.repeats, args.threads, args.peer.resolve(),
                                       args.frame.resolve(), args.compile)))
        return
    before_after(args.baseline.resolve(), args.threads, args.frames, args.rounds)


if __name__ == "__main__":
    main()
