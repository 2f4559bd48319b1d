"""``torchmocap-track``: track a sequence with a tracker assembled from config (Hydra CLI).

Default: the bundled 3 s CMU walk, the ``studio`` scenario, tracker ``default`` (the LS baseline of
Pons-Moll et al.: a local descent of a differentiable silhouette + appearance + orientation energy).
The sequence comes from the ``data`` node (a ``_target_`` source: synthesised from a clip, or a
real recording such as ``data=bodytrack``); the tracker is built from the ``tracker`` node by
:func:`torchmocap.assembly.build_tracker` — the command line never reaches into components.

Writes into the Hydra run directory: ``metrics.json`` (last, atomically), ``track.npz``,
``tracked.bvh``, overlay grids (every view, estimate and truth), ``errors.png``, and on request
an animation of the overlays (``video.enabled``) and an animated skinned body (``glb.enabled``);
the images, videos and GLB are written atomically too. A failure prints one line on stderr, writes
``failure.json`` and exits with status 2; in a multirun the other jobs go on and the command
exits with status 2 at the end if any job failed. A run directory whose ``metrics.json`` has the
same fingerprint (config, code, and every input file the data source read, unchanged) is
skipped as up to date (:func:`~torchmocap.cli.runs.completed_run`).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from torchmocap.assembly import load_sequence
from torchmocap.cli.batch import run_batch
from torchmocap.cli.jobs import finish, thread_policy, validate_tracker
from torchmocap.cli.outputs import print_summary, validate_outputs
from torchmocap.cli.runs import (
    completed_run,
    config_fingerprint,
    console_main,
    hydra_task,
    is_multirun,
    reported_warnings,
    run_fingerprint,
)

__all__ = ["OUTPUT_SETTINGS", "main", "run"]

#: settings that change what a run writes or how it runs, not the track: a checkpoint made
#: with other values of these is resumed
OUTPUT_SETTINGS = ("progress", "threads", "overlays", "overlay_scale", "video", "glb",
                   "checkpoint", "checkpoint_every", "skip_completed", "sequence_cache",
                   "diagnostics")


def _sequence_fingerprint(seq) -> str:
    import hashlib

    import torch

    h = hashlib.sha256()
    for x in (seq.silhouettes, seq.images, None if seq.imu is None else seq.imu.quaternions,
              None if seq.depth is None else seq.depth.points, seq.joints2d):
        if isinstance(x, torch.Tensor):
            h.update(x.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def run(cfg: DictConfig, out: Path) -> dict:
    """Run the configured job; returns the metrics written to ``out/metrics.json``."""
    from torchmocap.assembly import Runtime, build_tracker
    from torchmocap.data import split_heldout
    from torchmocap.filters.tracking.tracker import check_checkpoint

    if cfg.get("batch_seeds"):  # several seeds in one process: one run dir per seed
        return run_batch(cfg, out)
    settings = config_fingerprint(cfg)
    done = completed_run(out, settings) if cfg.get("skip_completed", True) else None
    if done is not None:
        print(f"torchmocap-track: {out} is complete and up to date (fingerprint "
              f"{done['fingerprint']}); skipped", file=sys.stderr)
        return done
    # a rerun in place: the old records must not outlive this run's config
    for stale in ("failure.json", "metrics.json"):
        (out / stale).unlink(missing_ok=True)
    with reported_warnings("torchmocap-track") as warned:
        governor = thread_policy(cfg)
        validate_tracker(cfg)  # settings errors before any loading, fitting or synthesis
        validate_outputs(cfg)
        ckpt = _checkpoint_path(cfg, out)
        every = cfg.get("checkpoint_every", 10)
        check_checkpoint(ckpt, every)
        seq = load_sequence(cfg, min_frames=2, min_views=2)
        inputs = seq.meta.inputs
        fingerprint = run_fingerprint(settings, inputs)
        tracked, _ = split_heldout(seq)  # the views the tracker sees (all but a held-out camera)
        runtime = Runtime.from_sequence(tracked)
        try:
            tracker = build_tracker(cfg.tracker, runtime, seed=cfg.seed)
            tracker.check_sequence(tracked)
        except ValueError as e:
            hint = seq.meta.suggested_tracker
            if hint and cfg.tracker.get("name") != hint:
                raise type(e)(f"{e} (this data is tracked with tracker={hint})") from e
            raise
        # the checkpoint's fingerprint: what the track depends on (output settings left out)
        tracking = run_fingerprint(config_fingerprint(cfg, exclude=OUTPUT_SETTINGS), inputs)
        track = tracker.run(tracked, progress=bool(cfg.get("progress", True)), checkpoint=ckpt,
                            checkpoint_every=every,
                            fingerprint=f"{tracking}-{_sequence_fingerprint(tracked)}",
                            callbacks=[governor])
    return finish(cfg, out, seq, runtime, tracker, track, fingerprint,
                  {"threads": governor.summary(), "inputs": inputs, "warnings": warned})


def _checkpoint_path(cfg, out: Path) -> str | None:
    """The ``checkpoint`` file: relative to the working directory of a single run, to each
    job's directory in a multirun."""
    ckpt = cfg.get("checkpoint")
    if not ckpt:
        return None
    ckpt = Path(str(ckpt)).expanduser()
    if not ckpt.is_absolute():
        ckpt = (out if is_multirun() else Path.cwd()) / ckpt
    return str(ckpt)


@hydra.main(config_path="../conf", config_name="track", version_base="1.3")
@hydra_task("torchmocap-track", failed=math.nan, fingerprint=config_fingerprint)
def _hydra_main(cfg: DictConfig, out: Path) -> float:
    metrics = run(cfg, out)
    print_summary(metrics)
    return float(metrics.get("orientation_error_deg", {}).get("mean", math.nan))


def main() -> None:
    """Console entry point (exit status 2 when the run, or any job of a sweep, failed)."""
    console_main(_hydra_main)


if __name__ == "__main__":
    main()
