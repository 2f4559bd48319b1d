"""``torchmocap-track``: track a motion observed through synthesised sensors (Hydra CLI).

Default: the bundled 4 s CMU walk, the ``studio`` scenario, method ``p`` (Pons-Moll et al.).
Overrides: ``data.clip.path``, ``data.clip.asf``, ``data.clip.skeleton_map``, ``data.clip.frames``,
``data.scenario``, ``tracker=<p|p_gaussian|p_nonoise|g|gs|rs|l|ls>``, ``tracker.num_particles``,
``seed``; ``--multirun`` sweeps any of them; ``data=bodytrack`` fits the real bodytrack frame.
Writes into the Hydra run directory: ``metrics.json``, ``track.npz``, ``tracked.bvh``,
``overlay_XXXX.png`` and ``errors.png``. Failures print one line on stderr and exit with status 2;
``metrics.json`` is written last and atomically, so a failed run never leaves one behind.
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

__all__ = ["main", "run", "write_json_atomic"]

VALIDATION_BONES_FALLBACK = ["spine", "l_shoulder", "r_shoulder", "l_hip", "r_hip"]


class _UsageError(Exception):
    pass


def write_json_atomic(obj: Any, path: Path) -> None:
    """Write JSON to ``path`` through a temporary file and a rename."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(obj, f, indent=2)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _sequence_from_config(cfg):
    """Clip -> subject -> synthesised sequence, exactly as ``torchmocap-synth`` builds it."""
    from torchmocap.cli import synth

    try:
        return synth.sequence_from_config(cfg, min_frames=2)
    except synth._UsageError as e:
        raise _UsageError(str(e)) from None


def _tracker_config(cfg):
    from torchmocap.filters.tracker import TrackerConfig

    tc = OmegaConf.to_container(cfg.tracker, resolve=True)
    tc["damping"] = tuple(tc.get("damping", (0.8, 0.3)))
    return TrackerConfig(**tc)


def run(cfg: DictConfig, out: Path) -> dict:
    """Run the configured job; returns the metrics written to ``out/metrics.json``."""
    if cfg.data.get("kind") == "bodytrack":
        from torchmocap.cli.bodytrack import run_bodytrack

        return run_bodytrack(cfg, out)
    import numpy as np

    from torchmocap.body import CapsuleBody
    from torchmocap.filters.tracker import Tracker
    from torchmocap.io import MotionClip, write_bvh
    from torchmocap.metrics import mpjpe_mm, orientation_error_deg, summarize_errors

    seq = _sequence_from_config(cfg)
    tcfg = _tracker_config(cfg)
    gt = seq.ground_truth
    sk = gt.build_skeleton().float()
    body = CapsuleBody(sk)
    rig = seq.rig.float()
    sensors = {}
    if seq.imu is not None:
        sensors = {n: b for n, b, t in zip(seq.imu.names, seq.imu.bones,
                                            seq.imu.tracking.tolist()) if t}
        val_bones = [b for b, t in zip(seq.imu.bones, seq.imu.tracking.tolist()) if not t]
    else:
        val_bones = VALIDATION_BONES_FALLBACK
    tracker = Tracker(body, rig, tcfg, sensors=sensors, seed=int(cfg.seed))
    ckpt = cfg.get("checkpoint")
    if ckpt:
        ckpt = str(out / ckpt) if not os.path.isabs(str(ckpt)) else str(ckpt)
    track = tracker.run(seq, theta0=gt.theta[0].float(), progress=bool(cfg.get("progress", True)),
                        checkpoint=ckpt, checkpoint_every=int(cfg.get("checkpoint_every", 10)))

    kin = sk(track.theta)
    vb = [sk.joint_index(b) for b in val_bones]
    ori = orientation_error_deg(kin.rotations[1:, vb], gt.rotations[1:, vb].float())
    mp = mpjpe_mm(kin.positions[1:], gt.positions[1:].float())
    metrics = {
        "method": tcfg.method,
        "frames": int(track.theta.shape[0]),
        "tracked_frames": int(track.theta.shape[0] - 1),
        "seconds_per_frame": track.seconds_per_frame,
        "num_particles": tcfg.num_particles,
        "layers": tcfg.layers,
        "scenario": seq.scenario,
        "seed": int(cfg.seed),
        "clip": seq.meta.get("clip", {}),
        "validation_bones": val_bones,
        **summarize_errors(ori, val_bones, mp),
    }
    np.savez_compressed(out / "track.npz", theta=track.theta.numpy(),
                        theta_gt=gt.theta.numpy(), orientation_error_deg=ori.numpy(),
                        mpjpe_mm=mp.numpy(), dof_names=np.array(sk.dof_names))
    write_bvh(out / "tracked.bvh", MotionClip.from_skeleton(sk.double(), track.theta.double(),
                                                            fps=seq.fps))
    sk.float()
    _write_plots(out, seq, sk, body, track.theta, ori, mp, int(cfg.get("overlays", 3)),
                 val_bones)
    write_json_atomic(metrics, out / "metrics.json")
    return metrics


