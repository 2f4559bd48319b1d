"""``Sequence``: frames × modalities of observations, the cameras, the sensors and ground truth.

Every modality is optional: silhouettes ``(T, C, H, W)`` bool (+ ``view_dropped (T, C)``),
colour images ``(T, C, H, W, 3)`` uint8, IMU orientations (:class:`~torchmocap.data.imu.ImuData`),
depth point clouds (:class:`~torchmocap.data.depth.DepthData`), 2D joints ``(T, C, J, 3)``
(u, v, confidence), and ground truth (:class:`GroundTruth`). A consumer declares what it needs
with :meth:`Sequence.require`, which raises :class:`MissingModalityError` naming the modality.

On disk (:meth:`Sequence.save` / :meth:`Sequence.load`), one directory::

    manifest.json                 format, version, fps, scenario, modalities, rig, sensors, ...
    arrays.npz                    IMU, depth, 2D joints, view flags, ground truth
    masks/cam<c>/<t:05d>.png      1-bit silhouettes
    images/cam<c>/<t:05d>.png     RGB images

written into a temporary sibling directory and renamed into place, so a reader never sees a
half-written sequence.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmocap.data.depth import DepthData
from torchmocap.data.imu import ImuData
from torchmocap.data.metadata import SequenceMeta

__all__ = [
    "MODALITIES",
    "Frame",
    "GroundTruth",
    "MissingModalityError",
    "Sequence",
    "SequenceFormatError",
]

#: Names accepted by :meth:`Sequence.require`.
MODALITIES = ("silhouettes", "images", "imu", "depth", "joints2d", "ground_truth", "rig")
FORMAT = "torchmocap-sequence"
VERSION = 1


class MissingModalityError(LookupError):
    """A sequence lacks an observation modality a consumer needs (names the modality)."""

    def __init__(self, modality: str, available: list[str], name: str = "") -> None:
        self.modality = modality
        self.available = available
        where = f"sequence {name!r}" if name else "sequence"
        super().__init__(f"{where} has no {modality!r} observations (it has: "
                         f"{', '.join(available) or 'none'}); synthesise them (scenario "
                         f"{modality}.enabled: true) or use a component that does not need them")

    def __str__(self) -> str:  # LookupError would quote the message like a KeyError
        return self.args[0]


class SequenceFormatError(ValueError):
    """A saved sequence directory is malformed (names the file)."""


@dataclass
class GroundTruth:
    """Ground truth of a synthetic sequence.

    Attributes:
        skeleton: the subject's skeleton as a dict (:meth:`Skeleton.to_dict`).
        theta: ``(T, D)`` fitted poses.
        positions: ``(T, J, 3)`` exact joint positions (m).
        rotations: ``(T, J, 3, 3)`` exact bone frames ``R_TB``.
        joint_names: ``J`` names.
        markers: optional ``(T, M, 3)`` positions of points on the observed body's skin (the
            motion-capture markers of Hauberg & Pedersen's error measure, eq. 16).
        marker_parts: ``M`` names of the joints whose body part carries each marker.
    """

    skeleton: dict[str, Any]
    theta: Tensor
    positions: Tensor
    rotations: Tensor
    joint_names: list[str]
    markers: Tensor | None = None
    marker_parts: list[str] = field(default_factory=list)

    def build_skeleton(self):
        """The :class:`~torchmocap.skeleton.Skeleton` (float64)."""
        from torchmocap.skeleton import Skeleton

        return Skeleton.from_dict(self.skeleton).to(torch.float64)


@dataclass
class Frame:
    """Observations of one frame (``None`` where a modality is absent).

    Attributes:
        index: frame index; time: seconds.
        silhouettes: ``(C, H, W)`` bool; view_dropped: ``(C,)`` bool.
        images: ``(C, H, W, 3)`` uint8.
        imu: ``(S, 4)`` quaternions; imu_valid: ``(S,)`` bool.
        depth: ``(N, 3)`` points.
        joints2d: ``(C, J, 3)`` (u, v, confidence).
        theta, positions, rotations: ground truth ``(D,)``, ``(J, 3)``, ``(J, 3, 3)``.

    A tracker sees the frame through :meth:`~torchmocap.filters.Tracker.observe`: the tracking
    IMUs only, as rotation matrices ``imu (S, 3, 3)``, and no ground truth.
    """

    index: int
    time: float
    silhouettes: Tensor | None = None
    view_dropped: Tensor | None = None
    images: Tensor | None = None
    imu: Tensor | None = None
    imu_valid: Tensor | None = None
    depth: Tensor | None = None
    joints2d: Tensor | None = None
    theta: Tensor | None = None
    positions: Tensor | None = None
    rotations: Tensor | None = None

    def has_evidence(self, modality: str) -> bool:
        """Whether the frame holds usable observations of ``modality``: present, and for IMUs
        a sample that was not dropped, for silhouettes a view that was not."""
        if modality not in MODALITIES:
            raise ValueError(f"modality: unknown modality {modality!r}; expected one of "
                             f"{list(MODALITIES)}")
        if modality == "imu":
            return self.imu is not None and (self.imu_valid is None or bool(self.imu_valid.any()))
        if modality == "silhouettes":
            return self.silhouettes is not None and (
                self.view_dropped is None or not bool(self.view_dropped.all()))
        if modality == "ground_truth":
            return self.theta is not None
        if modality == "rig":
            return True
        return getattr(self, modality) is not None


def _json_safe(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def _json_restore(x: Any) -> Any:
    if x in ("inf", "-inf", "nan"):
        return float(x)
    if isinstance(x, dict):
        return {k: _json_restore(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_json_restore(v) for v in x]
    return x


@dataclass
class Sequence:
    """Synthetic or recorded observations of one motion.

    Attributes:
        fps: frame rate.
        scenario: scenario name (``"recorded"`` for real data).
        rig: :class:`~torchmocap.cameras.CameraRig` of the views (``C`` cameras) or None.
        silhouettes: ``(T, C, H, W)`` bool.
        view_dropped: ``(T, C)`` bool, views lost in a frame.
        images: ``(T, C, H, W, 3)`` uint8.
        imu: :class:`~torchmocap.data.imu.ImuData`.
        depth: :class:`~torchmocap.data.depth.DepthData`.
        joints2d: ``(T, C, J, 3)`` (u, v, confidence) of ``joint_names``.
        joint_names: names of the 2D joints.
        ground_truth: :class:`GroundTruth`.
        meta: :class:`~torchmocap.data.SequenceMeta`: where the sequence came from and what
            its source fitted (a dict given here becomes one, :meth:`SequenceMeta.from_dict`).
    """

    fps: float
    scenario: str = "custom"
    rig: Any = None
    silhouettes: Tensor | None = None
    view_dropped: Tensor | None = None
    images: Tensor | None = None
    imu: ImuData | None = None
    depth: DepthData | None = None
    joints2d: Tensor | None = None
    joint_names: list[str] = field(default_factory=list)
    ground_truth: GroundTruth | None = None
    meta: SequenceMeta = field(default_factory=SequenceMeta)

    def __post_init__(self) -> None:
        if not isinstance(self.meta, SequenceMeta):
            self.meta = SequenceMeta.from_dict(self.meta)

    # ------------------------------------------------------------------ access
    @property
    def modalities(self) -> list[str]:
        """Names of the modalities present."""
        have = {"silhouettes": self.silhouettes, "images": self.images, "imu": self.imu,
                "depth": self.depth, "joints2d": self.joints2d,
                "ground_truth": self.ground_truth, "rig": self.rig}
        return [k for k in MODALITIES if have[k] is not None]

    @property
    def num_frames(self) -> int:
        for x in (self.silhouettes, self.images, self.joints2d):
            if x is not None:
                return int(x.shape[0])
        if self.imu is not None:
            return int(self.imu.quaternions.shape[0])
        if self.depth is not None:
            return int(self.depth.counts.shape[0])
        if self.ground_truth is not None:
            return int(self.ground_truth.theta.shape[0])
        return 0

    def __len__(self) -> int:
        return self.num_frames

    @property
    def num_cameras(self) -> int:
        return 0 if self.rig is None else int(self.rig.num_cameras)

    def require(self, *modalities: str) -> Sequence:
        """Check that every named modality is present; returns ``self``.

        Raises:
            ValueError: an unknown modality name.
            MissingModalityError: the first missing modality (named in the message).
        """
        have = self.modalities
        for m in modalities:
            if m not in MODALITIES:
                raise ValueError(f"modalities: unknown modality {m!r}; expected one of "
                                 f"{list(MODALITIES)}")
            if m not in have:
                raise MissingModalityError(m, have, self.scenario)
        return self

    def frame(self, t: int) -> Frame:
        """Observations of frame ``t`` (negative indices count from the end)."""
        T = self.num_frames
        if not -T <= t < T:
            raise IndexError(f"t: frame {t} out of range for a {T}-frame sequence")
        t = t % T
        gt = self.ground_truth
        return Frame(
            index=t,
            time=t / self.fps,
            silhouettes=None if self.silhouettes is None else self.silhouettes[t],
            view_dropped=None if self.view_dropped is None else self.view_dropped[t],
            images=None if self.images is None else self.images[t],
            imu=None if self.imu is None else self.imu.quaternions[t],
            imu_valid=None if self.imu is None else self.imu.valid[t],
            depth=None if self.depth is None else self.depth.frame_points(t),
            joints2d=None if self.joints2d is None else self.joints2d[t],
            theta=None if gt is None else gt.theta[t],
            positions=None if gt is None else gt.positions[t],
            rotations=None if gt is None else gt.rotations[t],
        )

    def __iter__(self) -> Iterator[Frame]:
        for t in range(self.num_frames):
            yield self.frame(t)

    def select_cameras(self, indices) -> Sequence:
        """The sequence seen by the cameras at ``indices`` only (in that order): the rig's
        subset and those views of the silhouettes, view flags, images and 2D joints (image
        arrays cropped to the largest selected view); the other modalities, the ground truth
        and ``meta`` (a copy, ``meta.cameras`` the selected names when it lists cameras)
        are shared.

        Raises:
            ValueError: no rig, an index out of range, repeated or no indices.
        """
        import copy

        if self.rig is None:
            raise ValueError("indices: the sequence has no cameras to select from")
        idx = [int(i) for i in indices]
        C = self.num_cameras
        if not idx or len(set(idx)) != len(idx) or not all(0 <= i < C for i in idx):
            raise ValueError(f"indices: expected distinct camera indices in [0, {C}), got "
                             f"{list(indices)}")
        rig = self.rig.subset(idx)
        W, H = (int(v) for v in rig.image_size.max(0).values.tolist())
        sel = torch.tensor(idx, dtype=torch.long)

        def views(x, image=False):
            if x is None:
                return None
            x = x.index_select(1, sel.to(x.device))
            return x[:, :, :H, :W] if image else x

        meta = copy.deepcopy(self.meta)
        if isinstance(meta.cameras, list) and len(meta.cameras) == C:
            meta.cameras = [meta.cameras[i] for i in idx]
        return Sequence(fps=self.fps, scenario=self.scenario, rig=rig,
                        silhouettes=views(self.silhouettes, True),
                        view_dropped=views(self.view_dropped), images=views(self.images, True),
                        imu=self.imu, depth=self.depth, joints2d=views(self.joints2d),
                        joint_names=list(self.joint_names), ground_truth=self.ground_truth,
                        meta=meta)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write the sequence into directory ``path`` atomically (temp dir, then rename).

        Raises:
            FileExistsError: ``path`` exists and ``overwrite`` is False.
        """
        from torchmocap.cameras import rig_to_dict

        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"path: {path} exists (pass overwrite=True to replace it)")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        try:
            arrays: dict[str, np.ndarray] = {}
            man: dict[str, Any] = {"format": FORMAT, "version": VERSION, "fps": self.fps,
                                   "scenario": self.scenario, "num_frames": self.num_frames,
                                   "modalities": self.modalities, "arrays": "arrays.npz"}
            if self.rig is not None:
                man["rig"] = rig_to_dict(self.rig)
            if self.silhouettes is not None:
                T, C, H, W = self.silhouettes.shape
                man["silhouettes"] = {"pattern": "masks/cam{c}/{t:05d}.png", "cameras": C,
                                      "size": [W, H]}
                _write_pngs(tmp / "masks", self.silhouettes.cpu().numpy(), mode="1")
            if self.view_dropped is not None:
                arrays["view_dropped"] = self.view_dropped.cpu().numpy()
            if self.images is not None:
                T, C, H, W, _ = self.images.shape
                man["images"] = {"pattern": "images/cam{c}/{t:05d}.png", "cameras": C,
                                 "size": [W, H]}
                _write_pngs(tmp / "images", self.images.cpu().numpy(), mode="RGB")
            if self.imu is not None:
                u = self.imu
                man["imu"] = {"names": u.names, "bones": u.bones,
                              "tracking": [bool(v) for v in u.tracking.tolist()],
                              "desync_frames": u.desync_frames,
                              "quaternion_order": "w, x, y, z"}
                for k in ("quaternions", "valid", "clean", "offsets", "misalignment",
                          "drift_rates"):
                    arrays[f"imu_{k}"] = getattr(u, k).cpu().numpy()
            if self.depth is not None:
                man["depth"] = {"camera": rig_to_dict(self.depth.camera)}
                arrays["depth_points"] = self.depth.points.cpu().numpy()
                arrays["depth_counts"] = self.depth.counts.cpu().numpy()
            if self.joints2d is not None:
                man["joints2d"] = {"joint_names": list(self.joint_names),
                                   "layout": "u, v, confidence (pixels)"}
                arrays["joints2d"] = self.joints2d.cpu().numpy()
            if self.ground_truth is not None:
                g = self.ground_truth
                man["ground_truth"] = {"skeleton": _json_safe(g.skeleton),
                                       "joint_names": list(g.joint_names)}
                arrays["gt_theta"] = g.theta.cpu().numpy()
                arrays["gt_positions"] = g.positions.cpu().numpy()
                arrays["gt_rotations"] = g.rotations.cpu().numpy()
                if g.markers is not None:
                    arrays["gt_markers"] = g.markers.cpu().numpy()
                    man["ground_truth"]["marker_parts"] = list(g.marker_parts)
            man["meta"] = _json_safe(self.meta.to_dict())
            with open(tmp / "arrays.npz", "wb") as f:
                np.savez_compressed(f, **arrays)
            with open(tmp / "manifest.json", "w") as f:
                json.dump(man, f, indent=1, allow_nan=False)
            if path.exists():
                old = path.parent / f".{path.name}.old-{uuid.uuid4().hex[:8]}"
                os.replace(path, old)
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Sequence:
        """Read a directory written by :meth:`save` (or its ``manifest.json``).

        Raises:
            FileNotFoundError: no manifest.
            SequenceFormatError: malformed manifest, missing or inconsistent files.
        """
        from torchmocap.cameras import rig_from_dict

        path = Path(path)
        if path.name == "manifest.json":
            path = path.parent
        mpath = path / "manifest.json"
        if not mpath.is_file():
            raise FileNotFoundError(f"path: no sequence manifest at {mpath}")
        try:
            man = json.loads(mpath.read_text())
        except json.JSONDecodeError as e:
            raise SequenceFormatError(f"{mpath}: not valid JSON ({e})") from e
        if man.get("format") != FORMAT:
            raise SequenceFormatError(f"{mpath}: format {man.get('format')!r}, expected "
                                      f"{FORMAT!r}")
        if int(man.get("version", 0)) > VERSION:
            raise SequenceFormatError(f"{mpath}: version {man.get('version')} is newer than "
                                      f"this reader ({VERSION})")
        apath = path / man.get("arrays", "arrays.npz")
        try:
            with np.load(apath) as z:
                arr = {k: torch.from_numpy(z[k].copy()) for k in z.files}
        except (OSError, ValueError) as e:
            raise SequenceFormatError(f"{apath}: cannot read arrays ({e})") from e
        T = int(man["num_frames"])

        def need(key: str) -> Tensor:
            if key not in arr:
                raise SequenceFormatError(f"{apath}: missing array {key!r}")
            return arr[key]

        rig = rig_from_dict(man["rig"], source=str(mpath)) if "rig" in man else None
        seq = cls(fps=float(man["fps"]), scenario=str(man.get("scenario", "custom")), rig=rig,
                  meta=SequenceMeta.from_dict(_json_restore(man.get("meta", {}))))
        if "silhouettes" in man:
            s = man["silhouettes"]
            seq.silhouettes = _read_pngs(path / "masks", T, int(s["cameras"]), "1").bool()
        if "view_dropped" in arr:
            seq.view_dropped = arr["view_dropped"]
        if "images" in man:
            s = man["images"]
            seq.images = _read_pngs(path / "images", T, int(s["cameras"]), "RGB")
        if "imu" in man:
            m = man["imu"]
            seq.imu = ImuData(list(m["names"]), list(m["bones"]), torch.tensor(m["tracking"]),
                              need("imu_quaternions"), need("imu_valid"), need("imu_clean"),
                              need("imu_offsets"), need("imu_misalignment"),
                              need("imu_drift_rates"), float(m.get("desync_frames", 0.0)))
        if "depth" in man:
            cam = rig_from_dict(man["depth"]["camera"], source=f"{mpath}: depth.camera")
            seq.depth = DepthData(need("depth_points"), need("depth_counts"), cam)
        if "joints2d" in man:
            seq.joints2d = need("joints2d")
            seq.joint_names = list(man["joints2d"]["joint_names"])
        if "ground_truth" in man:
            g = man["ground_truth"]
            seq.ground_truth = GroundTruth(_json_restore(g["skeleton"]), need("gt_theta"),
                                           need("gt_positions"), need("gt_rotations"),
                                           list(g["joint_names"]))
            if "marker_parts" in g:
                seq.ground_truth.markers = need("gt_markers")
                seq.ground_truth.marker_parts = list(g["marker_parts"])
        if seq.num_frames != T:
            raise SequenceFormatError(f"{mpath}: num_frames {T} but arrays hold "
                                      f"{seq.num_frames} frames")
        return seq


def _write_pngs(root: Path, data: np.ndarray, mode: str) -> None:
    """``data (T, C, H, W[, 3])`` → ``root/cam<c>/<t:05d>.png``."""
    from PIL import Image

    T, C = data.shape[:2]
    for c in range(C):
        d = root / f"cam{c}"
        d.mkdir(parents=True)
        for t in range(T):
            img = data[t, c]
            im = Image.fromarray(img.astype(np.uint8) * 255, "L").convert("1") if mode == "1" \
                else Image.fromarray(img, "RGB")
            im.save(d / f"{t:05d}.png", compress_level=1)


def _read_pngs(root: Path, T: int, C: int, mode: str) -> Tensor:
    from PIL import Image

    frames = []
    for t in range(T):
        views = []
        for c in range(C):
            p = root / f"cam{c}" / f"{t:05d}.png"
            if not p.is_file():
                raise SequenceFormatError(f"{p}: missing image")
            with Image.open(p) as im:
                views.append(np.asarray(im.convert(mode if mode == "RGB" else "L")))
        frames.append(np.stack(views))
    out = torch.from_numpy(np.stack(frames))
    return out > 0 if mode == "1" else out
