"""Choosing the subject among several detected people, per frame and view, across views and time.

A 2D detector reports everyone it sees: the subject, but also a bystander in some views. The
subject is the person whose detections agree across views (one 3D body explains them) and
whose detections move continuously in time.

Per frame, :func:`select_person` forms one 3D hypothesis from every pair of people in two
views (confidence-weighted DLT, :func:`~torchmocap.cameras.triangulate_dlt`), projects it into
every view and scores each view's people by

* ``agreement``: the median pixel distance between the person's keypoints and the
  hypothesis' projection, and
* ``continuity``: the median pixel distance to the person chosen in that view in the previous
  frame (0 in the first frame, or when the view had no choice),

each capped at ``max_error`` pixels. A hypothesis' score is the mean over views of its best
person's ``agreement + continuity``; the best hypothesis wins, and each view takes its best
person for it — provided that person's agreement is under ``max_error`` (else the view has no
detection in that frame: a view that sees only a bystander is not given the bystander). A
detector sometimes splits one body into two "people" (upper and lower body): other people of
the view that agree with the hypothesis fill in the keypoints the chosen one lacks (each within
``max_error`` of the projection). With
several people consistent in every view, the first frame's best agreement chooses and later
frames follow that person.

:func:`person_agreement` is the reported measure: each view's median reprojection error (px)
of the chosen detections' triangulation from all views.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from torchmocap.cameras import triangulate_dlt

__all__ = ["person_agreement", "select_person"]


def _median_distance(a: Tensor, b: Tensor, valid: Tensor, min_keypoints: int) -> Tensor:
    """Median over ``K`` of ``|a - b|`` where ``valid``; inf with fewer than ``min_keypoints``.

    ``a, b (*, K, 2)``, ``valid (*, K)`` -> ``(*)``."""
    d = (a - b).norm(dim=-1)
    d = torch.where(valid, d, torch.full_like(d, float("nan")))
    med = d.nanmedian(dim=-1).values
    return torch.where(valid.sum(-1) >= min_keypoints, med, torch.full_like(med, math.inf))


def person_agreement(joints: Tensor, rig, min_keypoints: int = 4) -> Tensor:
    """Each view's median reprojection error (px) of the detections' triangulation.

    Args:
        joints: ``(T, C, K, 3)`` detections (u, v, confidence; confidence 0 = none) in the
            rig's pixels.
        rig: the :class:`~torchmocap.cameras.CameraRig` of the ``C`` views.
        min_keypoints: views with fewer triangulated keypoints detected get NaN.

    Returns:
        ``(T, C)`` float64 errors in pixels (NaN where not measurable).
    """
    j = joints.double()
    X = triangulate_dlt(j[..., :2], j[..., 2], rig)  # (T, K, 3), float64 like the pixels
    pix = rig.project(X)[0]  # (T, C, K, 2)
    valid = (j[..., 2] > 0) & torch.isfinite(pix).all(-1)
    err = _median_distance(pix, j[..., :2], valid, min_keypoints)
    return torch.where(torch.isinf(err), torch.full_like(err, float("nan")), err)


def _hypotheses(people: Sequence[Tensor], rig) -> Tensor:
    """3D hypotheses ``(H, K, 3)`` from every pair of people in two views (H may be 0)."""
    C = len(people)
    K = next(x.shape[1] for x in people if x.shape[0] > 0)
    pix, w = [], []
    for a in range(C):
        for b in range(a + 1, C):
            for i in range(people[a].shape[0]):
                for k in range(people[b].shape[0]):
                    p = torch.zeros(C, K, 2, dtype=torch.float64)
                    c = torch.zeros(C, K, dtype=torch.float64)
                    p[a], c[a] = people[a][i, :, :2], people[a][i, :, 2]
                    p[b], c[b] = people[b][k, :, :2], people[b][k, :, 2]
                    pix.append(p)
                    w.append(c)
    if not pix:
        return torch.zeros(0, K, 3, dtype=torch.float64)
    return triangulate_dlt(torch.stack(pix), torch.stack(w), rig)


def select_person(people: Sequence[Sequence[Tensor]], rig, min_confidence: float = 0.0,
                  max_error: float | None = None, min_keypoints: int = 4
                  ) -> tuple[Tensor, dict]:
    """The subject's detections among several people (see the module docstring).

    Args:
        people: per frame, per view, ``(P, K, 3)`` detections (u, v, confidence) in the rig's
            pixels (``P`` may differ per frame and view, and be 0).
        rig: :class:`~torchmocap.cameras.CameraRig` of the ``C`` views.
        min_confidence: keypoints below it are treated as missed (confidence and position 0).
        max_error: the cap and consistency threshold (px); default 3 % of the largest image
            diagonal (66 px on 1088x1920 images).
        min_keypoints: keypoints two detections must share to be compared.

    Returns:
        ``joints (T, C, K, 3)`` float64 (zeros where a view has no chosen person) and a report:
        ``max_error_px``, and per view ``people`` (count per frame), ``chosen`` (index of the
        chosen person per frame, -1 none), ``frames_with_several_people``, ``rejected_frames``
        (frames where the view had people but none agreed), ``merged`` (``[frame, person]``
        pairs whose keypoints completed the chosen person's), ``agreement_px`` (per frame,
        None where not measurable, :func:`person_agreement`).

    Raises:
        ValueError: ``people`` not ``T`` lists of ``C`` tensors of one ``K``.
    """
    C = rig.num_cameras
    if max_error is None:
        max_error = 0.03 * float(rig.image_size.double().norm(dim=-1).max())
    shapes = {x.shape[1:] for frame in people for x in frame if x.shape[0] > 0}
    if any(len(frame) != C for frame in people) or len(shapes) > 1 or \
            any(s[-1] != 3 for s in shapes):
        raise ValueError(f"people: expected per frame {C} tensors (P, K, 3) of one K, got "
                         f"{[len(f) for f in people][:5]}... views and shapes {sorted(shapes)}")
    K = next(iter(shapes))[0] if shapes else 0
    T = len(people)
    out = torch.zeros(T, C, K, 3, dtype=torch.float64)
    chosen = [[-1] * T for _ in range(C)]
    rejected: list[list[int]] = [[] for _ in range(C)]
    merged: list[list[list[int]]] = [[] for _ in range(C)]
    prev: list[Tensor | None] = [None] * C
    for t, frame in enumerate(people):
        views = [_clean(x.double(), min_confidence, K) for x in frame]
        pick, parts = _select_frame(views, rig, prev, max_error, min_keypoints)
        for c, k in enumerate(pick):
            if k >= 0:
                out[t, c] = views[c][k]
                for k2 in parts[c]:
                    fill = (out[t, c, :, 2] == 0) & (views[c][k2, :, 2] > 0)
                    out[t, c][fill] = views[c][k2][fill]
                    merged[c].append([t, k2])
                chosen[c][t] = k
                prev[c] = out[t, c].clone()
            elif views[c].shape[0] > 0:
                rejected[c].append(t)
    agree = person_agreement(out, rig, min_keypoints) if K else torch.full((T, C), math.nan)
    names = rig.names
    report = {"max_error_px": max_error, "views": {}}
    for c in range(C):
        counts = [int(frame[c].shape[0]) for frame in people]
        report["views"][names[c]] = {
            "people": counts,
            "frames_with_several_people": [t for t, n in enumerate(counts) if n > 1],
            "chosen": chosen[c],
            "rejected_frames": rejected[c],
            "merged": merged[c],
            "agreement_px": [None if math.isnan(v) else round(v, 2) for v in
                             agree[:, c].tolist()],
        }
    return out, report


def _clean(x: Tensor, min_confidence: float, K: int) -> Tensor:
    if x.shape[0] == 0:
        return torch.zeros(0, K, 3, dtype=torch.float64)
    low = x[..., 2] < min_confidence
    return torch.where(low[..., None] | (x[..., 2:3] <= 0), torch.zeros_like(x), x)


def _select_frame(views: list[Tensor], rig, prev: list[Tensor | None], max_error: float,
                  min_keypoints: int) -> tuple[list[int], list[list[int]]]:
    """Index of the chosen person per view (-1 = none) in one frame, and per view the other
    people whose keypoints complete the chosen one's."""
    C = len(views)
    busy = [c for c in range(C) if views[c].shape[0] > 0]
    if not busy:
        return [-1] * C, [[] for _ in range(C)]
    cont = [_continuity(views[c], prev[c], max_error, min_keypoints) for c in range(C)]
    X = _hypotheses(views, rig) if len(busy) >= 2 else None
    if X is None or X.shape[0] == 0:
        # one view sees people: nothing to triangulate; follow the previous choice, else the
        # most confident person
        return [int(torch.argmin(cont[c] - 1e-9 * views[c][..., 2].sum(-1)))
                if views[c].shape[0] else -1 for c in range(C)], [[] for _ in range(C)]
    pix = rig.project(X)[0]  # (H, C, K, 2)
    H = X.shape[0]
    cost = torch.full((H, C), 2 * max_error, dtype=torch.float64)
    agree_hc: list[Tensor | None] = [None] * C
    for c in busy:
        det = views[c]  # (P, K, 3)
        valid = (det[None, :, :, 2] > 0) & torch.isfinite(pix[:, c, None]).all(-1)
        e = _median_distance(pix[:, c, None], det[None, :, :, :2], valid, min_keypoints)
        agree_hc[c] = e  # (H, P)
        total = e.clamp(max=max_error) + cont[c][None].clamp(max=max_error)
        cost[:, c] = total.min(-1).values
    h = int(torch.argmin(cost.mean(-1)))
    pick: list[int] = [-1] * C
    for c in busy:
        e = agree_hc[c][h]
        total = e.clamp(max=max_error) + cont[c].clamp(max=max_error)
        k = int(torch.argmin(total))
        if float(e[k]) < max_error:
            pick[c] = k
    return pick, _parts(views, rig, pick, max_error, min_keypoints)


