"""The triangulation pipelines a researcher would otherwise use, on the same associated BODY_25B
detections, scored leave-one-camera-out (``protocol.py``): each reconstructs the keypoints from
the C-1 other views, is projected into the held-out view and compared with its detections.

Peers (every one uses the detections of confidence above :data:`INPUT_CONFIDENCE`, Pose2Sim's
``likelihood_threshold_triangulation``; anipose's own default of 0.8 is for DeepLabCut's
likelihoods and would drop most OpenPose keypoints, whose median confidence here is 0.62):

* ``dlt``: confidence-weighted DLT (:func:`torchmocap.cameras.triangulate_dlt`; what Pose2Sim's
  triangulation does per keypoint);
* ``dlt_drop``: the same, plus Pose2Sim's habit of dropping views: when a keypoint's mean
  reprojection error in the views used exceeds :data:`VIEW_DROP_PX` (Pose2Sim's default
  ``reproj_error_threshold_triangulation``), it is triangulated again without one view (every
  choice; the smallest error wins), then without two, ... while at least two views remain; a
  keypoint still above the threshold is left out (NaN, counted as missing). Pose2Sim then
  interpolates such gaps; that step is not part of this row;
* ``anipose_dlt``, ``anipose_ransac``, ``anipose_optim`` (``aniposelib``, the optional extra
  ``peers``): ``CameraGroup.triangulate`` (DLT of undistorted points, unweighted),
  ``triangulate_ransac`` (the view subset of smallest mean reprojection error, at least two
  views) and ``triangulate_optim`` (the DLT refined by least squares with a temporal smoothness
  term and soft constant-length constraints on :data:`ANIPOSE_LIMBS`, weak ones on
  :data:`ANIPOSE_LIMBS_WEAK`; aniposelib's default weights), built from the same calibration;
* ``pose2sim_raw``, ``pose2sim_butterworth``: Pose2Sim's committed output
  (``pose2sim_output/*.trc``, raw and Butterworth-filtered; the LSTM-augmented file is left
  out) — context only: Pose2Sim triangulated from all four views, the held-out one included.

Writes ``results/peers.json``: per method and held-out camera the scores of
``protocol.score_row`` and the seconds per frame, with the machine's load while they ran.

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python experiments/real_multiview/peers.py
    OMP_NUM_THREADS=1 python experiments/real_multiview/peers.py --recording DIR --out FILE

aniposelib: ``pip install -e '.[peers]'``, or ``pip install aniposelib`` — in an environment
that already has ``opencv-python(-headless)``, ``pip install --no-deps aniposelib`` and then
``pip install numba pandas toml jax`` keeps one OpenCV (aniposelib asks for
``opencv-contrib-python``, whose extra modules only its ChArUco boards use). Without it the
anipose rows are skipped with a message saying so.
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import sys
import time
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from protocol import (  # noqa: E402 - this folder is not a package
    CV_BONES,
    KEYPOINTS,
    MIN_CONFIDENCE,
    Detections,
    heldout_scores,
    load_detections,
    score_row,
)

from torchmocap.cameras import CameraRig, triangulate_dlt  # noqa: E402
from torchmocap.evaluation import leave_one_camera_out  # noqa: E402

#: the recording (``../shared/data`` beside the checkout)
RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
OUT = HERE / "results" / "peers.json"
#: detections the peers reconstruct from: confidence above this (Pose2Sim's default)
INPUT_CONFIDENCE = 0.3
#: Pose2Sim's view dropping: mean reprojection error (px) above which views are dropped
VIEW_DROP_PX = 15.0
#: anipose's soft constant-length constraints: the BODY_25B skeleton's limbs, the hip and
#: shoulder widths, the feet and the face
ANIPOSE_LIMBS = (*CV_BONES, ("LAnkle", "LHeel"), ("LAnkle", "LBigToe"), ("LBigToe", "LSmallToe"),
                 ("RAnkle", "RHeel"), ("RAnkle", "RBigToe"), ("RBigToe", "RSmallToe"),
                 ("Nose", "LEye"), ("Nose", "REye"), ("LEye", "LEar"), ("REye", "REar"),
                 ("LEar", "REar"))
#: weak ones: the trunk's sides and the neck (the spine and neck bend)
ANIPOSE_LIMBS_WEAK = (("LShoulder", "LHip"), ("RShoulder", "RHip"), ("Neck", "LShoulder"),
                      ("Neck", "RShoulder"), ("Neck", "Head"), ("Neck", "Nose"))
ANIPOSE_MISSING = ("aniposelib is not installed: the anipose rows are skipped (pip install -e "
                   "'.[peers]', or see this script's docstring)")

#: ``f(pixels (T, C-1, K, 2), confidences (T, C-1, K), rig) -> (T, K, 3)``
Triangulate = Callable[[torch.Tensor, torch.Tensor, CameraRig], torch.Tensor]


def _used(confidences: torch.Tensor) -> torch.Tensor:
    """Weights of the detections the peers use (0 at or below :data:`INPUT_CONFIDENCE`)."""
    return torch.where(confidences > INPUT_CONFIDENCE, confidences,
                       torch.zeros_like(confidences))


def dlt(pixels: torch.Tensor, confidences: torch.Tensor, rig: CameraRig) -> torch.Tensor:
    """Confidence-weighted DLT of the used detections: ``(T, K, 3)``."""
    return triangulate_dlt(pixels, _used(confidences), rig)


def dlt_view_dropping(pixels: torch.Tensor, confidences: torch.Tensor, rig: CameraRig,
                      threshold_px: float = VIEW_DROP_PX, min_views: int = 2) -> torch.Tensor:
    """Weighted DLT with Pose2Sim's view dropping (module docstring): ``(T, K, 3)``, NaN where
    no choice of at least ``min_views`` views reprojects within ``threshold_px`` on average."""
    w = _used(confidences)  # (T, C, K)
    C = rig.num_cameras
    T, _, K, _ = pixels.shape
    out = torch.full((T, K, 3), float("nan"), dtype=pixels.dtype, device=pixels.device)
    done = torch.zeros(T, K, dtype=torch.bool, device=pixels.device)
    for n_off in range(C - min_views + 1):
        errors, points = [], []
        for off in itertools.combinations(range(C), n_off):
            keep = torch.ones(C, dtype=pixels.dtype, device=pixels.device)
            keep[list(off)] = 0
            wk = w * keep[:, None]
            X = triangulate_dlt(pixels, wk, rig, min_views=min_views)  # (T, K, 3)
            uv = rig.project(torch.nan_to_num(X))[0]  # (T, C, K, 2)
            used = wk > 0
            e = torch.where(used, (uv - pixels).norm(dim=-1), torch.zeros_like(wk)).sum(1)
            e = e / used.sum(1).clamp_min(1)
            errors.append(torch.where(torch.isfinite(X).all(-1), e, torch.full_like(e, np.inf)))
            points.append(X)
        err, best = torch.stack(errors).min(0)  # (T, K)
        X = torch.stack(points).gather(0, best[None, ..., None].expand(1, T, K, 3))[0]
        accept = ~done & (err <= threshold_px)
        out[accept] = X[accept]
        done |= accept
    return out


def _aniposelib():
    """The ``aniposelib`` module, or None when it is not installed."""
    try:
        import aniposelib.cameras
    except ImportError:
        return None
    return aniposelib


def camera_group(rig: CameraRig):
    """The rig as an ``aniposelib`` ``CameraGroup``: the same K, distortion (OpenCV's k1 k2 p1
    p2 k3), world-to-camera rotation as a Rodrigues vector, translation (m) and image size
    [width, height]."""
    from aniposelib.cameras import Camera, CameraGroup

    from torchmocap.geometry.rotations import so3_log

    r = rig.double()
    rvec = so3_log(r.R).numpy()
    return CameraGroup([
        Camera(matrix=r.K[c].numpy(), dist=r.dist[c].numpy(), size=r.image_size[c].tolist(),
               rvec=rvec[c], tvec=r.t[c].numpy(), name=r.names[c])
        for c in range(r.num_cameras)])


@contextmanager
def _quiet_numba():
    """aniposelib's numba-jitted functions warn on compilation that they run in object mode,
    as they are written to; the warnings say nothing about the results."""
    from numba.core.errors import NumbaWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaWarning)
        yield


def _anipose_input(pixels: torch.Tensor, confidences: torch.Tensor) -> np.ndarray:
    """``(C, T, K, 2)`` float64 pixels, NaN where a detection is not used (anipose's missing
    points)."""
    p = pixels.double().clone()
    p[_used(confidences) <= 0] = float("nan")
    return p.permute(1, 0, 2, 3).numpy()


def anipose_dlt(pixels: torch.Tensor, confidences: torch.Tensor, rig: CameraRig
                ) -> torch.Tensor:
    """aniposelib's ``CameraGroup.triangulate`` (undistorted points): ``(T, K, 3)``."""
    p = _anipose_input(pixels, confidences)
    C, T, K, _ = p.shape
    with _quiet_numba():
        X = camera_group(rig).triangulate(p.reshape(C, T * K, 2), undistort=True)
    return torch.from_numpy(np.asarray(X, dtype=np.float64).reshape(T, K, 3))


