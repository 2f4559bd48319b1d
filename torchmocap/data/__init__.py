"""torchmocap.data: sequences of observations — the container, its metadata, and where they come
from.

* :class:`Sequence` (:mod:`~torchmocap.data.sequence`): frames x modalities of observations
  (silhouettes, colour images, :class:`ImuData`, :class:`DepthData`, 2D joints), the cameras and
  the ground truth; its :class:`SequenceMeta` (:mod:`~torchmocap.data.metadata`) is the typed
  record of where it came from and what its source fitted. :func:`split_heldout` splits off a
  held-out camera.
* :mod:`torchmocap.data.synthetic`: observations synthesised from motion capture and a
  scenario.
* :mod:`torchmocap.data.recordings`: real recordings read from their own files (videos,
  calibrations, keypoints, masks).
* :mod:`torchmocap.data.subjects`: the subject (the tracking skeleton with a person's bone
  lengths) fitted to a motion clip, or to a recording's first frames.
"""

from torchmocap.data.depth import DepthData
from torchmocap.data.heldout import split_heldout
from torchmocap.data.imu import ImuData, SensorPlacementError
from torchmocap.data.metadata import SequenceMeta
from torchmocap.data.sequence import (
    MODALITIES,
    Frame,
    GroundTruth,
    MissingModalityError,
    Sequence,
    SequenceFormatError,
)

__all__ = [
    "MODALITIES",
    "DepthData",
    "Frame",
    "GroundTruth",
    "ImuData",
    "MissingModalityError",
    "SensorPlacementError",
    "Sequence",
    "SequenceFormatError",
    "SequenceMeta",
    "split_heldout",
]