def _parts(views: list[Tensor], rig, pick: list[int], max_error: float, min_keypoints: int
           ) -> list[list[int]]:
    """Per view, the other people whose keypoints complete the chosen one's: a detector may
    split one body into two "people" (upper and lower body). The chosen detections of all
    views are triangulated; another person of a view contributes when it agrees with that
    body (median under ``max_error``) and has keypoints the chosen one lacks, each within
    ``max_error`` of the body's projection."""
    C = len(views)
    parts: list[list[int]] = [[] for _ in range(C)]
    if sum(k >= 0 for k in pick) < 2 or all(v.shape[0] < 2 for v in views):
        return parts
    K = views[pick.index(next(k for k in pick if k >= 0))].shape[1]
    det = torch.stack([views[c][k] if k >= 0 else torch.zeros(K, 3, dtype=torch.float64)
                       for c, k in enumerate(pick)])
    pix = rig.project(triangulate_dlt(det[..., :2], det[..., 2], rig))[0]  # (C, K, 2)
    for c, k in enumerate(pick):
        if k < 0:
            continue
        for k2 in range(views[c].shape[0]):
            other = views[c][k2]
            ok = (other[:, 2] > 0) & torch.isfinite(pix[c]).all(-1)
            if k2 == k or float(_median_distance(pix[c], other[:, :2], ok, min_keypoints)) \
                    >= max_error:
                continue
            d = (other[:, :2] - pix[c]).norm(dim=-1)
            if bool((ok & (views[c][k, :, 2] == 0) & (d < max_error)).any()):
                parts[c].append(k2)
    return parts


def _continuity(det: Tensor, prev: Tensor | None, max_error: float, min_keypoints: int
                ) -> Tensor:
    """``(P,)`` median pixel distance of each person to the previous choice (0 without one)."""
    if prev is None or det.shape[0] == 0:
        return torch.zeros(det.shape[0], dtype=torch.float64)
    valid = (det[..., 2] > 0) & (prev[None, :, 2] > 0)
    d = _median_distance(det[..., :2], prev[None, :, :2], valid, min_keypoints)
    return d.clamp(max=max_error)