def anipose_ransac(pixels: torch.Tensor, confidences: torch.Tensor, rig: CameraRig
                   ) -> torch.Tensor:
    """aniposelib's ``CameraGroup.triangulate_ransac`` (at least two views): ``(T, K, 3)``.
    Only the points seen in two views or more are passed (the others are NaN, as its
    ``triangulate`` makes them; aniposelib 0.8's ``triangulate_ransac`` fails on a point that
    no view sees)."""
    p = _anipose_input(pixels, confidences).reshape(pixels.shape[1], -1, 2)
    T, _, K, _ = pixels.shape
    seen = (~np.isnan(p[..., 0])).sum(0) >= 2
    X = np.full((T * K, 3), np.nan)
    if seen.any():
        with _quiet_numba():
            X[seen] = camera_group(rig).triangulate_ransac(p[:, seen], undistort=True,
                                                           min_cams=2)[0]
    return torch.from_numpy(X.reshape(T, K, 3))


def anipose_optim(pixels: torch.Tensor, confidences: torch.Tensor, rig: CameraRig
                  ) -> torch.Tensor:
    """aniposelib's ``CameraGroup.triangulate_optim`` with :data:`ANIPOSE_LIMBS` (strong) and
    :data:`ANIPOSE_LIMBS_WEAK` (weak) constant-length constraints and its temporal smoothness,
    at aniposelib's default weights: ``(T, K, 3)``. A keypoint that the DLT initialisation never
    triangulated has nothing to hold it (aniposelib puts it at the origin) and is NaN."""
    p = _anipose_input(pixels, confidences)
    index = {k: i for i, k in enumerate(KEYPOINTS)}
    strong = [[index[a], index[b]] for a, b in ANIPOSE_LIMBS]
    weak = [[index[a], index[b]] for a, b in ANIPOSE_LIMBS_WEAK]
    with _quiet_numba():
        X = camera_group(rig).triangulate_optim(p, constraints=strong, constraints_weak=weak)
    X = torch.from_numpy(np.asarray(X, dtype=np.float64))
    seen = (torch.from_numpy(~np.isnan(p[..., 0])).sum(0) >= 2).any(0)  # (K,)
    return torch.where(seen[None, :, None], X, torch.full_like(X, float("nan")))


