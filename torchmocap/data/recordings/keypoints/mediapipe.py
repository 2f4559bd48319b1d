"""2D keypoints computed from the recording's own frames (``data.keypoints.source=mediapipe``).

MediaPipe Pose (:class:`~torchmocap.detectors.MediaPipePoseDetector`, format ``mediapipe_33``)
runs on every loaded frame of every camera — videos or image folders — so a calibrated set of
videos is all a recording needs. The landmarker follows **one person per image** and knows
nothing of the other views, so what it returns is checked across the views before the loader
sees it:

1. **Whole image.** Every frame of every view is searched whole
   (:func:`~torchmocap.detectors.cached_detections`; cached, a progress bar per view).
2. **Cross-view check** (:func:`frame_consensus`, per frame). Every pair of views proposes a 3D
   body (confidence-weighted DLT, :func:`~torchmocap.cameras.triangulate_dlt`), the second view
   also with its arms and/or legs relabelled left/right; a view *agrees* with a proposal when
   the median distance of its body keypoints (shoulders to feet) from the proposal's projection
   is under ``max_disagreement`` times the subject's size in that view (the longer side of the
   projected body's box). The proposal most views agree with wins (ties: the smaller errors,
   then the nearer to the previous frame's body). Each view is then measured against the
   triangulation of the *other* agreeing views (leave-one-out): its **agreement** in pixels.
3. **Left/right swaps.** For each view and each group of keypoints — arms (shoulders to
   fingers), legs (hips to feet), face — the mirrored assignment (every left keypoint taken as
   the right one and vice versa) is tested against the others' triangulation; it replaces the
   detector's labels when it at least halves that group's error (:data:`RELABEL_GAIN`). Which
   labelling is "as detected" is decided by the majority of the agreeing views.
4. **The subject's region.** A view that does not agree (the landmarker followed a bystander,
   or found nobody) is searched again inside the subject's box: the projection of the agreeing
   views' triangulation of that frame (``triangulation``), or, when the frame has no agreeing
   views, of the nearest earlier (``previous``) or later (``next``) frame that has. Its new
   detection is checked again; a view that still disagrees is **dropped for that frame** (no
   keypoints, no mask) — never kept silently.

What was chosen is reported per frame and camera in ``meta.keypoint_report``
(:meth:`MediaPipeKeypoints.read`): where the kept detection was searched (``box``), its
agreement (px of the full-size images), the groups relabelled (``relabelled``) and why a view
was dropped. A frame where fewer than two views found anybody cannot be checked: its one
detection is kept, reported ``unchecked``.

**Cache.** The detector's output (keypoints as OpenPose JSON and the person masks as PNGs) is
stored in ``cache`` (default ``outputs/keypoint_cache`` under the working directory; never the
recording's folder unless named): ``<cache>/image/`` holds the whole-image searches,
``<cache>/box/`` the searches inside the subject's box, each in entries keyed by the frames'
content and the detector's settings (:func:`~torchmocap.detectors.cached_detections`). A
second load reads them and does not run the detector.

**Masks.** ``data.masks=detector`` takes the person masks of the same run: the kept
detection's segmentation, inside its region (:meth:`MediaPipeKeypoints.person_masks`).

Settings (``data.keypoints.<name>``, defaults in ``conf/keypoint_source/mediapipe.yaml``):
``cache``, ``min_detection_confidence``, ``margin`` (the detector's), ``max_disagreement``,
``min_visibility`` (keypoints the cross-view check compares), ``relabel`` (test left/right
swaps), ``progress``.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmocap.data.recordings.keypoints import (
    KeypointDetections,
    KeypointRequest,
    KeypointSource,
)

__all__ = ["BODY", "FORMAT", "GROUPS", "RELABEL_GAIN", "FrameConsensus", "MediaPipeKeypoints",
           "frame_consensus", "mirror_permutations"]

#: the detections' keypoint format
FORMAT = "mediapipe_33"
#: keypoints whose agreement across views decides (shoulders to feet)
BODY = ("LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LHip", "RHip",
        "LKnee", "RKnee", "LAnkle", "RAnkle", "LHeel", "RHeel", "LFootIndex", "RFootIndex")
#: the keypoint groups whose left/right labels are tested on their own (base names: ``L`` +
#: name and ``R`` + name)
GROUPS = {
    "arms": ("Shoulder", "Elbow", "Wrist", "Pinky", "Index", "Thumb"),
    "legs": ("Hip", "Knee", "Ankle", "Heel", "FootIndex"),
    "face": ("EyeInner", "Eye", "EyeOuter", "Ear", "Mouth"),
}
#: a group's mirrored labels replace the detector's when its error is at most this fraction
#: of the as-detected error
RELABEL_GAIN = 0.5
#: keypoints a view needs (compared, in the body) to be checked
MIN_KEYPOINTS = 4
#: the left/right labels of at most this many agreeing views are decided together (every
#: assignment is tried); with more, the detector's labels are kept
MAX_LABELLED = 8
#: boxes searched again are rounded outwards to this many pixels (a slightly different
#: triangulation then finds the same cached crop)
BOX_GRID = 16


def mirror_permutations(names: Sequence[str], groups: Mapping[str, Sequence[str]] = GROUPS
                        ) -> dict[str, Tensor]:
    """Per group, the permutation ``(K,)`` that swaps its left and right keypoints (others
    fixed): ``detections[..., perm, :]`` are the detections with that group relabelled.

    Raises:
        ValueError: a group with no left/right pair among ``names``.
    """
    out = {}
    for g, bases in groups.items():
        perm = list(range(len(names)))
        pairs = 0
        for b in bases:
            if f"L{b}" in names and f"R{b}" in names:
                i, j = names.index(f"L{b}"), names.index(f"R{b}")
                perm[i], perm[j] = j, i
                pairs += 1
        if not pairs:
            raise ValueError(f"groups[{g!r}]: none of {list(bases)} has an L/R pair in the "
                             f"keypoints {list(names)[:6]}...")
        out[g] = torch.tensor(perm, dtype=torch.long)
    return out


def _group_members(names: Sequence[str], groups: Mapping[str, Sequence[str]]
                   ) -> dict[str, Tensor]:
    return {g: torch.tensor([i for i, n in enumerate(names) if n[:1] in "LR" and n[1:] in b],
                            dtype=torch.long) for g, b in groups.items()}


@dataclass
class FrameConsensus:
    """The cross-view check of one frame (:func:`frame_consensus`).

    Attributes:
        points: ``(K, 3)`` float64 the agreeing views' triangulation (NaN: no agreement, or a
            keypoint fewer than two of them saw), in the agreed labelling.
        agrees: ``(C,)`` bool, the views that agree.
        agreement_px: ``(C,)`` float64 each view's median distance (px) from the
            triangulation of the other agreeing views (all of them when it is one of only two);
            NaN where not measurable.
        limit_px: ``(C,)`` float64 the disagreement limit in each view (px; NaN: no body).
        relabelled: per view, the groups whose left/right labels were swapped (in
            :data:`GROUPS` order).
        permutation: ``(C, K)`` long, per view the keypoint order of its relabelled
            detections (``detections[c, permutation[c]]``).
    """

    points: Tensor
    agrees: Tensor
    agreement_px: Tensor
    limit_px: Tensor
    relabelled: list[tuple[str, ...]]
    permutation: Tensor

    @property
    def num_agreeing(self) -> int:
        return int(self.agrees.sum())


def _median(d: Tensor, valid: Tensor, min_count: int) -> Tensor:
    """Median over the last dim of ``d`` where ``valid`` (inf with fewer than ``min_count``)."""
    x = torch.where(valid, d, torch.full_like(d, math.nan)).nanmedian(dim=-1).values
    return torch.where(valid.sum(-1) >= min_count, x, torch.full_like(x, math.inf))


def _size(pix: Tensor, body: Tensor) -> Tensor:
    """``(*)`` the longer side of the box of the finite body points ``pix (*, K, 2)``."""
    p = pix[..., body, :]
    ok = torch.isfinite(p).all(-1, keepdim=True)
    hi = torch.where(ok, p, torch.full_like(p, -math.inf)).amax(-2)
    lo = torch.where(ok, p, torch.full_like(p, math.inf)).amin(-2)
    s = (hi - lo).amax(-1)
    return torch.where(torch.isfinite(s), s, torch.full_like(s, math.nan))


class _Views:
    """One frame's detections and what a check needs (shared by the steps)."""

    def __init__(self, det: Tensor, names: Sequence[str], min_visibility: float,
                 relabel: bool) -> None:
        self.det = det.double()
        self.K = det.shape[1]
        self.seen = self.det[..., 2] > min_visibility  # (C, K)
        self.body = torch.tensor([names.index(n) for n in BODY], dtype=torch.long)
        self.perms = mirror_permutations(names) if relabel else {}
        self.members = _group_members(names, GROUPS) if relabel else {}
        self.present = self.seen[:, self.body].sum(-1) >= MIN_KEYPOINTS  # (C,)

    def order(self, bits: Tensor) -> Tensor:
        """``(*, K)`` keypoint order of the detections with the groups of ``bits (*, G)``
        relabelled."""
        idx = torch.arange(self.K).expand(*bits.shape[:-1], self.K).clone()
        for g, (name, perm) in enumerate(self.perms.items()):
            m = self.members[name]
            idx[..., m] = torch.where(bits[..., g:g + 1], perm[m], idx[..., m])
        return idx

    def errors(self, pix: Tensor, order: Tensor) -> tuple[Tensor, Tensor]:
        """Against projections ``pix (H, C, K, 2)`` with the keypoint orders ``order (H, C,
        K)``: the body's median error ``(H, C)`` and each group's ``(H, C, G)`` (inf: not
        comparable)."""
        H, C = pix.shape[:2]
        d = self.det.expand(H, C, self.K, 3).gather(2, order[..., None].expand(H, C, self.K, 3))
        ok = self.seen.expand(H, C, self.K).gather(2, order)
        dist = (pix - d[..., :2]).norm(dim=-1)
        b = self.body
        body = _median(dist[..., b], ok[..., b], MIN_KEYPOINTS)
        groups = [_median(dist[..., m], ok[..., m], 2) for m in self.members.values()]
        return body, (torch.stack(groups, -1) if groups else body[..., None])

    def fit(self, pix: Tensor) -> tuple[Tensor, Tensor]:
        """Each view's labels against projections ``pix (H, C, K, 2)``: per group the mirrored
        labels where they at most halve its error (:data:`RELABEL_GAIN`) — the keypoint order
        ``(H, C, K)`` — and the body's median error ``(H, C)``."""
        H, C = pix.shape[:2]
        bits = torch.zeros(H, C, len(self.perms), dtype=torch.bool)
        det, seen = self.det[None], self.seen[None]
        for g, (name, perm) in enumerate(self.perms.items()):
            m = self.members[name]
            e0 = _median((pix[:, :, m] - det[:, :, m, :2]).norm(dim=-1), seen[:, :, m], 2)
            e1 = _median((pix[:, :, m] - det[:, :, perm[m], :2]).norm(dim=-1),
                         seen[:, :, perm[m]], 2)
            bits[..., g] = torch.isfinite(e1) & (e1 < RELABEL_GAIN * e0)
        order = self.order(bits)
        return order, self.errors(pix, order)[0]

    def relabelled(self, order: Tensor) -> Tensor:
        """``(*, C, K, 3)`` the detections in the keypoint orders ``order (*, C, K)``."""
        return self.det.expand(*order.shape, 3).gather(
            -2, order[..., None].expand(*order.shape, 3))

    def label(self, agree: Tensor, rig) -> Tensor:
        """``(C, G)`` the groups to relabel in the agreeing views ``agree (C,)``: per group,
        every assignment of mirrored labels to them (up to :data:`MAX_LABELLED` views) is
        triangulated, and the one whose reprojection (mean over the views of their median
        error) is lowest wins; of two mirror-image assignments (the same errors), the one
        relabelling fewer views (a tie: the less confident ones); and it replaces the
        detector's labels only when the relabelled views' error at least halves
        (:data:`RELABEL_GAIN`) — the face's of a view whose arms and legs are relabelled only
        when it fits better."""
        C = agree.shape[0]
        bits = torch.zeros(C, len(self.perms), dtype=torch.bool)
        views = agree.nonzero().flatten().tolist()
        n = len(views)
        if n < 2 or n > MAX_LABELLED:
            return bits
        A = torch.tensor(list(itertools.product((False, True), repeat=n - 1)),
                         dtype=torch.bool).reshape(-1, n - 1)
        A = torch.cat([torch.zeros(A.shape[0], 1, dtype=torch.bool), A], 1)  # (N, n)
        conf = self.det[:, self.body, 2].sum(-1)
        use = agree.expand(A.shape[0], C)
        for g, (name, perm) in enumerate(self.perms.items()):
            m = self.members[name]
            order = torch.arange(self.K).expand(A.shape[0], C, self.K).clone()
            flip = torch.zeros(A.shape[0], C, dtype=torch.bool)
            flip[:, views] = A
            order[..., m] = torch.where(flip[..., None], perm[m], order[..., m])
            d = self.relabelled(order)[..., m, :]  # (N, C, |m|, 3)
            X = _triangulate(d, use, rig)  # (N, |m|, 3)
            pix = rig.project(X)[0]  # (N, C, |m|, 2)
            ok = self.seen.expand(A.shape[0], C, self.K).gather(2, order)[..., m]
            e = _median((pix - d[..., :2]).norm(dim=-1), ok, 2)[:, views]  # (N, n)
            e = torch.where(torch.isfinite(e), e, torch.full_like(e, math.nan))
            score = e.nanmean(-1)
            if not bool(torch.isfinite(score).any()):
                continue
            best = int(torch.argmin(score.nan_to_num(math.inf)))
            pick = A[best]
            on = int(pick.sum())
            if 2 * on > n or (2 * on == n and
                              float(conf[views][pick].sum()) >
                              float(conf[views][~pick].sum())):
                pick = ~pick  # its mirror image: the same errors
            # the relabelled views' own error must at least halve; the face of a body seen
            # mirrored (arms and legs relabelled) needs only to fit better
            limbs = [i for i, k in enumerate(self.perms) if k in ("arms", "legs")]
            mirrored = name == "face" and len(limbs) == 2 and \
                bool(bits[views][pick][:, limbs].all())
            gain = 1.0 if mirrored else RELABEL_GAIN
            if not bool(pick.any()) or not float(e[best][pick].nanmean()) < \
                    gain * float(e[0][pick].nanmean()):
                continue
            bits[views, g] = pick
        return bits


