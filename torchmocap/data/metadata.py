"""What a :class:`~torchmocap.data.Sequence` knows about itself besides its observations.

:class:`SequenceMeta` is the one typed record of it: where the sequence came from, the files it
was read from, and what its source fitted (the subject, the first poses, the keypoint map). A
data source fills the fields it knows and leaves the others None; consumers read fields by
name (``sequence.meta.initial_poses``) and never by string key. The record is JSON-ready (the
values are plain numbers, strings, lists and dicts) and is saved with the sequence
(:meth:`~torchmocap.data.Sequence.save`: ``manifest.json``'s ``meta``, the fields that are set).

A user's own data source may keep information the package does not read in ``extra``
(``SequenceMeta(extra={"operator": "..."})``, also saved).

Example:
    >>> meta = SequenceMeta(source="recording", cameras=["cam01", "cam02"], scale=0.5)
    >>> meta.to_dict()
    {'source': 'recording', 'cameras': ['cam01', 'cam02'], 'scale': 0.5}
    >>> SequenceMeta.from_dict(meta.to_dict()) == meta
    True
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["SequenceMeta"]


@dataclass
class SequenceMeta:
    """The metadata of a sequence (module docstring). Every field is optional (None: unknown
    or not applicable).

    Any sequence:
        source: what made it — ``"recording"`` (:func:`~torchmocap.data.recordings.load_recording`),
            ``"bodytrack"`` (the PARSEC frame), None for synthesis.
        inputs: ``{path: digest}`` of every input file its data source read
            (:mod:`torchmocap.inputs`; filled by :func:`torchmocap.assembly.load_sequence`).
        cameras: the cameras' names, in the rig's order.
        heldout_camera: the camera held out of tracking and scored (its name); the sequence
            holds it until :func:`~torchmocap.data.split_heldout` splits it off.
        scale: the images' scale relative to the recorded ones; pixel scores are reported in
            the recorded images' pixels (divided by it). None: 1.
        suggested_tracker: the preset this data is tracked with (named when another fails).

    A synthesised sequence (:func:`~torchmocap.data.synthetic.synthesize`):
        seed: the synthesis seed.
        scenario: the scenario's settings (:meth:`~torchmocap.data.synthetic.Scenario.to_dict`).
        body: the rendered body (``skinned``, ``capsules`` or ``anny``).
        phenotype: the Anny body's phenotype (all six parameters; ``body: anny``).
        body_height: the Anny body's standing height (m, its skeleton's rest pose).
        subject: the subject fit's summary (skeleton family, residual, mapped bones).
        timings: seconds per synthesis stage.
        joints2d_occluded_fraction: fraction of 2D joints hidden by the body.
        skeleton: the tracking skeleton (``human31`` or a skeleton file).
        clip: the motion clip (name, path, skeleton map, unit, fps, frames, ...).

    A recording (:func:`~torchmocap.data.recordings.load_recording`):
        path, calibration: the recording folder and its calibration file.
        calibration_names: the calibration entries of the loaded cameras.
        frames: the video or image folder of each camera.
        frame_indices: the loaded frames' indices in the videos.
        fps, fps_source: the frame rate and where it came from (``video``, ``data.fps``,
            ``default``).
        image_sizes, calibrated_image_sizes: ``{camera: [W, H]}`` decoded and calibrated.
        keypoint_format: the detections' format (None: no keypoints).
        keypoint_source: the keypoint source's name (:mod:`~torchmocap.data.recordings.keypoints`).
        keypoint_report: what the keypoint source read or computed.
        selection: the person selection's report per view.
        masks: the mask folder of each camera (mask files), else None.
        mask_source: ``files``, ``computed`` or None.
        mask_report: the computed masks' report (cache entry, preview, fractions).
        background: the background plates of each camera.
        images_bytes: bytes of the decoded images.
        view_consistency: each view's agreement with the others on the first frames, the
            subject's triangulated size and the cameras' distances to it
            (:func:`~torchmocap.data.recordings.checks.view_consistency`).
        calibration_refinement: the self-calibration's record when ``data.calibration.refine``
            (:func:`~torchmocap.data.recordings.self_calibration.refine_rig`: objective, frames,
            groups, per-camera report, time offsets, the refined rig at the calibrated sizes).

    The subject and the first pose fitted by the source (:mod:`torchmocap.data.subjects`):
        subject_skeleton: the tracking skeleton (:meth:`~torchmocap.skeleton.Skeleton.to_dict`).
        initial_poses: ``(K, D)`` candidate first poses, the best first.
        skeleton_scale: the subject's size relative to human31.
        keypoint_map: the keypoint map fitted with the subject
            (:meth:`~torchmocap.skeleton.KeypointMap.to_dict`).
        subject_fit: the keypoint fit's report (or why it was skipped: ``{"skipped": ...}``).
        hull_centre, hull_top_m: the visual hull's centre and top (a masks-only start).

    Anything else:
        extra: information of a user's data source that the package does not read.
    """

    source: str | None = None
    inputs: dict[str, str] | None = None
    cameras: list[str] | None = None
    heldout_camera: str | None = None
    scale: float | None = None
    suggested_tracker: str | None = None
    # synthesis
    seed: int | None = None
    scenario: dict[str, Any] | None = None
    body: str | None = None
    phenotype: dict[str, float] | None = None
    body_height: float | None = None
    subject: dict[str, Any] | None = None
    timings: dict[str, float] | None = None
    joints2d_occluded_fraction: float | None = None
    skeleton: str | None = None
    clip: dict[str, Any] | None = None
    # recordings
    path: str | None = None
    calibration: str | None = None
    calibration_names: list[str] | None = None
    frames: dict[str, str] | None = None
    frame_indices: list[int] | None = None
    fps: float | None = None
    fps_source: str | None = None
    image_sizes: dict[str, list[int]] | None = None
    calibrated_image_sizes: dict[str, list[int]] | None = None
    keypoint_format: str | None = None
    keypoint_source: str | None = None
    keypoint_report: dict[str, Any] | None = None
    selection: dict[str, Any] | None = None
    masks: dict[str, str] | None = None
    mask_source: str | None = None
    mask_report: dict[str, Any] | None = None
    background: dict[str, list[str]] | None = None
    images_bytes: int | None = None
    view_consistency: dict[str, Any] | None = None
    calibration_refinement: dict[str, Any] | None = None
    # the subject fitted by the source
    subject_skeleton: dict[str, Any] | None = None
    initial_poses: list[list[float]] | None = None
    skeleton_scale: float | None = None
    keypoint_map: dict[str, Any] | None = None
    subject_fit: dict[str, Any] | None = None
    hull_centre: list[float] | None = None
    hull_top_m: float | None = None
    # a user's own
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The record's fields (without ``extra``)."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.name != "extra")

    def update(self, entries: Mapping[str, Any]) -> SequenceMeta:
        """Set the fields named in ``entries`` (e.g. what a subject fit returns); returns self.

        Raises:
            KeyError: a name that is not a field (with the closest one).
        """
        names = self.field_names()
        for k, v in entries.items():
            if k not in names:
                import difflib

                near = difflib.get_close_matches(k, names, n=1)
                raise KeyError(f"meta: {k!r} is not a SequenceMeta field"
                               + (f" (did you mean {near[0]!r}?)" if near else "")
                               + "; keep a data source's own information in meta.extra")
            setattr(self, k, v)
        return self

    def to_dict(self) -> dict[str, Any]:
        """The fields that are set (not None) and ``extra``'s entries, as a plain dict."""
        out = {k: v for k in self.field_names() if (v := getattr(self, k)) is not None}
        out.update(self.extra)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> SequenceMeta:
        """The record of a dict written by :meth:`to_dict` (entries that are not fields go to
        ``extra``)."""
        if data is None:
            return cls()
        if isinstance(data, SequenceMeta):
            return copy.deepcopy(data)
        if not isinstance(data, Mapping):
            raise TypeError(f"meta: expected a SequenceMeta or a mapping, got "
                            f"{type(data).__name__}")
        names = set(cls.field_names())
        known = {k: v for k, v in data.items() if k in names}
        extra = {k: v for k, v in data.items() if k not in names}
        return cls(**known, extra=extra)