class Peer(NamedTuple):
    """A triangulation method: its key, its label in the table, the function."""

    key: str
    label: str
    triangulate: Triangulate
    needs_aniposelib: bool = False


PEERS = (
    Peer("dlt", "weighted DLT (Pose2Sim's triangulation)", dlt),
    Peer("dlt_drop", f"weighted DLT + view dropping > {VIEW_DROP_PX:g} px (Pose2Sim)",
         dlt_view_dropping),
    Peer("anipose_dlt", "aniposelib triangulate (DLT)", anipose_dlt, True),
    Peer("anipose_ransac", "aniposelib triangulate_ransac", anipose_ransac, True),
    Peer("anipose_optim", "aniposelib triangulate_optim (temporal + limb lengths)",
         anipose_optim, True),
)


def run_peer(peer: Peer, det: Detections) -> dict[str, dict]:
    """Leave-one-camera-out rows of ``peer``: ``{camera: score_row + seconds_per_frame}``.

    The seconds are wall time of the triangulation alone, after one untimed call of the same
    size (aniposelib compiles its jax and numba functions for the shapes of their first
    use)."""
    points, seconds = [], []
    rest = list(range(1, det.rig.num_cameras))
    peer.triangulate(det.points[:, rest, :, :2], det.points[:, rest, :, 2],
                     det.rig.subset(rest))

    def timed(pixels, confidences, rig):
        t0 = time.perf_counter()
        X = peer.triangulate(pixels, confidences, rig)
        seconds.append(time.perf_counter() - t0)
        points.append(X)
        return X

    scores = leave_one_camera_out(det.points, det.rig, MIN_CONFIDENCE, triangulate=timed)
    T = len(det.frames)
    return {cam: {**score_row(s, X, det.fps), "seconds_per_frame": round(dt / T, 5)}
            for cam, s, X, dt in zip(det.cameras, scores, points, seconds)}