def _triangulate(det: Tensor, use: Tensor, rig) -> Tensor:
    """``(*, K, 3)`` from ``det (*, C, K, 3)`` of the views ``use (*, C)``."""
    from torchmocap.cameras import triangulate_dlt

    w = det[..., 2] * use[..., None].to(det.dtype)
    return triangulate_dlt(det[..., :2], w, rig)


def frame_consensus(detections: Tensor, rig, names: Sequence[str] = (),
                    max_disagreement: float = 0.1, min_visibility: float = 0.5,
                    relabel: bool = True, previous: Tensor | None = None,
                    iterations: int = 3) -> FrameConsensus:
    """Which views of one frame agree on one body, with left/right swaps undone (module
    docstring, steps 2 and 3).

    Args:
        detections: ``(C, K, 3)`` (u, v, confidence) per view in the rig's pixels (zeros: no
            detection).
        rig: the :class:`~torchmocap.cameras.CameraRig` of the ``C`` views.
        names: the ``K`` keypoint names (default: ``mediapipe_33``'s); they need the
            :data:`BODY` keypoints.
        max_disagreement: a view agrees when its median body error is under this fraction of
            the subject's size in it.
        min_visibility: keypoints of confidence above it are compared.
        relabel: test the mirrored labels of each :data:`GROUPS` group.
        previous: ``(K, 3)`` the previous frame's agreed points (ties between proposals go to
            the one nearer to it), or None.
        iterations: rounds of re-measuring the views against the agreeing ones' triangulation.

    Returns:
        :class:`FrameConsensus` (no view agrees when fewer than two views have enough body
        keypoints, or no two of them agree).

    Raises:
        ValueError: a shape that does not match the rig or the names.
    """
    from torchmocap.io.openpose import keypoint_format

    names = tuple(names) or keypoint_format(FORMAT)
    C = rig.num_cameras
    if detections.dim() != 3 or detections.shape != (C, len(names), 3):
        raise ValueError(f"detections: expected shape ({C}, {len(names)}, 3) (views, "
                         f"keypoints, u v confidence), got {tuple(detections.shape)}")
    missing = [n for n in BODY if n not in names]
    if missing:
        raise ValueError(f"names: the cross-view check needs the body keypoints {missing}")
    v = _Views(detections, names, min_visibility, relabel)
    K, G = v.K, len(v.perms)
    nan = torch.full((C,), math.nan, dtype=torch.float64)
    ident = torch.arange(K).expand(C, K).clone()
    none = FrameConsensus(torch.full((K, 3), math.nan, dtype=torch.float64),
                          torch.zeros(C, dtype=torch.bool), nan.clone(), nan.clone(),
                          [()] * C, ident)
    live = [c for c in range(C) if bool(v.present[c])]
    if len(live) < 2:
        return none
    # proposals: every pair of views, the second also with arms and/or legs relabelled
    variants = [torch.zeros(G, dtype=torch.bool)]
    if relabel:
        names_g = list(v.perms)
        for r in (("arms",), ("legs",), ("arms", "legs", "face")):
            variants.append(torch.tensor([n in r for n in names_g]))
    orders, uses = [], []
    for a, b in itertools.combinations(live, 2):
        for bits in variants:
            order = ident.clone()
            order[b] = v.order(bits[None])[0]
            orders.append(order)
            use = torch.zeros(C, dtype=torch.bool)
            use[[a, b]] = True
            uses.append(use)
    X = _triangulate(v.relabelled(torch.stack(orders)), torch.stack(uses), rig)  # (H, K, 3)
    pix = rig.project(X)[0]  # (H, C, K, 2)
    order_h, err = v.fit(pix)
    _, group_err = v.errors(pix, order_h)
    limit = max_disagreement * _size(pix, v.body)  # (H, C)
    inl = err < limit.nan_to_num(0.0)
    count = inl.sum(-1)
    # cost: every group's error counts (a proposal wrong in the arms alone still fits the
    # body's median)
    worst = group_err[..., :2].amax(-1) if G else err
    cost = (worst / limit).nan_to_num(1.0, posinf=1.0).clamp(max=1.0).sum(-1)
    if previous is not None and bool(torch.isfinite(previous[v.body]).all(-1).any()):
        # the nearer to the previous body (in units of the subject's size in each view)
        pp = rig.project(previous[None])[0][0]  # (C, K, 2)
        centre = (lambda p: p[..., v.body, :].nanmean(-2))
        shift = (centre(pix) - centre(pp)[None]).norm(dim=-1) / limit.nan_to_num(math.inf)
        cost = cost + max_disagreement * shift.nan_to_num(0.0).mean(-1)
    h = int(torch.argmin(torch.where(count == count.max(), cost,
                                     torch.full_like(cost, math.inf))))
    agree = inl[h]
    if int(agree.sum()) < 2:
        return none
    for _ in range(max(1, iterations)):
        order = v.order(v.label(agree, rig))
        # each view against the triangulation of the other agreeing views (of only two: both)
        use = agree.expand(C, C).clone()
        use.fill_diagonal_(False)
        use = torch.where((use.sum(-1) >= 2)[:, None], use, agree.expand(C, C))
        Xl = _triangulate(v.relabelled(order).expand(C, C, K, 3), use, rig)  # (C, K, 3)
        pl = rig.project(Xl)[0].diagonal(dim1=0, dim2=1).permute(2, 0, 1)  # (C, K, 2)
        e_kept, _ = v.errors(pl[None], order[None])
        o_fit, e_fit = v.fit(pl[None])  # a view outside: its best labels
        order = torch.where(agree[:, None], order, o_fit[0])
        err = torch.where(agree, e_kept[0], e_fit[0])
        limit = max_disagreement * _size(pl, v.body)
        new = err < limit.nan_to_num(0.0)
        if int(new.sum()) < 2:
            return none
        done = torch.equal(new, agree)
        agree = new
        if done:
            break
    points = _triangulate(v.relabelled(order), agree, rig)
    relabelled = [tuple(g for g, perm in v.perms.items()
                        if bool((order[c, v.members[g]] == perm[v.members[g]]).all()))
                  for c in range(C)]
    return FrameConsensus(points=points, agrees=agree,
                          agreement_px=torch.where(torch.isfinite(err), err, nan),
                          limit_px=limit, relabelled=relabelled, permutation=order)


