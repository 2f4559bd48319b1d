"""A real multi-view recording as a :class:`~torchmocap.data.Sequence`: :func:`load_recording`.

The folder layout is that of :mod:`torchmocap.data.recordings.files` (calibration, a video or
image folder per camera, optional OpenPose keypoints, masks and background plates); see
``docs/recordings.md``. What the loader checks:

* every chosen camera has a calibration entry (matched by the number in its name, refused when
  missing or ambiguous);
* the calibrated image size is the decoded one — except a codec's macroblock crop (the
  calibrated size is the decoded one rounded up to a multiple of 16, e.g. a 1088-row H.264
  stream cropped to 1080): accepted with a warning, the camera keeps the decoded size (its
  intrinsics are unchanged); and a calibration of the same aspect ratio at another resolution
  (a 4K calibration of 1088x1920 videos): its intrinsics are scaled, with a warning;
* the videos have one frame rate and (unless ``stop`` stays within the shortest) one length;
  views of different sizes (a codec's crop, cameras of other resolutions) share one image
  tensor, the smaller ones padded with black at the right/bottom (``rig.image_size`` and
  ``meta.image_sizes`` have each view's own size);
* keypoint files exist for every loaded frame and are of the declared format.

Memory: the images are ``T × C × H × W × 3`` bytes at the working scale — 100 frames of 4
views of 1088x1920 at ``scale=0.5`` are 100 · 4 · 544 · 960 · 3 B ≈ 0.63 GB (2.5 GB at full
scale); frames are decoded and scaled one at a time, so the full-resolution frames are never
all in memory.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchmocap.cameras import CameraError, CameraRig, camera_key, read_calibration
from torchmocap.data.recordings.checks import (
    check_camera_choice,
    check_detections,
    check_mode,
    check_views,
    mask_consistency,
    view_consistency,
)
from torchmocap.data.recordings.files import (
    RecordingCamera,
    discover_recording,
)
from torchmocap.data.recordings.keypoints import (
    KeypointRequest,
    KeypointSource,
    choose_keypoint_source,
    keypoint_settings,
)
from torchmocap.data.recordings.mask_source import (
    check_mask_settings,
    detector_masks,
    mask_mode,
    read_plates,
    recording_masks,
)
from torchmocap.data.recordings.person_selection import person_agreement, select_person
from torchmocap.data.recordings.self_calibration import (
    calibration_settings,
    refine_range,
    refine_rig,
    shift_detections,
    warn_overlap,
)
from torchmocap.data.sources import data_source
from torchmocap.data.subjects.recorded import hull_start, keypoint_start, subject_settings
from torchmocap.io.frames import (
    IMAGE_SUFFIXES,
    FrameSourceError,
    VideoFrames,
    check_frame_range,
    numbered_files,
    open_frames,
    read_mask,
    resize_image,
    scaled_size,
)
from torchmocap.io.openpose import keypoint_format

__all__ = ["CROP_TOLERANCE", "calibrate_recording", "load_recording"]

log = logging.getLogger(__name__)

#: a codec's macroblock size: a decoded frame may lack the pixels that pad its size to a
#: multiple of it at the right / bottom edge (a codec's crop)
CROP_TOLERANCE = 16
#: frame rate of image folders without ``fps``
DEFAULT_FPS = 25.0


class _LazySizes(Mapping):
    """Decoded ``(width, height)`` by camera name, opening a camera's frames only when asked
    (a calibration that stores no sizes asks for every camera it has)."""

    def __init__(self, cameras: Sequence[RecordingCamera], opened: dict[str, Any]) -> None:
        self._cams = {c.name: c for c in cameras}
        self._opened = opened

    def __getitem__(self, name: str) -> tuple[int, int]:
        if name not in self._opened:
            self._opened[name] = open_frames(self._cams[name].frames)
        return self._opened[name].size

    def __iter__(self) -> Iterator[str]:
        return iter(self._cams)

    def __len__(self) -> int:
        return len(self._cams)


def _find_camera(cams: list[RecordingCamera], name: str) -> list[RecordingCamera]:
    """The cameras called ``name``, else those with its number (:func:`camera_key`)."""
    return [c for c in cams if c.name == name] or [c for c in cams if c.key == camera_key(name)]


def _heldout_index(chosen: list[RecordingCamera], cams: list[RecordingCamera], heldout
                   ) -> int | None:
    """Index among the loaded cameras of the held-out one (by name or index in
    ``data.cameras``' order), None for none."""
    if heldout is None:
        return None
    where = "evaluation.heldout_camera"
    names = [c.name for c in chosen]
    if isinstance(heldout, bool) or not isinstance(heldout, (str, int)):
        raise ValueError(f"{where}: expected a camera name or index, got {heldout!r}")
    if isinstance(heldout, int):
        if not 0 <= heldout < len(chosen):
            raise ValueError(f"{where}: index {heldout} out of range for the {len(chosen)} "
                             f"loaded cameras {names}")
        h = heldout
    else:
        hits = _find_camera(chosen, heldout)
        if len(hits) != 1:
            if len(_find_camera(cams, heldout)) == 1:
                raise ValueError(f"{where}: camera {heldout!r} is not among the loaded cameras "
                                 f"(data.cameras: {names}); add it there to hold it out")
            raise ValueError(f"{where}: unknown camera {heldout!r}; the recording has "
                             f"{[c.name for c in cams]}")
        h = chosen.index(hits[0])
    if len(chosen) < 2:
        raise ValueError(f"{where}: holding out {names[h]!r} leaves no camera to track with "
                         f"(data.cameras: {names})")
    return h


def _choose_cameras(cams: list[RecordingCamera], cameras) -> list[RecordingCamera]:
    if cameras is None:
        return cams
    if isinstance(cameras, (str, int)):
        cameras = [cameras]
    names = [c.name for c in cams]
    out = []
    for sel in cameras:
        if isinstance(sel, bool) or not isinstance(sel, (str, int)):
            raise ValueError(f"data.cameras: expected camera names or indices, got {sel!r}")
        if isinstance(sel, int):
            if not 0 <= sel < len(cams):
                raise ValueError(f"data.cameras: index {sel} out of range; the recording has "
                                 f"{len(cams)} cameras {names}")
            cam = cams[sel]
        else:
            hits = _find_camera(cams, sel)
            if len(hits) != 1:
                raise ValueError(f"data.cameras: unknown camera {sel!r}; the recording has "
                                 f"{names}")
            cam = hits[0]
        if cam in out:
            raise ValueError(f"data.cameras: camera {cam.name!r} chosen twice")
        out.append(cam)
    if not out:
        raise ValueError("data.cameras: expected at least one camera")
    return out


def _match_calibration(rig: CameraRig, cams: list[RecordingCamera], path: Path) -> list[int]:
    idx = []
    for cam in cams:
        hits = [i for i, n in enumerate(rig.names) if camera_key(n) == cam.key]
        if not hits:
            raise CameraError(f"{path}: no calibration for camera {cam.name!r} ({cam.frames}); "
                              f"the calibration has {rig.names}")
        if len(hits) > 1:
            raise CameraError(f"{path}: calibration entries {[rig.names[i] for i in hits]} all "
                              f"match camera {cam.name!r}; rename them")
        idx.append(hits[0])
    return idx


def _codec_crop(calibrated: int, decoded: int) -> bool:
    """Whether ``decoded`` pixels are a codec's crop of ``calibrated``: the encoder pads a
    frame to a multiple of :data:`CROP_TOLERANCE` (its macroblocks) and the decoder crops the
    padding again, so the calibrated size is the decoded one rounded up to that multiple."""
    m = CROP_TOLERANCE
    return calibrated == decoded or (calibrated % m == 0 and calibrated == -(-decoded // m) * m)


def _check_sizes(rig: CameraRig, sources: list, cams: list[RecordingCamera], calib: Path
                 ) -> CameraRig:
    """The rig with each camera's decoded size: a codec's crop accepted with a warning (the
    intrinsics unchanged), a calibration of the same aspect ratio at another resolution scaled
    with a warning, any other size refused."""
    sizes, K = [], rig.K.clone()
    for c, (src, cam) in enumerate(zip(sources, cams)):
        W, H = (int(v) for v in rig.image_size[c].tolist())
        w, h = src.size
        if (w, h) != (W, H):
            if _codec_crop(W, w) and _codec_crop(H, h):
                warnings.warn(f"{cam.frames}: frames are {w}x{h}, the calibration "
                              f"({rig.names[c]}) says {W}x{H}: a codec's crop of {W - w} "
                              f"columns / {H - h} rows at the right / bottom edge (assumed: the "
                              f"video was coded at {W}x{H}, the next multiple of "
                              f"{CROP_TOLERANCE} pixels, and cropped); using {w}x{h} with the "
                              "intrinsics unchanged", stacklevel=3)
            elif W * h == H * w:
                f = w / W
                K[c] = rig.subset([c]).scaled_images(f).K[0]
                warnings.warn(f"{cam.frames}: frames are {w}x{h}, the calibration "
                              f"({rig.names[c]}) is of {W}x{H} images, the same aspect ratio: "
                              f"its intrinsics are scaled by {f:g} (assumed: the same camera "
                              "and lens recorded at another resolution)", stacklevel=3)
            else:
                raise CameraError(
                    f"{cam.frames}: frames are {w}x{h} but the calibration ({calib}, "
                    f"{rig.names[c]}) says {W}x{H}; the calibration is of other images (not a "
                    f"codec's crop, which lacks fewer than {CROP_TOLERANCE} pixels of a multiple "
                    f"of {CROP_TOLERANCE}, nor another resolution of the same aspect ratio)")
        sizes.append((w, h))
    return CameraRig(K, rig.R, rig.t, sizes, rig.dist, [c.name for c in cams])


def _check_streams(sources: list, cams: list[RecordingCamera], fps, stop) -> tuple[float, int,
                                                                                   str]:
    """Common frame rate, usable frame count, and where the rate came from."""
    videos = [(s, c) for s, c in zip(sources, cams) if isinstance(s, VideoFrames)]
    rates = {round(s.fps, 3) for s, _ in videos}
    if len(rates) > 1:
        raise FrameSourceError("videos of different frame rates: " + ", ".join(
            f"{c.frames} {s.fps:g} fps" for s, c in videos))
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float)) or
                            not (math.isfinite(fps) and fps > 0)):
        raise ValueError(f"data.fps: expected a frame rate > 0 or null, got {fps!r}")
    if videos:
        rate, origin = videos[0][0].fps, "video"
        if fps is not None and abs(fps - rate) > 1e-3 * rate:
            raise ValueError(f"data.fps: {fps} differs from the videos' {rate:g} fps (data.fps "
                             "is for image folders)")
    else:
        rate, origin = (float(fps), "data.fps") if fps is not None else (DEFAULT_FPS, "default")
    counts = [s.num_frames for s in sources]
    if len(set(counts)) > 1 and (stop is None or (isinstance(stop, int) and stop > min(counts))):
        raise FrameSourceError(
            "cameras of different lengths: " + ", ".join(
                f"{c.frames} {n} frames" for c, n in zip(cams, counts)) +
            f"; set data.stop <= {min(counts)} to use the frames all of them have")
    return rate, min(counts), origin


