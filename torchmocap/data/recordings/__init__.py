"""Real recordings as :class:`~torchmocap.data.Sequence`\\ s.

* :func:`load_recording` (``data=recording``): a folder of synchronised cameras — a video or
  image folder per camera (:mod:`~torchmocap.data.recordings.files`), the calibration in the
  ecosystem's formats (:func:`~torchmocap.cameras.read_calibration`), 2D keypoints from a
  registered keypoint source (:mod:`~torchmocap.data.recordings.keypoints`; the subject chosen
  among several people by :mod:`~torchmocap.data.recordings.person_selection`), and masks from
  files or computed (:mod:`~torchmocap.data.recordings.mask_source`,
  :mod:`~torchmocap.data.recordings.masks`); the subject and the first pose fitted to the
  first frames (:mod:`torchmocap.data.subjects.recorded`); before anything is tracked, the
  views' agreement, the calibration's unit and the detections are checked
  (:mod:`~torchmocap.data.recordings.checks`).
* :func:`load_bodytrack_sequence` (``data=bodytrack``): PARSEC's one real 4-camera frame.
"""

from torchmocap.data.recordings.bodytrack import load_bodytrack_sequence
from torchmocap.data.recordings.files import (
    RecordingCamera,
    RecordingFiles,
    RecordingLayoutError,
    discover_recording,
)
from torchmocap.data.recordings.keypoints import (
    KeypointDetections,
    KeypointRequest,
    KeypointSource,
    keypoint_sources,
)
from torchmocap.data.recordings.loader import load_recording

__all__ = [
    "KeypointDetections",
    "KeypointRequest",
    "KeypointSource",
    "RecordingCamera",
    "RecordingFiles",
    "RecordingLayoutError",
    "discover_recording",
    "keypoint_sources",
    "load_bodytrack_sequence",
    "load_recording",
]