def _rig_of(request: KeypointRequest):
    """The full-size float64 rig of the request's cameras, in their order (the recording's
    calibration, matched by camera number like the loader does)."""
    from torchmocap.cameras import CameraError, CameraRig, camera_key, read_calibration
    from torchmocap.data.recordings.files import discover_recording

    files = discover_recording(request.root)
    sizes = {c.name: tuple(int(x) for x in v.size) for c, v in zip(request.cameras,
                                                                     request.videos)}
    for c in files.cameras:  # a calibration without sizes asks for every camera it has
        if c.name not in sizes:
            from torchmocap.io.frames import open_frames

            sizes[c.name] = tuple(open_frames(c.frames).size)
    full = read_calibration(files.calibration, sizes)
    idx = []
    for cam in request.cameras:
        hits = [i for i, n in enumerate(full.names) if camera_key(n) == cam.key]
        if len(hits) != 1:
            raise CameraError(f"{files.calibration}: expected one calibration entry for camera "
                              f"{cam.name!r}, found {[full.names[i] for i in hits]}")
        idx.append(hits[0])
    rig = full.subset(idx).double()
    return CameraRig(rig.K, rig.R, rig.t, [sizes[c.name] for c in request.cameras], rig.dist,
                     [c.name for c in request.cameras])