def _read_masks(cam: RecordingCamera, frames: range, size: tuple[int, int], scale: float
                ) -> Iterator[np.ndarray]:
    files = numbered_files(cam.masks, IMAGE_SUFFIXES)
    from PIL import Image

    for t in frames:
        if t not in files:
            raise FrameSourceError(f"{cam.masks}: no mask file for frame {t}")
        m = Image.fromarray(read_mask(files[t], size))
        yield np.asarray(resize_image(m, scale, Image.NEAREST))


def _scale_joints(joints: torch.Tensor, scale: float) -> torch.Tensor:
    """Pixels of the full-size images to the scaled ones (``u' + 0.5 = s (u + 0.5)``)."""
    seen = joints[..., 2:3] > 0
    uv = scale * (joints[..., :2] + 0.5) - 0.5
    return torch.where(seen, torch.cat([uv, joints[..., 2:3]], -1), torch.zeros_like(joints))


def _canvas(sources: list, scale: float) -> tuple[int, int]:
    """``(W, H)`` of the image tensor: the largest scaled view; smaller views (a codec's crop,
    a camera of another resolution) fill its top-left corner, padded black at the right /
    bottom (``rig.image_size`` and ``meta.image_sizes`` keep each view's own size)."""
    sizes = [scaled_size(s.size, scale) for s in sources]
    return max(w for w, _ in sizes), max(h for _, h in sizes)


