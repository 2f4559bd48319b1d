"""2D keypoint and person-mask detectors that run on a recording's own frames.

* :class:`MediaPipePoseDetector` (:mod:`~torchmocap.detectors.mediapipe_pose`): MediaPipe Pose
  on one RGB image — ``(P, 33, 3)`` keypoints (format ``mediapipe_33``, ``P`` = 0 or 1) and an
  ``(H, W)`` person probability mask; optionally inside a box (the subject's region);
  its models ship in the mediapipe wheel (the ``detector`` extra), nothing is downloaded.
* :mod:`~torchmocap.detectors.regions`: boxes to crops and crops' keypoints and masks back to
  the full image.
* :func:`cached_detections` (:mod:`~torchmocap.detectors.cache`): a video's or image folder's
  detections as OpenPose JSON and mask PNGs in a cache folder keyed by the source's content and
  the detector's settings; a second run reads them.

The package imports only :mod:`torchmocap.io` (frame sources, OpenPose JSON, atomic writes);
mediapipe is imported when a detector is built. Docs: ``docs/detectors.md``.
"""

from torchmocap.detectors.cache import (
    CACHE_VERSION,
    CachedDetections,
    cached_detections,
    detection_key,
    source_digest,
)
from torchmocap.detectors.mediapipe_pose import (
    MEDIAPIPE_33,
    MEDIAPIPE_VERSION,
    MODEL_FILES,
    DetectorSettingsError,
    DetectorUnavailableError,
    MediaPipePoseDetector,
    MediaPipePoseSettings,
    PoseDetection,
    check_image,
    check_model_files,
    landmarks_to_keypoints,
)
from torchmocap.detectors.regions import (
    Box,
    DetectorInputError,
    Region,
    box_to_region,
    check_box,
    crop_image,
    keypoint_box,
    paste_region,
    region_to_image,
)

__all__ = [
    "CACHE_VERSION",
    "MEDIAPIPE_33",
    "MEDIAPIPE_VERSION",
    "MODEL_FILES",
    "Box",
    "CachedDetections",
    "DetectorInputError",
    "DetectorSettingsError",
    "DetectorUnavailableError",
    "MediaPipePoseDetector",
    "MediaPipePoseSettings",
    "PoseDetection",
    "Region",
    "box_to_region",
    "cached_detections",
    "check_box",
    "check_image",
    "check_model_files",
    "crop_image",
    "detection_key",
    "keypoint_box",
    "landmarks_to_keypoints",
    "paste_region",
    "region_to_image",
    "source_digest",
]
