"""Benchmark: observation synthesis of a 10 s clip (250 frames at 25 fps).

Run:  python experiments/benchmarks/synthesis.py [--threads 2] [--clip PATH] [--scenario studio]
      [--frames 250] [--repeats 1] [--no-save] [--peer]

A real CMU walk (``../shared/data/mocap/cmu/131_02.bvh`` beside the checkout, else the bundled
4 s clip played forwards and backwards to the requested length) is resampled to 25 fps and
fitted once (``fit_subject``, timed separately); then ``synthesize`` renders the skinned CC0 mesh
into 4 cameras at 320×240 (silhouettes with the scenario's corruptions and colour images), 10
IMUs, one depth camera (160×120 point clouds) and 2D joints. Reported: wall-clock and process
CPU seconds per stage (best of repeats), and the time to save the sequence (npz + PNGs).
Target: synthesis under 60 s on 2 cores.

``--peer`` also times the silhouette rasteriser against the tool a user would otherwise reach
for on a CPU without an OpenGL context: a Python loop of ``PIL.ImageDraw.polygon`` per triangle
(masks only, same projected mesh), and reports the pixel agreement of the two.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from torchmocap.data.subjects.mocap import fit_subject
from torchmocap.data.synthetic import load_scenario, synthesize
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


def _peer(subject, images: int = 32) -> str:
    """Masks of ``images`` views: ours (vectorised torch) vs a PIL polygon loop."""
    import copy

    import numpy as np
    from PIL import Image, ImageDraw

    from torchmocap.data.synthetic import build_rig
    from torchmocap.data.synthetic.render import rasterize_mask
    from torchmocap.data.synthetic.synthesis import body_surface

    rig = build_rig("ring4", [320, 240]).float()
    T = images // rig.num_cameras
    theta = subject.theta[:T].float().clone()
    theta[:, :2] -= subject.positions[:T, 0, :2].float().mean(0)
    surf = body_surface(copy.deepcopy(subject.skeleton).float(), theta)
    pix, z, _ = rig.project(surf.vertices)
    pix, z = pix.reshape(T * 4, -1, 2), z.reshape(T * 4, -1)
    t_ours = float("inf")
    for _ in range(3):  # best of 3 (the first call also warms up)
        t0 = time.perf_counter()
        ours = rasterize_mask(pix, z, surf.faces, 320, 240)
        t_ours = min(t_ours, time.perf_counter() - t0)
    faces = surf.faces.numpy()
    t0 = time.perf_counter()
    peer = []
    for b in range(pix.shape[0]):
        im = Image.new("1", (320, 240))
        draw = ImageDraw.Draw(im)
        tri = pix[b].numpy()[faces]  # (F, 3, 2)
        for t in tri.tolist():
            draw.polygon([tuple(v) for v in t], fill=1)
        peer.append(np.asarray(im))
    t_peer = time.perf_counter() - t0
    peer_t = torch.from_numpy(np.stack(peer))
    iou = float((ours & peer_t).sum() / (ours | peer_t).sum())
    return (f"silhouette rasteriser, {pix.shape[0]} views 320x240, {faces.shape[0]} triangles: "
            f"ours {t_ours * 1e3:.0f} ms ({t_ours / pix.shape[0] * 1e3:.2f} ms/view), "
            f"PIL polygon loop {t_peer * 1e3:.0f} ms ({t_peer / pix.shape[0] * 1e3:.1f} ms/view), "
            f"speed-up {t_peer / t_ours:.0f}x; mask IoU ours vs PIL {iou:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--clip", type=Path, default=None)
    ap.add_argument("--scenario", nargs="+", default=["studio", "outdoor"])
    ap.add_argument("--frames", type=int, default=250)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--no-save", action="store_true")
    ap.add_argument("--peer", action="store_true", help="also time a PIL polygon-loop peer")
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
                best = (wall, cpu, seq.meta.timings)
        save_s = float("nan")
        if not args.no_save:
            with tempfile.TemporaryDirectory() as d:
                t0 = time.perf_counter()
                seq.save(Path(d) / "sequence")
                save_s = time.perf_counter() - t0
        rows.append((name, seq.num_frames, best, save_s, int(seq.depth.counts.float().mean())))
    if args.peer:
        print("#", _peer(subject))
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