def _read_keypoints(source: KeypointSource, request: KeypointRequest, rig: CameraRig
                    ) -> tuple[list[list[torch.Tensor]], str, bool, dict]:
    """The source's detections of every requested view (full-size pixels), checked
    (:func:`~torchmocap.data.recordings.checks.check_detections`), their format, whether they
    are associated, and the source's report."""
    det = source.read(request)
    names = [c.name for c in request.cameras]
    folders = det.report.get("folders") if isinstance(det.report, dict) else None
    # --- checks: the detections (torchmocap.data.recordings.checks) ---
    people = check_detections(
        det.people, len(keypoint_format(det.format)), names,
        [tuple(int(v) for v in s) for s in rig.image_size.tolist()],
        [str(folders.get(n, "")) for n in names] if isinstance(folders, dict) else None,
        list(request.frames))
    return people, det.format, det.associated, det.report


def _select_keypoints(people: list[list[torch.Tensor]], fmt: str, associated: bool,
                      kp: dict[str, Any], rig: CameraRig, names: list[str], scale: float
                      ) -> tuple[torch.Tensor, dict]:
    """``joints2d (T, C, K, 3)`` float32 in the scaled images' pixels of the subject chosen
    among ``people`` (full-size pixels) and the selection report."""
    K = len(keypoint_format(fmt))
    if not associated or any(x.shape[0] > 1 for frame in people for x in frame):
        joints, selection = select_person(people, rig, kp["min_confidence"])
        selection["method"] = "triangulation"
    else:
        joints = torch.stack([torch.stack([
            x[0] if x.shape[0] else torch.zeros(K, 3, dtype=torch.float64) for x in frame])
            for frame in people])
        low = joints[..., 2] < kp["min_confidence"]
        joints = torch.where(low[..., None], torch.zeros_like(joints), joints)
        agree = person_agreement(joints, rig)
        selection = {"method": "associated", "views": {
            name: {"people": [int(frame[c].shape[0]) for frame in people],
                   "agreement_px": [None if math.isnan(v) else round(v, 2)
                                    for v in agree[:, c].tolist()]}
            for c, name in enumerate(names)}}
    return _scale_joints(joints, scale).float(), selection