def _write_plots(out, seq, sk, body, theta, ori, mp, n_overlays, val_bones):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchmocap.viz import overlay_on_image

    T = theta.shape[0]
    t_axis = np.arange(1, T) / seq.fps
    fig, ax = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for k, b in enumerate(val_bones):
        ax[0].plot(t_axis, ori[:, k].numpy(), label=b, lw=1)
    ax[0].plot(t_axis, ori.mean(1).numpy(), "k", lw=2, label="mean")
    ax[0].set_ylabel("orientation error (deg)")
    ax[0].legend(fontsize=7, ncol=3)
    ax[1].plot(t_axis, mp.numpy(), "k")
    ax[1].set_ylabel("MPJPE (mm)")
    ax[1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(out / "errors.png", dpi=100)
    plt.close(fig)
    if n_overlays <= 0 or seq.silhouettes is None:
        return
    frames = sorted({int(round(x)) for x in np.linspace(1, T - 1, n_overlays)})
    for t in frames:
        f = seq.frame(t)
        img = f.images[0] if f.images is not None else f.silhouettes[0].float()
        kin = sk(theta[t])
        overlay_on_image(img, seq.rig, 0, kin, out / f"overlay_{t:04d}.png", skeleton=sk,
                         capsules=body, mask=f.silhouettes[0],
                         title=f"frame {t}: model (capsules) over camera 0")


@hydra.main(config_path="../conf", config_name="track", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> float:
    out = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    try:
        metrics = run(cfg, out)
    except Exception as e:  # one line, exit 2; metrics.json is only written on success
        from torchmocap.data.sequence import MissingModalityError
        from torchmocap.filters.tracker import MissingObservationError
        from torchmocap.io import MotionFormatError, SkeletonMapError

        known = (_UsageError, MotionFormatError, SkeletonMapError, MissingObservationError,
                 MissingModalityError, FileNotFoundError, ValueError, KeyError)
        if isinstance(e, known):
            print(f"torchmocap-track: error: {e}", file=sys.stderr)
            sys.exit(2)
        raise
    _print_summary(metrics)
    return float(metrics.get("orientation_error_deg", {}).get("mean", math.nan))


def _print_summary(m: dict) -> None:
    if "orientation_error_deg" not in m:
        print(json.dumps(m, indent=2))
        return
    o = m["orientation_error_deg"]
    rows = [("method", m["method"]), ("scenario", m.get("scenario")), ("frames", m["frames"]),
            ("particles x layers", f"{m['num_particles']} x {m['layers']}"),
            ("seconds / frame", f"{m['seconds_per_frame']:.3f}"),
            ("orientation error (deg)", f"{o['mean']:.2f} +- {o['std']:.2f}"),
            ("MPJPE (mm)", f"{m['mpjpe_mm']['mean']:.1f} +- {m['mpjpe_mm']['std']:.1f}")]
    rows += [(f"  {b}", f"{v:.2f}") for b, v in o["per_bone"].items()]
    w = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")


def main() -> None:
    """Console entry point."""
    _hydra_main()


if __name__ == "__main__":
    main()
