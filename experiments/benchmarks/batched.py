"""Batched seeds: sequence-frames per second of B seeds in one batch vs B separate runs.

Run (on an otherwise idle machine):

    python experiments/benchmarks/batched.py [--B 1 4 16] [--frames 12] [--threads 1] [--cli]
    python experiments/benchmarks/batched.py --B 1 2 --frames 2 --particles 20 --layers 2 \\
        --image 80x60 --cli          # a quick check that it runs
    python experiments/benchmarks/batched.py --device cuda                    # on a GPU

Tracker ``p`` (200 particles x 15 layers by default) on the bundled CMU walk, ``studio``
scenario (4 views at 320x240 + IMUs), one synthesised sequence tracked with seeds 0..B-1:

1. **in process, tracking only** — :func:`torchmocap.filters.track_seeds` (the
   particles of all B seeds evaluated in one energy call per layer) vs B ``tracker.run`` calls
   one after the other; sequence-frames per second = B x tracked frames / seconds. Each is
   warmed up once.
2. **end to end** (``--cli``) — ``torchmocap-track batch_seeds=[0..B-1] data.seed=0`` (one
   process) vs B processes ``torchmocap-track seed=s data.seed=0`` run one after the other,
   start-up, synthesis and outputs included (``overlays=0 glb.enabled=false``).

``--threads`` sets torch's threads (in the CLI runs through ``threads=``); with 1 thread the two
sides use one core each way, so the ratio is the batching's own gain.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

EXE = str(Path(sys.executable).parent / "torchmocap-track")


def in_process(Bs, args) -> list[str]:
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.data.synthetic.clips import synthesized_sequence
    from torchmocap.filters.tracking.batched import track_seeds

    size = [int(v) for v in args.image.split("x")]
    seq = synthesized_sequence({"frames": args.frames + 1}, "studio", {"image_size": size},
                               seed=0)
    tr = build_tracker(tracker_config("p", [f"tracker.num_particles={args.particles}",
                                            f"tracker.inference.layers={args.layers}"]),
                       Runtime.from_sequence(seq), seed=0).to(args.device)
    n = seq.num_frames - 1

    def sync():
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    def separate(B):
        for s in range(B):
            tr.seed = s
            tr.run(seq, progress=False)

    def batched(B):
        track_seeds(tr, seq, list(range(B)), progress=False, max_batch=args.max_batch)

    separate(1)  # warm-up (caches, allocator)
    batched(2)
    rows = []
    for B in Bs:
        out = {}
        for label, fn in (("separate", separate), ("batched", batched)):
            sync()
            t0 = time.perf_counter()
            fn(B)
            sync()
            out[label] = B * n / (time.perf_counter() - t0)
        rows.append(f"| {B} | {out['separate']:.2f} | {out['batched']:.2f} | "
                    f"{out['batched'] / out['separate']:.2f}x |")
    return rows


def end_to_end(Bs, args) -> list[str]:
    common = [f"data.clip.frames={args.frames + 1}", "data.seed=0",
              f"tracker.num_particles={args.particles}",
              f"tracker.inference.layers={args.layers}", "overlays=0", "glb.enabled=false",
              "progress=false", f"threads={args.threads}", "skip_completed=false"]
    if args.image != "320x240":
        w, h = args.image.split("x")
        common.append(f"+data.scenario_overrides.image_size=[{w},{h}]")
    env = dict(os.environ)
    env.pop("OMP_NUM_THREADS", None)
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="torchmocap-batched-"))
    try:
        def call(extra, out):
            r = subprocess.run([EXE, *common, *extra, f"hydra.run.dir={out}"],
                               capture_output=True, text=True, env=env, cwd=tmp)
            if r.returncode != 0:
                raise SystemExit(f"torchmocap-track failed:\n{r.stderr[-3000:]}")

        for B in Bs:
            t0 = time.perf_counter()
            for s in range(B):
                call([f"seed={s}"], tmp / f"sep_{B}_{s}")
            t_sep = time.perf_counter() - t0
            t0 = time.perf_counter()
            call([f"batch_seeds=[{','.join(str(s) for s in range(B))}]"], tmp / f"batch_{B}")
            t_bat = time.perf_counter() - t0
            n = B * args.frames
            rows.append(f"| {B} | {t_sep:.1f} s, {n / t_sep:.2f} | {t_bat:.1f} s, "
                        f"{n / t_bat:.2f} | {t_sep / t_bat:.2f}x |")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--B", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--frames", type=int, default=12, help="tracked frames per sequence")
    ap.add_argument("--particles", type=int, default=200)
    ap.add_argument("--layers", type=int, default=15)
    ap.add_argument("--image", default="320x240", help="camera image size WxH")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--max-batch", type=int, default=None,
                    help="most particles per energy call in the batched runs (default: all)")
    ap.add_argument("--cli", action="store_true", help="also the end-to-end process comparison")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dev = torch.cuda.get_device_name() if args.device.startswith("cuda") else \
        (platform.processor() or platform.machine())
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.device} "
          f"({dev}); tracker p, {args.particles} x {args.layers}, 4 views {args.image}, "
          f"{args.frames} tracked frames per sequence; max batch "
          f"{args.max_batch or 'all'} particles")
    print("\nIn process, tracking only (sequence-frames/s):\n")
    print("| B | B separate runs | one batch of B | speed-up |")
    print("|---|---|---|---|")
    print("\n".join(in_process(args.B, args)))
    if args.cli:
        print("\nEnd to end, torchmocap-track processes (wall time, sequence-frames/s):\n")
        print("| B | B separate processes | one process, batch_seeds | speed-up |")
        print("|---|---|---|---|")
        print("\n".join(end_to_end(args.B, args)))


if __name__ == "__main__":
    main()