@data_source(provides=("images", "silhouettes", "joints2d", "rig"),
             trackers=("real_keypoints", "real_local", "real_sir", "real_mixture"))
def load_recording(path: str | Path, cameras: Sequence[str | int] | str | int | None = None,
                   start: int = 0, stop: int | None = None, stride: int = 1,
                   scale: float = 0.5, keypoints: Mapping[str, Any] | None = None,
                   masks: str = "auto", mask_settings: Mapping[str, Any] | None = None,
                   mask_cache: str | Path | None = None, subject: Mapping[str, Any] | None = None,
                   heldout_camera: str | int | None = None,
                   fps: float | None = None, unit: str | float | None = None,
                   checks: str = "refuse", calibration: Mapping[str, Any] | None = None,
                   min_views: int = 0, seed: int = 0):
    """A recording folder as a :class:`~torchmocap.data.Sequence` (``scenario="recorded"``).

    Args:
        path: the recording folder (layout: :mod:`torchmocap.data.recordings.files`).
        cameras: the cameras to load, by name (``"cam01"``, or anything with its number) or by
            index in name order; None = all.
        start, stop, stride: frames ``start, start + stride, … < stop`` (stop None = the end).
        scale: image scale in (0, 1]; the rig is scaled with
            :meth:`~torchmocap.cameras.CameraRig.scaled_images`, keypoints with it.
        keypoints: ``source`` (a registered keypoint source,
            :mod:`torchmocap.data.recordings.keypoints`: ``openpose``, ``mediapipe`` (computed
            from the frames); ``auto``: the first whose files every camera has, else none;
            ``none``), ``format`` (``auto``, ``body_25b``, ``body_25``, ``coco_17``,
            ``halpe_26``, ``mediapipe_33``), ``min_confidence`` (keypoints below it count as
            missed: confidence and position 0), and the chosen source's own settings
            (``openpose``: ``folder``; ``mediapipe``: ``cache``, ...). Defaults:
            :data:`~torchmocap.data.recordings.keypoints.KEYPOINT_SETTINGS` and the source's
            config file.
        masks: ``auto`` (mask files when every camera has them, else computed when the
            recording has keypoints or background plates, else none), ``files`` (required),
            ``compute``, ``detector`` (the keypoint detector's person masks), ``none``
            (:mod:`torchmocap.data.recordings.mask_source`).
        mask_settings: :class:`~torchmocap.data.recordings.masks.MaskSettings` of computed masks
            (their
            dict form without ``scale``: the masks are computed at ``scale``).
        mask_cache: folder caching computed masks (and their preview PNGs); None = no cache.
        subject: settings of the subject fit to the keypoints
            (:func:`~torchmocap.data.subjects.recorded.subject_settings`: ``frames``,
            ``max_error_px``, ``keypoint_map``).
        heldout_camera: a camera (name, or index among the loaded ones) held out of what a
            tracker sees: the masks of the other views, the subject fit and the person selection
            use only the others; :func:`~torchmocap.data.heldout.split_heldout` splits the
            sequence into the tracked views and the held-out one.
        fps: frame rate of image folders (videos carry theirs; default 25 with a warning).
        unit: length unit of the calibration's translations; None = the format's default
            (TOML and intri/extri metres, Bouguet millimetres).
        checks: ``refuse`` (default) or ``warn``: what views that disagree with the others
            and a subject whose triangulated size is not a person's are
            (:mod:`~torchmocap.data.recordings.checks`; the report is
            ``meta.view_consistency``).
        calibration: the self-calibration settings
            (:func:`~torchmocap.data.recordings.self_calibration.calibration_settings`:
            ``refine`` (default false), ``frames`` (``[start, stop)`` of the recording; null =
            the first half of the loaded frames), ``groups``, ``objective`` (``bundle`` |
            ``model``), ``priors``, ``loss``, ...): with ``refine`` the rig is refined from the
            subject's detections on those frames (every loaded camera) before anything else
            uses it; ``meta.calibration_refinement`` has the report and the refined rig.
        min_views: tracked views the caller needs (the commands: 2, to triangulate the
            subject); fewer are refused before anything is read.
        seed: unused (loading is deterministic); accepted like every data source's.

    Returns:
        the :class:`~torchmocap.data.Sequence`: ``fps``, ``rig`` (float32, the chosen cameras,
        scaled), ``images (T, C, H, W, 3)`` uint8, ``view_dropped (T, C)`` False,
        ``silhouettes (T, C, H, W)`` bool when masks are loaded, ``joints2d (T, C, K, 3)``
        float32 (u, v, confidence in the scaled images' pixels; zeros = not detected) with
        ``joint_names`` the format's keypoint names when keypoints are loaded, and ``meta``:
        ``source: "recording"``, ``path``, ``calibration``, ``cameras``,
        ``calibration_names``, ``frames`` (video / folder per camera), ``frame_indices``,
        ``fps``, ``fps_source``, ``scale``, ``image_sizes`` (decoded, per camera),
        ``calibrated_image_sizes``, ``keypoint_format``, ``keypoint_source`` (the source's
        name), ``keypoint_report`` (what it read or computed; with a held-out camera the
        tracked views' read, that of every view under ``with_heldout_view``), ``selection``
        (per view: people per frame, the chosen person, frames with several people,
        reprojection agreement in px of the full-size images), ``masks`` (the folders or
        None), ``mask_source`` (``files``, ``computed``, ``detector`` or None), ``mask_report``
        (computed masks: :func:`~torchmocap.data.recordings.masks.compute_masks`' report,
        cache entry, preview; detector masks:
        :func:`~torchmocap.data.recordings.mask_source.detector_masks`'),
        ``background`` (plate paths per camera), ``images_bytes``, ``heldout_camera`` (name
        or None); with keypoints the fitted subject (``subject_skeleton``, ``initial_poses``,
        ``keypoint_map``, ``skeleton_scale``, ``subject_fit``), with masks only a visual-hull
        start (``subject_skeleton``, ``initial_poses`` one per heading, ``hull_top_m``): see
        :mod:`torchmocap.data.subjects.recorded`.

    Raises:
        RecordingLayoutError: missing folder, calibration, frames or keypoints (named).
        CameraError: a camera without (or with ambiguous) calibration, a calibrated size that
            is not the decoded one.
        FrameSourceError: unreadable videos/images/masks, videos of different rates or
            lengths, missing per-frame files (named).
        KeypointFormatError: keypoint files of another format, empty or unparsable.
        ValueError: a setting out of bounds (named ``data.<setting>``).

    Example:
        >>> seq = load_recording("pose2sim_balancing", stop=4, cameras=["cam03"])  # doctest: +SKIP
        >>> seq.images.shape, seq.joints2d.shape                                   # doctest: +SKIP
        (torch.Size([4, 1, 960, 544, 3]), torch.Size([4, 1, 25, 3]))
    """
    from torchmocap.data.metadata import SequenceMeta
    from torchmocap.data.sequence import Sequence as Seq

    files = discover_recording(path)
    chosen = _choose_cameras(files.cameras, cameras)
    h = _heldout_index(chosen, files.cameras, heldout_camera)
    # --- checks: enough tracked views, the check mode (torchmocap.data.recordings.checks) ---
    check_camera_choice([c.name for c in chosen], None if h is None else chosen[h].name,
                        min_views)
    check_mode(checks)
    seen = [i for i in range(len(chosen)) if i != h]
    kp = keypoint_settings(keypoints)
    fit_settings = subject_settings(subject)
    settings = check_mask_settings(mask_settings)
    cal = calibration_settings(calibration)
    opened: dict[str, Any] = {}
    sources = [opened.setdefault(c.name, open_frames(c.frames)) for c in chosen]
    rate, length, fps_source = _check_streams(sources, chosen, fps, stop)
    try:
        frames = check_frame_range(length, start, stop, stride, scale, "the recording")
    except ValueError as e:
        raise ValueError(f"data.{e}") from None
    for src in sources:  # numbered images pair by number: a gap is refused, never shifted
        if hasattr(src, "check_complete"):
            src.check_complete(frames.start, frames.stop, frames.step)
    if fps_source == "default" and len(frames) > 1:
        warnings.warn(f"{files.root}: image folders carry no frame rate; using "
                      f"{DEFAULT_FPS:g} fps (set data.fps)", stacklevel=2)
    files = _calibration_file(files, cal["file"])
    full = read_calibration(files.calibration, _LazySizes(files.cameras, opened), unit)
    idx = _match_calibration(full, chosen, files.calibration)
    calibrated = full.subset(idx)
    rig = _check_sizes(calibrated, sources, chosen, files.calibration)

    canvas = _canvas(sources, scale)
    request = KeypointRequest(files.root, chosen, frames, kp["format"], sources)
    source = choose_keypoint_source(kp, request)
    mode = mask_mode(masks, chosen, source is not None, files.root, source)
    joints2d, fmt, selection, kp_report, consistency = None, None, None, None, None
    names = [c.name for c in chosen]
    refinement = None
    if cal["refine"]:
        rig, refinement = _self_calibrate(source, files, chosen, sources, rig, calibrated, kp,
                                          cal, frames, length, rate, fit_settings, unit,
                                          None if h is None else chosen[h].name)
    request_seen, seen_report = request, None
    if source is not None:
        people, fmt, associated, kp_report = _read_keypoints(source, request, rig)
        joints2d, selection = _select_keypoints(people, fmt, associated, kp, rig, names, scale)
        seen_report = kp_report
    if source is not None and h is not None:  # the tracked views' person chosen without it
        rig_seen, names_seen = rig.subset(seen), [names[i] for i in seen]
        if source.views_interact:  # its detections of a view depend on the others: again
            request_seen = KeypointRequest(files.root, [chosen[i] for i in seen], frames,
                                           kp["format"], [sources[i] for i in seen])
            people_seen, _, associated, seen_report = _read_keypoints(source, request_seen,
                                                                      rig_seen)
            # the tracked views' report; the held-out view's detections came from every view
            kp_report = {**seen_report, "with_heldout_view": kp_report}
        else:
            people_seen = [[frame[i] for i in seen] for frame in people]
        chosen_seen, selection = _select_keypoints(people_seen, fmt, associated, kp, rig_seen,
                                                   names_seen, scale)
        joints2d[:, seen] = chosen_seen
    if joints2d is not None and refinement is not None and \
            any(v != 0.0 for v in refinement["time_offsets"]):  # onto the subject's clock
        joints2d = shift_detections(joints2d, torch.tensor(refinement["time_offsets"]) /
                                    frames.step)
    if joints2d is not None:
        # --- checks: the views' agreement and the units (torchmocap.data.recordings.checks) ---
        first = min(int(fit_settings["frames"]), len(frames))
        consistency = view_consistency(joints2d[:first], rig.scaled_images(scale), names,
                                       scale, list(frames)[:first],
                                       None if h is None else names[h])
        check_views(consistency, checks, unit, files.calibration)
    T, C = len(frames), len(chosen)
    images = torch.zeros(T, C, canvas[1], canvas[0], 3, dtype=torch.uint8)
    log.info("loading %d frames x %d views of %dx%d: %.2f GB of images", T, C, *canvas,
             images.numel() / 1e9)
    for c, src in enumerate(sources):
        w, h_img = scaled_size(src.size, scale)
        for t, frame in enumerate(src.frames(frames.start, frames.stop, frames.step, scale)):
            images[t, c, :h_img, :w].numpy()[:] = frame
    meta = SequenceMeta(
        source="recording", path=str(files.root), calibration=str(files.calibration),
        cameras=[c.name for c in chosen], calibration_names=calibrated.names,
        frames={c.name: str(c.frames) for c in chosen},
        frame_indices=list(frames), fps=rate, fps_source=fps_source, scale=scale,
        image_sizes={c.name: list(s.size) for c, s in zip(chosen, sources)},
        calibrated_image_sizes={c.name: [int(v) for v in calibrated.image_size[i].tolist()]
                                for i, c in enumerate(chosen)},
        keypoint_format=fmt, keypoint_source=None if source is None else source.name,
        keypoint_report=kp_report, selection=selection,
        masks={c.name: str(c.masks) for c in chosen} if mode == "files" else None,
        mask_source={"files": "files", "compute": "computed", "detector": "detector"}.get(mode),
        background={c.name: [str(p) for p in c.background] for c in chosen},
        images_bytes=images.numel(),
        heldout_camera=None if h is None else chosen[h].name,
        view_consistency=consistency, calibration_refinement=refinement)
    seq = Seq(fps=rate, scenario="recorded", rig=rig.scaled_images(scale).float(),
              view_dropped=torch.zeros(T, C, dtype=torch.bool), images=images,
              joints2d=joints2d, joint_names=[] if fmt is None else list(keypoint_format(fmt)),
              meta=meta)
    tracked = seq if h is None else seq.select_cameras(seen)
    if mode == "files":
        seq.silhouettes = torch.zeros(T, C, canvas[1], canvas[0], dtype=torch.bool)
        for c, (src, cam) in enumerate(zip(sources, chosen)):
            w, h_img = scaled_size(src.size, scale)
            for t, m in enumerate(_read_masks(cam, frames, src.size, scale)):
                seq.silhouettes[t, c, :h_img, :w].numpy()[:] = m
    elif mode == "compute":
        seq.silhouettes, meta.mask_report = _computed_masks(
            seq, tracked, seen, h, read_plates(chosen, scale), settings, mask_cache)
    elif mode == "detector":  # the tracked views' from their own check, as their keypoints
        seq.silhouettes, meta.mask_report = detector_masks(source, request_seen, seen_report,
                                                           scale, canvas)
        if h is not None:  # the held-out view's from the check with every view
            one = KeypointRequest(files.root, [chosen[h]], frames, kp["format"], [sources[h]])
            held, _ = detector_masks(source, one, kp_report["with_heldout_view"], scale, canvas)
            seq.silhouettes = torch.cat([seq.silhouettes, held], 1)[
                :, [seen.index(c) if c in seen else len(seen) for c in range(C)]]
    if h is not None:
        tracked.silhouettes = None if seq.silhouettes is None else \
            seq.select_cameras(seen).silhouettes
    if joints2d is not None and tracked.num_cameras < 2:
        meta.subject_fit = {"skipped": f"the keypoints of one view ({tracked.rig.names}) "
                                          "cannot be triangulated"}
    elif joints2d is not None:
        meta.update(keypoint_start(tracked.joints2d, tracked.joint_names, fmt, tracked.rig,
                                   fit_settings, scale))
    elif tracked.silhouettes is not None and tracked.num_cameras >= 2:
        # --- checks: the views' masks agree (torchmocap.data.recordings.checks) ---
        meta.view_consistency = mask_consistency(seq.silhouettes[0], seq.rig, names,
                                                 meta.heldout_camera)
        check_views(meta.view_consistency, checks)
        meta.update(hull_start(tracked.rig, tracked.silhouettes[0]))
    elif tracked.silhouettes is None:
        meta.subject_fit = {"skipped": "the recording has neither keypoints nor masks (no "
                                       "pose/ or pose-associated/ files); "
                                       "data.keypoints.source=mediapipe computes keypoints "
                                       "from the frames"}
    return seq