def _grid_box(box, size: tuple[int, int]) -> tuple[float, float, float, float] | None:
    """``box`` rounded outwards to :data:`BOX_GRID` pixels (None: it misses the image)."""
    if box is None:
        return None
    g = BOX_GRID
    u0, v0 = math.floor(box[0] / g) * g, math.floor(box[1] / g) * g
    u1, v1 = math.ceil(box[2] / g) * g, math.ceil(box[3] / g) * g
    if u1 <= 0 or v1 <= 0 or u0 >= size[0] or v0 >= size[1]:
        return None
    return float(u0), float(v0), float(u1), float(v1)


def _projected_box(points: Tensor, rig, c: int):
    """The box of ``points (K, 3)``'s projection into view ``c`` (those in front of it)."""
    from torchmocap.detectors import keypoint_box

    ok = torch.isfinite(points).all(-1)
    if int(ok.sum()) < 2:
        return None
    pix, depth, _ = rig.subset([c]).project(points[ok])
    front = depth[0] > 0
    if int(front.sum()) < 2:
        return None
    kp = torch.cat([pix[0][front], torch.ones(int(front.sum()), 1, dtype=pix.dtype)], -1)
    return keypoint_box(kp)


def _setting_error(e: Exception) -> ValueError:
    return ValueError(f"data.keypoints.{e}")


