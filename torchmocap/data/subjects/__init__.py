"""The subject: the tracking skeleton with a person's bone lengths, and where a track starts.

* From motion capture (:mod:`~torchmocap.data.subjects.mocap`): :func:`fit_subject` maps a
  clip's skeleton onto human31 and fits its bone lengths and per-frame poses — the ground truth
  of a synthetic sequence.
* From a recording's own observations (:mod:`~torchmocap.data.subjects.recorded`):
  :func:`keypoint_start` fits the skeleton, its keypoint map and the first pose to the first
  frames' triangulated keypoints; :func:`hull_start` scales human31 to the visual hull of the
  first masks, with one standing candidate per heading. Both fill the
  :class:`~torchmocap.data.SequenceMeta` fields of the subject (``subject_skeleton``,
  ``initial_poses``, ...).
"""

from torchmocap.data.subjects.mocap import Subject, fit_subject
from torchmocap.data.subjects.recorded import hull_start, keypoint_start, subject_settings

__all__ = ["Subject", "fit_subject", "hull_start", "keypoint_start", "subject_settings"]