def _calibration_file(files, file: str | None):
    """The recording's files with ``data.calibration.file`` (relative to the working directory)
    in place of its own calibration."""
    if file is None:
        return files
    p = Path(file).expanduser()
    if not p.exists():
        raise ValueError(f"data.calibration.file: {p} does not exist (a calibration file, e.g. "
                         "a run's calibration/Calib_refined.toml, or a folder holding one)")
    from torchmocap.inputs import note_input

    note_input(p)  # a changed file changes the run's fingerprint
    return dataclasses.replace(files, calibration=p.resolve())


def _self_calibrate(source, files, chosen, sources, rig: CameraRig, calibrated: CameraRig,
                    kp, cal, frames: range, length: int, rate: float, subject, unit,
                    heldout: str | None) -> tuple[CameraRig, dict]:
    """The rig refined from the detections of ``data.calibration.frames`` (every loaded
    camera), and the refinement's record (the refined rig at the calibrated image sizes
    under ``rig``, for writing it in the recording's format)."""
    from torchmocap.cameras import rig_to_dict

    if source is None:
        raise ValueError("data.calibration.refine: the recording has no keypoints to refine "
                         "its calibration from (no pose/ or pose-associated/ files); "
                         "data.keypoints.source=mediapipe computes them from the frames")
    if len(chosen) < 2:
        raise ValueError(f"data.calibration.refine: refining a calibration needs at least two "
                         f"cameras, got {[c.name for c in chosen]} (data.cameras)")
    span = refine_range(cal, frames, length)
    warn_overlap(span, frames, heldout)
    request = KeypointRequest(files.root, chosen, span, kp["format"], sources)
    people, fmt, associated, _ = _read_keypoints(source, request, rig)
    det, _ = _select_keypoints(people, fmt, associated, kp, rig, [c.name for c in chosen], 1.0)
    refined, record = refine_rig(det, rig, list(keypoint_format(fmt)), fmt, cal, rate, span,
                                 subject)
    written = CameraRig(refined.K, refined.R, refined.t, calibrated.image_size, refined.dist,
                        calibrated.names)
    record["rig"] = rig_to_dict(written)
    record["unit"] = unit
    record["calibration"] = str(files.calibration)
    return refined, record