class MediaPipeKeypoints(KeypointSource):
    """MediaPipe Pose on the recording's frames, checked across views (module docstring).

    Args:
        cache: folder of the detector's cached output (relative: to the working directory).
        min_detection_confidence: the person detector's threshold in ``[0, 1]``.
        margin: a searched box is widened by this fraction of its size on each side.
        max_disagreement: a view agrees with the others when its body keypoints' median
            distance from their triangulation is under this fraction of the subject's size in
            the view, in ``(0, 1]``.
        min_visibility: keypoints of confidence (MediaPipe's visibility) above this take part
            in the cross-view check, in ``[0, 1)``.
        relabel: test and undo left/right swaps.
        progress: progress bars while detecting.

    Raises:
        ValueError: a bad setting (named ``data.keypoints.<name>``).
    """

    views_interact = True  # the cross-view check reads every loaded view together

    def __init__(self, cache: str | Path = "outputs/keypoint_cache",
                 min_detection_confidence: float = 0.5, margin: float = 0.25,
                 max_disagreement: float = 0.1, min_visibility: float = 0.5,
                 relabel: bool = True, progress: bool = True) -> None:
        from torchmocap.detectors import DetectorSettingsError, MediaPipePoseSettings

        if not isinstance(cache, (str, Path)) or not str(cache).strip():
            raise ValueError(f"data.keypoints.cache: expected the folder of the detector's "
                             f"cached output (e.g. outputs/keypoint_cache), got {cache!r}")
        try:
            self.detector = MediaPipePoseSettings(
                min_detection_confidence=min_detection_confidence, margin=margin,
                segmentation=True)
        except DetectorSettingsError as e:
            raise _setting_error(e) from None
        for key, value, lo, hi, closed in (("max_disagreement", max_disagreement, 0.0, 1.0,
                                            "(0, 1]"),
                                           ("min_visibility", min_visibility, 0.0, 1.0,
                                            "[0, 1)")):
            ok = not isinstance(value, bool) and isinstance(value, (int, float)) and \
                math.isfinite(value)
            if ok:
                ok = (lo < value <= hi) if closed == "(0, 1]" else (lo <= value < hi)
            if not ok:
                raise ValueError(f"data.keypoints.{key}: expected a number in {closed}, got "
                                 f"{value!r}")
        for key, value in (("relabel", relabel), ("progress", progress)):
            if not isinstance(value, bool):
                raise ValueError(f"data.keypoints.{key}: expected true or false, got "
                                 f"{value!r}")
        self.cache = Path(str(cache)).expanduser()
        self.max_disagreement = float(max_disagreement)
        self.min_visibility = float(min_visibility)
        self.relabel = relabel
        self.progress = progress

    # ------------------------------------------------------------------------------ reading
    def _detect(self, cam, folder: str, frames, boxes=None):
        from torchmocap.detectors import cached_detections

        t0 = time.perf_counter()
        out = cached_detections(cam.frames, self.detector, self.cache / folder, frames=frames,
                                boxes=boxes, progress=self.progress)
        return out, time.perf_counter() - t0

    def read(self, request: KeypointRequest) -> KeypointDetections:
        """Detect, check across views, search again in the subject's box, drop what still
        disagrees (module docstring).

        Returns:
            :class:`~torchmocap.data.recordings.keypoints.KeypointDetections` of format
            ``mediapipe_33``, ``associated`` (one person or none per view and frame), and the
            report: ``detector`` (settings), ``cache`` (the folder), ``entries`` (per camera
            the cache entries of the ``image`` and ``box`` searches), ``seconds`` and
            ``computed`` (per camera: wall time of the detection calls, frames the detector
            ran on — 0 when everything was cached), ``max_disagreement``, and per camera
            ``views[cam]``: per frame ``box`` (``image``, ``triangulation``, ``previous``,
            ``next``: where the kept detection was searched), ``agreement_px`` (None: not
            measurable), ``relabelled`` (groups whose left/right labels were swapped, or
            None), ``dropped`` (why the view has no detection in that frame, or None), and
            the counts ``frames_dropped``, ``frames_relabelled``, ``frames_searched_in_box``,
            ``frames_unchecked``, ``median_agreement_px``.

        Raises:
            DetectorUnavailableError: mediapipe or its models are missing.
            KeypointFormatError: ``data.keypoints.format`` other than ``auto`` or
                ``mediapipe_33``.
        """
        from torchmocap.io.openpose import KeypointFormatError, keypoint_format

        if request.format not in ("auto", FORMAT):
            raise KeypointFormatError(f"data.keypoints.format: the mediapipe source detects "
                                      f"{FORMAT!r} keypoints, got {request.format!r} (set "
                                      "auto)")
        names = keypoint_format(FORMAT)
        K = len(names)
        cams = list(request.cameras)
        C, frames = len(cams), list(request.frames)
        T = len(frames)
        rig = _rig_of(request) if C >= 2 else None
        seconds = {c.name: 0.0 for c in cams}
        computed = {c.name: 0 for c in cams}
        entries: dict[str, dict[str, str | None]] = {c.name: {"image": None, "box": None}
                                                     for c in cams}
        det = torch.zeros(T, C, K, 3, dtype=torch.float64)
        for c, cam in enumerate(cams):
            out, dt = self._detect(cam, "image", request.frames)
            seconds[cam.name] += dt
            computed[cam.name] += len(out.computed)
            entries[cam.name]["image"] = str(out.path)
            for i, t in enumerate(frames):
                x = out.keypoints(t)
                if x.shape[0]:
                    det[i, c] = x[0]
        where = [["image"] * C for _ in range(T)]
        cons = self._check_all(det, rig, names)
        # views that do not agree: search again inside the subject's box
        if rig is not None:
            redo: dict[int, dict[int, tuple]] = {c: {} for c in range(C)}
            for i in range(T):
                if cons[i] is None or cons[i].num_agreeing == C:
                    continue
                src, ref = self._box_source(cons, i)
                if ref is None:
                    continue
                for c in range(C):
                    if bool(cons[i].agrees[c]):
                        continue
                    box = _grid_box(_projected_box(ref.points, rig, c),
                                    tuple(int(x) for x in rig.image_size[c].tolist()))
                    if box is not None:
                        redo[c][frames[i]] = (box, src)
            changed = set()
            for c, cam in enumerate(cams):
                if not redo[c]:
                    continue
                boxes = {t: b for t, (b, _) in redo[c].items()}
                out, dt = self._detect(cam, "box", sorted(boxes), boxes)
                seconds[cam.name] += dt
                computed[cam.name] += len(out.computed)
                entries[cam.name]["box"] = str(out.path)
                index = {t: i for i, t in enumerate(frames)}
                for t, (_, src) in redo[c].items():
                    i = index[t]
                    x = out.keypoints(t)
                    det[i, c] = x[0] if x.shape[0] else 0.0
                    where[i][c] = src
                    changed.add(i)
            for i in sorted(changed):
                prev = next((cons[j].points for j in range(i - 1, -1, -1)
                             if cons[j] is not None and cons[j].num_agreeing), None)
                cons[i] = frame_consensus(det[i], rig, names, self.max_disagreement,
                                          self.min_visibility, self.relabel, prev)
        people, views = self._choose(det, cons, where, cams, frames, names)
        report = {
            "detector": {"name": "mediapipe_pose", **self.detector.to_dict()},
            "cache": str(self.cache), "entries": entries,
            "seconds": {k: round(v, 3) for k, v in seconds.items()}, "computed": computed,
            "max_disagreement": self.max_disagreement, "min_visibility": self.min_visibility,
            "relabel": self.relabel, "views": views,
        }
        return KeypointDetections(people, FORMAT, associated=True, report=report)

    def _check_all(self, det: Tensor, rig, names) -> list[FrameConsensus | None]:
        """The cross-view check of every frame (None: one camera, nothing to check)."""
        if rig is None:
            return [None] * det.shape[0]
        out: list[FrameConsensus | None] = []
        prev = None
        for i in range(det.shape[0]):
            r = frame_consensus(det[i], rig, names, self.max_disagreement,
                                self.min_visibility, self.relabel, prev)
            out.append(r)
            if r.num_agreeing:
                prev = r.points
        return out

    @staticmethod
    def _box_source(cons: list[FrameConsensus | None], i: int
                    ) -> tuple[str, FrameConsensus | None]:
        """Where frame ``i``'s subject box comes from: its own agreeing views, else the nearest
        earlier, else the nearest later frame with agreeing views."""
        if cons[i].num_agreeing:
            return "triangulation", cons[i]
        for j in range(i - 1, -1, -1):
            if cons[j] is not None and cons[j].num_agreeing:
                return "previous", cons[j]
        for j in range(i + 1, len(cons)):
            if cons[j] is not None and cons[j].num_agreeing:
                return "next", cons[j]
        return "", None

    def _choose(self, det: Tensor, cons, where, cams, frames, names
                ) -> tuple[list[list[Tensor]], dict[str, Any]]:
        """The kept detection of every frame and view, and the per-view report."""
        T, C, K = det.shape[:3]
        empty = torch.zeros(0, K, 3, dtype=torch.float64)
        people: list[list[Tensor]] = [[] for _ in range(T)]
        rows = {c.name: {"box": [], "agreement_px": [], "relabelled": [], "dropped": [],
                         "unchecked": []} for c in cams}
        present = (det[..., 2] > 0).any(-1)  # (T, C): anybody found
        for i in range(T):
            r = cons[i]
            checkable = r is not None and int(present[i].sum()) >= 2
            for c, cam in enumerate(cams):
                row = rows[cam.name]
                kept, why, px, swapped = None, None, math.nan, None
                unchecked = False
                if not bool(present[i, c]):
                    why = "nobody found"
                elif not checkable:  # one view found somebody: nothing to check it against
                    kept, unchecked = det[i, c], True
                elif bool(r.agrees[c]):
                    kept = det[i, c][r.permutation[c]]
                    px = float(r.agreement_px[c])
                    swapped = list(r.relabelled[c]) or None
                elif not r.num_agreeing:
                    why = "no two views agree in this frame"
                else:
                    e = float(r.agreement_px[c])
                    why = ("disagrees with the other views" + (
                        f" ({e:.0f} px, limit {float(r.limit_px[c]):.0f} px)"
                        if math.isfinite(e) else " (too few body keypoints seen)"))
                if why and where[i][c] != "image":
                    why += f"; searched again in the subject's box ({where[i][c]})"
                people[i].append(empty if kept is None else kept[None].clone())
                row["box"].append(where[i][c])
                row["agreement_px"].append(round(px, 2) if math.isfinite(px) else None)
                row["relabelled"].append(swapped)
                row["dropped"].append(why)
                row["unchecked"].append(unchecked)
        views = {}
        for cam in cams:
            row = rows[cam.name]
            ag = [a for a in row["agreement_px"] if a is not None]
            views[cam.name] = {
                "frames": list(frames), "box": row["box"], "agreement_px": row["agreement_px"],
                "relabelled": row["relabelled"], "dropped": row["dropped"],
                "frames_dropped": [t for t, d in zip(frames, row["dropped"]) if d],
                "frames_relabelled": [t for t, s in zip(frames, row["relabelled"]) if s],
                "frames_searched_in_box": [t for t, b in zip(frames, row["box"])
                                           if b != "image"],
                "frames_unchecked": [t for t, u in zip(frames, row.pop("unchecked")) if u],
                "median_agreement_px": round(float(np.median(ag)), 2) if ag else None,
            }
        return people, views

    # ------------------------------------------------------------------------------- masks
    def person_masks(self, request: KeypointRequest, report: Mapping[str, Any], scale: float
                     ) -> list[Tensor]:
        """The person masks of the kept detections (``data.masks=detector``).

        Per camera ``(T, h, w)`` bool at the working ``scale`` (:func:`~torchmocap.io.frames
        .scaled_size` of the camera's frames): the segmentation of the search that gave the
        kept detection (the cached mask PNG, probability resampled like the frames, above 0.5),
        inside the detection's region (its keypoints' box widened by ``margin``); empty
        where the view was dropped or nobody was found.

        Args:
            request: the request :meth:`read` answered.
            report: its report (``KeypointDetections.report``).
            scale: image scale in (0, 1].

        Raises:
            ValueError: a report of other cameras or frames than the request's.
        """
        from PIL import Image

        from torchmocap.detectors import box_to_region, keypoint_box
        from torchmocap.io.frames import resize_image, scaled_size
        from torchmocap.io.openpose import read_openpose_json

        out = []
        frames = list(request.frames)
        for cam, video in zip(request.cameras, request.videos):
            view = report.get("views", {}).get(cam.name)
            if view is None or view.get("frames") != frames:
                raise ValueError(f"report: no detections of camera {cam.name!r} for frames "
                                 f"{frames[0]}..{frames[-1]} (the report of another request)")
            size = tuple(int(x) for x in video.size)
            w, h = scaled_size(size, scale)
            masks = torch.zeros(len(frames), h, w, dtype=torch.bool)
            for i, t in enumerate(frames):
                if view["dropped"][i]:
                    continue
                entry = report["entries"][cam.name]["image" if view["box"][i] == "image"
                                                    else "box"]
                base = Path(entry)
                kp = read_openpose_json(base / "keypoints" / f"{t:06d}.json", 33)
                if not kp.shape[0]:
                    continue
                region = box_to_region(keypoint_box(kp[0], 0.0) or (0, 0, 1, 1), size,
                                       self.detector.margin)
                with Image.open(base / "masks" / f"{t:06d}.png") as im:
                    grey = np.array(im.convert("L"))
                if region is not None:
                    x0, y0, x1, y1 = region
                    keep = np.zeros_like(grey)
                    keep[y0:y1, x0:x1] = grey[y0:y1, x0:x1]
                    grey = keep
                small = np.asarray(resize_image(Image.fromarray(grey), scale))
                masks[i] = torch.from_numpy(small > 127)
            out.append(masks)
        return out
