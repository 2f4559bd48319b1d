"""Compiled components against eager ones: the same tracker over seeds, accuracy and speed.

Run:  python experiments/benchmarks/compiled.py [--tracker p] [--seeds 8] [--frames 25]
                                                [--threads 1]

The compile options (``compile: true`` of the silhouette and appearance terms and of the
manifold proposal, :mod:`torchmocap.compilation`) round differently from the eager code, so a
compiled track is not the eager track bit for bit: a particle tracker amplifies last-bit
differences over frames. What must hold is that the two are statistically equivalent. Both
variants track the bundled walk (``studio`` scenario, observations synthesised with seed 0) with
tracker seeds ``0 .. seeds-1``; the script prints each variant's mean orientation error and
MPJPE over the seeds, the paired differences (compiled − eager) with a 95 % interval (t
distribution over seeds), and the median seconds per frame (the two variants' seeds in
alternation; the first, compiling, run excluded).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

#: every compile option of tracker p's components
COMPILED = ["tracker.likelihood.terms.silhouette.compile=true",
            "tracker.likelihood.terms.appearance.compile=true", "tracker.proposal.compile=true"]


def _t95(n: int) -> float:
    """Two-sided 95 % quantile of Student's t with ``n - 1`` degrees of freedom."""
    from scipy.stats import t

    return float(t.ppf(0.975, n - 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tracker", default="p")
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--frames", type=int, default=25)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import synthesize
    from torchmocap.evaluation.truth import track_errors
    from torchmocap.io import bundled_clip_path, load_motion

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, args.frames)
    seq = synthesize(fit_subject(clip), "studio", seed=0)
    errors: dict[str, list[tuple[float, float]]] = {"eager": [], "compiled": []}
    seconds: dict[str, list[float]] = {"eager": [], "compiled": []}
    for s in range(args.seeds):
        order = ("eager", "compiled") if s % 2 == 0 else ("compiled", "eager")
        for variant in order:
            ov = COMPILED if variant == "compiled" else []
            tr = build_tracker(tracker_config(args.tracker, ov), Runtime.from_sequence(seq),
                               seed=s)
            t0 = time.perf_counter()
            track = tr.run(seq, progress=False)
            dt = (time.perf_counter() - t0) / (seq.num_frames - 1)
            if s > 0:
                seconds[variant].append(dt)
            summ = track_errors(seq, tr.skeleton, track.theta)["summary"]
            errors[variant].append((summ["orientation_error_deg"]["mean"],
                                    summ["mpjpe_mm"]["mean"]))
    n = args.seeds
    print(f"# torch {torch.__version__}, {args.threads} thread(s); tracker {args.tracker}, "
          f"bundled walk, {seq.num_frames} frames, seeds 0..{n - 1}")
    print("| variant | orientation error (deg), mean over seeds | MPJPE (mm) | s/frame (median) |")
    print("|---|---|---|---|")
    for v in ("eager", "compiled"):
        o = statistics.mean(e[0] for e in errors[v])
        m = statistics.mean(e[1] for e in errors[v])
        sec = statistics.median(seconds[v]) if seconds[v] else float("nan")
        print(f"| {v} | {o:.2f} | {m:.1f} | {sec:.3f} |")
    for k, name in ((0, "orientation error (deg)"), (1, "MPJPE (mm)")):
        d = [c[k] - e[k] for c, e in zip(errors["compiled"], errors["eager"])]
        mean = statistics.mean(d)
        half = _t95(n) * statistics.stdev(d) / n**0.5 if n > 1 else float("nan")
        spread = statistics.stdev(e[k] for e in errors["eager"]) if n > 1 else float("nan")
        print(f"\ncompiled - eager, {name}: {mean:+.3f} (95 % interval {mean - half:+.3f} .. "
              f"{mean + half:+.3f}; spread over seeds of the eager runs {spread:.3f})")


if __name__ == "__main__":
    main()