def _computed_masks(seq, tracked, seen: list[int], h: int | None, plates, settings, cache
                    ) -> tuple[torch.Tensor, dict]:
    """Masks of every view of ``seq``: the tracked views' computed from them alone, the
    held-out view's (view ``h``) from every view (it scores the track, it is not tracked)."""
    T, C, H, W = seq.images.shape[:4]
    out = torch.zeros(T, C, H, W, dtype=torch.bool)
    masks, report = recording_masks(tracked.images, tracked.rig, [plates[i] for i in seen],
                                    tracked.joints2d, settings, cache)
    out[:, seen, :masks.shape[2], :masks.shape[3]] = masks
    if h is not None:
        every, rep = recording_masks(seq.images, seq.rig, plates, seq.joints2d, settings, cache)
        out[:, h] = every[:, h]
        report["heldout_view"] = {k: rep[k] for k in ("mask_fraction", "cache", "preview")
                                  if k in rep}
    return out, report


def calibrate_recording(path: str | Path, cameras: Sequence[str | int] | str | int | None = None,
                        start: int = 0, stop: int | None = None, stride: int = 1,
                        keypoints: Mapping[str, Any] | None = None,
                        subject: Mapping[str, Any] | None = None, fps: float | None = None,
                        unit: str | float | None = None,
                        calibration: Mapping[str, Any] | None = None, **_: Any
                        ) -> tuple[CameraRig, dict]:
    """Refine a recording's calibration from the subject's detections, without loading its
    images (``torchmocap-calibrate``): the settings of :func:`load_recording` (``data.*``; the
    image, mask and check settings are accepted and unused), ``calibration.refine`` implied.

    Returns:
        ``(rig, record)``: the refined rig at the decoded image sizes and the refinement's
        record (``record["rig"]``: the refined rig at the calibrated sizes, what
        :func:`~torchmocap.data.recordings.self_calibration.write_refinement` writes).

    Raises:
        the errors of :func:`load_recording` for these settings.
    """
    files = discover_recording(path)
    chosen = _choose_cameras(files.cameras, cameras)
    kp = keypoint_settings(keypoints)
    fit_settings = subject_settings(subject)
    cal = calibration_settings({**dict(calibration or {}), "refine": True})
    opened: dict[str, Any] = {}
    sources = [opened.setdefault(c.name, open_frames(c.frames)) for c in chosen]
    rate, length, _ = _check_streams(sources, chosen, fps, stop)
    try:
        frames = check_frame_range(length, start, stop, stride, 1.0, "the recording")
    except ValueError as e:
        raise ValueError(f"data.{e}") from None
    files = _calibration_file(files, cal["file"])
    full = read_calibration(files.calibration, _LazySizes(files.cameras, opened), unit)
    idx = _match_calibration(full, chosen, files.calibration)
    calibrated = full.subset(idx)
    rig = _check_sizes(calibrated, sources, chosen, files.calibration)
    span = refine_range(cal, frames, length)
    request = KeypointRequest(files.root, chosen, span, kp["format"], sources)
    source = choose_keypoint_source(kp, request)
    return _self_calibrate(source, files, chosen, sources, rig, calibrated, kp, cal, frames,
                           length, rate, fit_settings, unit, None)
