"""Time per frame of the Hauberg & Pedersen trackers: the data-driven importance distributions
against the angular prior at equal particles (the paper: about +10 % time).

Run:  python experiments/benchmarks/hauberg_proposals.py [--threads 1] [--particles 150]
                                                          [--frames 20] [--repeats 3]

Observations: the bundled CMU walk with its root held (the paper's subjects stand in place),
the ``stereo`` scenario (one viewpoint: left-camera silhouettes and a depth cloud of up to 2000
points). Trackers: the presets ``hauberg_angular``, ``hauberg_spatial``,
``hauberg_silhouette`` and ``hauberg_depth`` (upper body, point-cloud likelihood thinned to 400
points). Each tracker runs the whole clip ``--repeats`` times, the trackers taking turns (one round
times each once, after a warm-up round); the median seconds per frame, the median over rounds of
the ratio to the angular prior and the share spent in the proposal (``seconds`` of the
proposal's statistics) are printed. Run it on an idle machine: timings under load mean nothing.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

PRESETS = ["hauberg_angular", "hauberg_spatial", "hauberg_silhouette", "hauberg_depth"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--particles", type=int, default=150)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.synthetic.clips import synthesized_sequence

    seq = synthesized_sequence({"name": "walk", "path": None, "start": 1.0,
                                "frames": args.frames + 1, "in_place": True}, "stereo", {},
                               seed=0)
    rt = Runtime.from_sequence(seq)
    print(f"# torch {torch.__version__}, {args.threads} threads, {platform.machine()}, "
          f"{args.particles} particles, {args.frames} frames, stereo scenario "
          f"({int(seq.depth.counts.float().mean()) if hasattr(seq.depth, 'counts') else '?'} "
          "points per frame before thinning)")
    print("| tracker | s/frame (median of runs) | time / angular (median of per-round ratios) "
          "| proposal s/frame |")
    print("|---|---:|---:|---:|")
    cfgs = {name: tracker_config(name, [f"tracker.num_particles={args.particles}"])
            for name in PRESETS}
    times = {name: [] for name in PRESETS}
    props = {name: [] for name in PRESETS}
    # round robin: every round times each tracker once, so a slow spell of a shared machine
    # hits all of them and the per-round ratios to the angular prior stay comparable
    for r in range(args.repeats + 1):
        for name in PRESETS:
            tr = build_tracker(cfgs[name], rt, seed=r)
            t0 = time.perf_counter()
            track = tr.run(seq, progress=False)
            dt = (time.perf_counter() - t0) / args.frames
            if r == 0:
                continue  # warm-up
            times[name].append(dt)
            props[name].append(sum(float(i.proposal.get("seconds", 0.0))
                                   for i in track.infos[1:]) / args.frames)
    base = times[PRESETS[0]]
    for name in PRESETS:
        ratio = statistics.median(t / b for t, b in zip(times[name], base))
        print(f"| {name} | {statistics.median(times[name]):.3f} | x{ratio:.2f} "
              f"| {statistics.median(props[name]):.3f} |")

if __name__ == "__main__":
    main()
