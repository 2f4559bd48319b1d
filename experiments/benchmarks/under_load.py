"""The tracker beside a busy core: seconds per frame idle and under load, per thread policy.

Run (on an otherwise idle machine; it starts its own load):

    python experiments/benchmarks/under_load.py [--frames 10] [--busy 1] [--repeats 2]
    python experiments/benchmarks/under_load.py --frames 2 --particles 20 --layers 2   # check

Each measurement is a fresh process (so that the OpenMP settings of the environment apply)
tracking the bundled CMU walk (``studio``: 4 views at 320x240 + IMUs) with tracker ``p`` (200
particles x 15 layers by default); the first tracked frame is a warm-up, the others are timed.
"Under load" starts ``--busy`` processes spinning a Python loop (one core each) before the
tracker process and stops them after it. Policies:

* ``default``   — torch's default: one thread per core (what ``torchmocap-track`` did before
  its thread policy);
* ``passive``   — the same with ``OMP_WAIT_POLICY=PASSIVE`` (waiting threads sleep);
* ``auto``      — :mod:`torchmocap.threads` (``threads: auto``, the command's default): the free
  cores, measured when the process starts, re-checked between frames.

Printed: a markdown table with seconds per frame idle and under load, the threads each used,
and the slowdown under load relative to the same policy idle and to the ``default`` policy idle
(the target: <= 2.5x with one core busy).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

POLICIES = ("default", "passive", "auto")
SPIN = "while True:\n    pass\n"


def child(args) -> None:
    """One measurement (in its own process): prints a JSON line."""
    import torch

    from torchmocap.threads import ThreadGovernor

    if args.policy == "auto":
        governor = ThreadGovernor.start("auto", interval=args.recheck)
    else:  # torch's own default (one thread per physical core)
        governor = None
    threads0 = torch.get_num_threads()
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.synthetic.clips import synthesized_sequence

    size = [int(v) for v in args.image.split("x")]
    seq = synthesized_sequence({"frames": args.frames + 2}, "studio", {"image_size": size},
                               seed=0)
    tr = build_tracker(tracker_config("p", [f"tracker.num_particles={args.particles}",
                                            f"tracker.inference.layers={args.layers}"]),
                       Runtime.from_sequence(seq), seed=0)
    tracking = seq.imu.tracking.nonzero()[:, 0]
    st = tr.init(seq.ground_truth.theta[0], tr.observe(seq.frame(0), tracking))
    st, _, _ = tr.step(st, tr.observe(seq.frame(1), tracking))  # warm-up
    times, used = [], []
    for t in range(2, seq.num_frames):
        t0 = time.perf_counter()
        st, _, info = tr.step(st, tr.observe(seq.frame(t), tracking))
        times.append(time.perf_counter() - t0)
        used.append(torch.get_num_threads())
        if governor is not None:
            governor(st, info)
    print(json.dumps({"seconds": times, "threads_start": threads0, "threads": used,
                      "reason": None if governor is None else governor.initial.reason}))


def measure(policy: str, busy: int, args) -> dict:
    env = dict(os.environ)
    env.pop("OMP_NUM_THREADS", None)  # the policies decide
    env.pop("OMP_WAIT_POLICY", None)
    if policy == "passive":
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(busy)]
    try:
        if spinners:
            time.sleep(1.0)  # let them take their cores
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--policy", policy,
               "--frames", str(args.frames), "--particles", str(args.particles),
               "--layers", str(args.layers), "--image", args.image,
               "--recheck", str(args.recheck)]
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    finally:
        for p in spinners:
            p.kill()
            p.wait()
    if r.returncode != 0:
        raise SystemExit(f"measurement {policy} (busy {busy}) failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10, help="timed frames per measurement")
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--layers", type=int, default=15)
    ap.add_argument("--image", default="320x240", help="camera image size WxH")
    ap.add_argument("--busy", type=int, default=1, help="busy-loop processes under load")
    ap.add_argument("--repeats", type=int, default=1, help="measurements per cell (median)")
    ap.add_argument("--policies", nargs="+", default=list(POLICIES), choices=POLICIES)
    ap.add_argument("--recheck", type=float, default=5.0,
                    help="seconds between the auto policy's load checks")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--policy", default="auto", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    import torch

    print(f"# torch {torch.__version__}, {os.cpu_count()} CPUs "
          f"(affinity {len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else '?'}"
          f"), {platform.processor() or platform.machine()}; tracker p, "
          f"{args.particles} x {args.layers}, 4 views {args.image}; {args.frames} timed frames; "
          f"load: {args.busy} busy-loop process(es)")
    rows = {}
    for policy in args.policies:
        cell = {}
        for busy in (0, args.busy):
            runs = [measure(policy, busy, args) for _ in range(args.repeats)]
            sec = statistics.median(statistics.median(r["seconds"]) for r in runs)
            cell[busy] = (sec, runs[0])
        rows[policy] = cell
    ref = rows.get("default", next(iter(rows.values())))[0][0]
    print("| policy | threads idle | s/frame idle | threads under load | s/frame under load | "
          "slowdown (own idle) | slowdown (default idle) |")
    print("|---|---|---|---|---|---|---|")
    for policy, cell in rows.items():
        (s0, r0), (s1, r1) = cell[0], cell[args.busy]
        t1 = sorted(set(r1["threads"]))
        switched = "" if t1 == [r1["threads_start"]] else " -> " + "/".join(map(str, t1))
        print(f"| {policy} | {r0['threads_start']} | {s0:.3f} | {r1['threads_start']}{switched}"
              f" | {s1:.3f} | {s1 / s0:.2f}x | {s1 / ref:.2f}x |")
    auto = rows.get("auto")
    if auto and auto[args.busy][1].get("reason"):
        print(f"\nauto under load: {auto[args.busy][1]['reason']}")


if __name__ == "__main__":
    main()