def trc_files(recording: Path) -> list[Path]:
    """Pose2Sim's outputs of the recording: ``pose2sim_output/*.trc`` without the
    LSTM-augmented ones (other markers), in name order."""
    folder = recording / "pose2sim_output"
    return sorted(p for p in folder.glob("*.trc") if "lstm" not in p.name.lower()) \
        if folder.is_dir() else []


def trc_keypoints(path: Path, det: Detections) -> torch.Tensor:
    """A Pose2Sim TRC as ``(T, K, 3)`` BODY_25B keypoints in the calibration's Z-up world (its
    markers by name; keypoints it lacks are NaN), on the frames of ``det``.

    Raises:
        ValueError: a marker that is not a BODY_25B keypoint, or frames ``det`` has that the
            file has not.
    """
    from torchmocap.io.trc import read_trc

    trc = read_trc(path)
    stray = [m for m in trc.marker_names if m not in KEYPOINTS]
    if stray:
        raise ValueError(f"{path}: markers {stray} are not BODY_25B keypoints")
    rows = {int(f) - 1: i for i, f in enumerate(trc.frames.tolist())}  # TRC frames count from 1
    lacking = [t for t in det.frames if t not in rows]
    if lacking:
        raise ValueError(f"{path}: no rows for frames {lacking[:5]} (the file has frames "
                         f"{min(rows)}..{max(rows)} counted from 0)")
    pts = trc.z_up()[[rows[t] for t in det.frames]]
    out = torch.full((len(det.frames), len(KEYPOINTS), 3), float("nan"), dtype=torch.float64)
    out[:, [KEYPOINTS.index(m) for m in trc.marker_names]] = pts
    return out


def trc_label(path: Path) -> tuple[str, str]:
    """``(key, label)`` of a Pose2Sim TRC row."""
    name = path.name.lower()
    key, kind = (("butterworth", "Butterworth-filtered") if "butterworth" in name else
                 ("filtered", "filtered") if "filt" in name else ("raw", "raw"))
    return f"pose2sim_{key}", f"Pose2Sim output, {kind} (all 4 views: saw the held-out one)"


def run_trc(path: Path, det: Detections) -> dict[str, dict]:
    """Rows of a fixed reconstruction (a TRC): ``{camera: score_row}``."""
    X = trc_keypoints(path, det)
    return {cam: score_row(heldout_scores(X, det, c), X, det.fps)
            for c, cam in enumerate(det.cameras)}


def machine() -> dict:
    """The conditions of the timings."""
    anipose = _aniposelib()
    return {"load_average_1_5_15min": [round(v, 2) for v in os.getloadavg()],
            "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
            "python": platform.python_version(), "torch": torch.__version__,
            "aniposelib": getattr(anipose, "__version__", None) if anipose else None}


def run_all(recording: Path, start: int = 0, stop: int | None = None,
            log=print) -> dict:
    """Every peer and every Pose2Sim TRC of ``recording``, as written to ``peers.json``."""
    det = load_detections(recording, start, stop)
    result = {
        "recording": det.path.name, "cameras": det.cameras,
        "frames": [det.frames[0], det.frames[-1]], "fps": det.fps,
        "min_confidence": MIN_CONFIDENCE, "input_confidence": INPUT_CONFIDENCE,
        "view_drop_px": VIEW_DROP_PX, "load_before": machine(), "methods": {}, "skipped": {}}
    anipose = _aniposelib()
    for peer in PEERS:
        if peer.needs_aniposelib and anipose is None:
            result["skipped"][peer.key] = ANIPOSE_MISSING
            log(f"peers: {peer.key}: {ANIPOSE_MISSING}")
            continue
        log(f"peers: {peer.key} ...")
        result["methods"][peer.key] = {"label": peer.label, "saw_heldout": False,
                                       "rows": run_peer(peer, det)}
    for path in trc_files(det.path):
        key, label = trc_label(path)
        log(f"peers: {key} ({path.name}) ...")
        result["methods"][key] = {"label": label, "saw_heldout": True, "file": path.name,
                                  "rows": run_trc(path, det)}
    result["load_after"] = machine()["load_average_1_5_15min"]
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", type=Path, default=RECORDING,
                    help="the recording folder (default: ../shared/data/multiview/"
                         "pose2sim_balancing beside the checkout)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stop", type=int, default=None)
    ap.add_argument("--out", type=Path, default=OUT, help="the JSON written")
    args = ap.parse_args(argv)
    from torchmocap.atomic import write_json_atomic

    result = run_all(args.recording, args.start, args.stop)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(result, args.out)
    print(f"peers: wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
