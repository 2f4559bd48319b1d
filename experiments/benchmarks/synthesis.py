"""Benchmark: observation synthesis of a 10 s clip (250 frames at 25 fps).

Run:  python experiments/benchmarks/synthesis.py [--threads 2] [--clip PATH] [--scenario studio]
      [--frames 250] [--repeats 1] [--markdown]

A real CMU walk (``../shared/data/mocap/cmu/131_02.bvh`` beside the checkout, else the bundled
4 s clip played forwards and backwards to the requested length) is resampled to 25 fps and
fitted once (``fit_subject``, timed separately); then ``synthesize`` renders the skinned CC0 mesh
into 4 cameras at 320×240 (silhouettes with the scenario's corruptions and colour images), 10
IMUs, one depth camera (160×120 point clouds) and 2D joints. Reported: wall-clock and process
CPU seconds per stage (best of repeats), and the time to save the sequence (npz + PNGs).
Target: synthesis under 60 s on 2 cores.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from torchmocap.data import load_scenario, synthesize
from torchmocap.data.subject import fit_subject
from torchmocap.io import bundled_clip_path, load_motion

SHARED_CLIP = Path(__file__).resolve().parents[3] / "shared" / "data" / "mocap" / "cmu" / \
    "131_02.bvh"


def _subject(path: Path | None, frames: int, fps: float):
    if path is None and SHARED_CLIP.is_file():
        path = SHARED_CLIP
    clip = load_motion(path if path is not None else bundled_clip_path()).resample(fps)
    source = str(path) if path is not None else "bundled cmu_131_01_walk (ping-pong)"
    t0 = time.perf_counter()
    subject = fit_subject(clip.slice(0, min(frames, clip.num_frames)))
    fit_s = time.perf_counter() - t0
    if subject.num_frames < frames:  # ping-pong the fitted motion to the requested length
        idx = []
        fwd = list(range(subject.num_frames)) + list(range(subject.num_frames - 2, 0, -1))
        while len(idx) < frames:
            idx += fwd
        idx = torch.tensor(idx[:frames])
        subject = replace(subject, theta=subject.theta[idx], positions=subject.positions[idx],
                          rotations=subject.rotations[idx], residual=subject.residual[idx],
                          rotation_residual=subject.rotation_residual[idx])
    return subject, fit_s, source


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--clip", type=Path, default=None)
    ap.add_argument("--scenario", nargs="+", default=["studio", "outdoor"])
    ap.add_argument("--frames", type=int, default=250)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-save", action="store_true")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    subject, fit_s, source = _subject(args.clip, args.frames, 25.0)
    synthesize(subject, args.scenario[0], seed=0, frames=2)  # warm-up (asset load, imports)
    rows = []
    for name in args.scenario:
        sc = load_scenario(name)
        best = None
        for r in range(args.repeats):
            c0, w0 = time.process_time(), time.perf_counter()
            seq = synthesize(subject, sc, seed=r)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            if best is None or wall < best[0]:
                best = (wall, cpu, seq.meta["timings"])
        save_s = float("nan")
        if not args.no_save:
            with tempfile.TemporaryDirectory() as d:
                t0 = time.perf_counter()
                seq.save(Path(d) / "sequence")
                save_s = time.perf_counter() - t0
        rows.append((name, seq.num_frames, best, save_s, int(seq.depth.counts.float().mean())))
    print(f"# synthesis benchmark: {platform.processor() or platform.machine()}, "
          f"torch {torch.__version__}, {args.threads} threads; clip {source}; "
          f"fit_subject {fit_s:.1f} s")
    head = ("| scenario | frames | synthesize wall s | CPU s | pose | render | corrupt | imu | "
            "depth | save s | depth pts/frame |")
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for name, T, (wall, cpu, tm), save_s, npts in rows:
        print(f"| {name} | {T} | {wall:.1f} | {cpu:.1f} | {tm.get('pose_s', 0):.1f} | "
              f"{tm.get('render_s', 0):.1f} | {tm.get('corrupt_s', 0):.1f} | "
              f"{tm.get('imu_s', 0):.2f} | {tm.get('depth_s', 0):.1f} | {save_s:.1f} | {npts} |")


if __name__ == "__main__":
    main()
