"""Fitting the capsule body to the subject's observed silhouettes at the start of a track.

The tracking model's capsule radii are anthropometric guesses; the observed person is thicker or
thinner (against the skinned CC0 mesh the default capsules overlap with IoU ≈ 0.77, so the
likelihood's optimum is not the true pose). :class:`SilhouetteBodyFit` adjusts the radius of
every capsule — one log-scale per body segment, left and right tied — so that the capsules at
the known first pose match the first frame's silhouettes: it maximises the soft
intersection-over-union of the differentiable capsule silhouettes
(:func:`~torchmocap.likelihoods.silhouette.soft_capsule_silhouettes`, every ``stride``-th pixel)
and the masks with Adam, within ``[min_scale, max_scale]`` of the initial radii. (The silhouette
*energy* is not used as the objective: its two normalised directions reward over-wide capsules —
at the true pose its optimum lowers the IoU from 0.78 to 0.70.) Bone lengths are the subject's
(fitted to the motion capture or scaled to the visual hull) and are not changed. The body is
updated in place, so every likelihood term that holds it sees the fitted radii.

With ``offsets`` (bone names) the same objective also moves those capsules off their bones (an
axis offset in the parent joint's frame, :class:`~torchmocap.body.CapsuleBody`
``axis_offsets``): a real head's centre lies several centimetres in front of the neck's axis
(the bundled mesh's head spans 17 cm in front of it and 5 cm behind), the chest and belly in
front of the spine; a capsule centred on the bone makes the silhouette term tilt the neck forward
to cover the face.

With ``hull_filter`` the fit sees only the foreground that all views agree on: the masks are
intersected with the reprojection of their own visual hull (carved from every valid view,
:func:`~torchmocap.cameras.visual_hull`, around the body at the pose). Clutter, reflections and
other false-positive blobs that one view sees and the others do not are removed before the fit;
corrupted masks otherwise pull the radii towards the corruptions (on the synthetic outdoor
scenario the filtered masks overlap the clean ones with IoU 0.52–0.84 per view instead of
0.41–0.67). What is consistent in 3D stays (a shadow on the floor), holes in one view carve the
hull and so are lost in every view; the reported ``iou_before``/``iou_after`` stay those with the
masks as given.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from torchmocap.cameras.hull import visual_hull
from torchmocap.likelihoods.silhouette import (
    check_fit_iou,
    prepare_silhouettes,
    render_capsule_silhouettes,
    silhouette_energy,
    silhouette_iou,
    soft_capsule_silhouettes,
)
from torchmocap.stateful import Stateful

__all__ = ["BodyFit", "SilhouetteBodyFit", "hull_filtered_masks"]



def hull_filtered_masks(rig, masks: torch.Tensor, valid: torch.Tensor | None, ends: torch.Tensor,
                        radii: torch.Tensor, margin: float, voxel: float, tolerance: int = 0,
                        reach: float | None = None) -> tuple[torch.Tensor, dict[str, Any]]:
    """The foreground all views agree on: ``masks (C, H, W)`` intersected with the
    reprojection of their visual hull (:func:`~torchmocap.cameras.visual_hull`), carved from
    every valid view with voxels of edge ``voxel`` in the box around the capsules ``ends
    (..., B, 2, 3)`` (radii ``(B,)``) padded by ``margin`` plus the largest radius (metres); and
    what was done (``applied``, ``views``, ``foreground_kept``).

    A voxel is kept when it lies in the masks of all valid views but ``tolerance``: with 0 a
    hole in one view carves the hull and is lost in every view; with 1 it stays one view's (a
    false-positive blob survives only where two other views see foreground too). With
    ``reach`` (metres) only voxels within that distance of a capsule's surface are kept: what
    is consistent in 3D but not near the body at the pose — a shadow on the floor, another
    person, a static object the masks hold — is removed too. With fewer than
    ``tolerance + 2`` valid views the masks are returned as given (``applied: False`` and the
    reason)."""
    if isinstance(tolerance, bool) or not isinstance(tolerance, int) or tolerance < 0:
        raise ValueError(f"tolerance: expected an int >= 0, got {tolerance!r}")
    if reach is not None and (isinstance(reach, bool) or not isinstance(reach, (int, float))
                              or not math.isfinite(reach) or reach <= 0):
        raise ValueError(f"reach: expected a finite number > 0 or None, got {reach!r}")
    C = masks.shape[0]
    ok = (torch.ones(C, dtype=torch.bool, device=masks.device) if valid is None
          else valid.to(masks.device).bool())
    n = int(ok.sum())
    if n < tolerance + 2:
        return masks, {"applied": False, "reason": f"{n} valid view(s); the hull needs "
                                                   f"{tolerance + 2}"}
    seg = ends.detach().reshape(-1, 2, 3).double().cpu()  # (B, 2, 3)
    r = radii.detach().reshape(-1).double().cpu()
    pts = seg.reshape(-1, 3)
    pad = margin + float(r.max())
    bounds = torch.stack([pts.min(0).values - pad, pts.max(0).values + pad], 1)
    fg = masks > 0
    hull = visual_hull(rig, fg, bounds, voxel, min_views=n - tolerance)
    info: dict[str, Any] = {"applied": True, "views": n, "tolerance": tolerance}
    if reach is not None:
        occ = hull.occupancy
        idx = occ.nonzero()
        c = hull.centers().double().cpu()  # (M, 3), the order of idx
        near = torch.zeros(c.shape[0], dtype=torch.bool)
        a, ab = seg[:, 0], seg[:, 1] - seg[:, 0]  # (B, 3)
        den = (ab * ab).sum(-1).clamp_min(1e-12)
        for s in range(0, c.shape[0], 1 << 15):
            p = c[s:s + (1 << 15), None, :]  # (m, 1, 3)
            t = (((p - a) * ab).sum(-1) / den).clamp(0, 1)  # (m, B)
            d = (p - (a + t[..., None] * ab)).norm(dim=-1) - r  # distance to each surface
            near[s:s + p.shape[0]] = (d <= reach).any(-1)
        keep = torch.zeros_like(occ)
        keep[tuple(idx[near.to(idx.device)].T)] = True
        info["voxels_off_the_body"] = round(1.0 - float(near.float().mean()) if len(near)
                                            else 0.0, 4)
        hull = type(hull)(keep, hull.origin, hull.voxel_size)
        info["reach"] = float(reach)
    out = fg & hull.silhouettes(rig).to(fg.device)
    info["foreground_kept"] = round(float(out[ok].sum()) / max(float(fg[ok].sum()), 1.0), 4)
    return out.to(masks.dtype), info


def _segment(name: str) -> str:
    for side in ("l_", "r_"):
        if name.startswith(side):
            return name[len(side):]
    return name


class BodyFit(nn.Module, Stateful):
    """A fit of the tracker's body to the first frame once its pose is known (the tracker's
    ``body_fit``): it changes the runtime body in place, so every term holding the body sees the
    fit, and saves that body in the tracker's checkpoints (:class:`~torchmocap.stateful.Stateful`).

    Subclasses implement ``forward(theta (D,), frame) -> info`` (a JSON-ready report).
    :meth:`start` is what the tracker runs: the fit and, when the tracker refines the first frame
    (``refine_first_frame``), ``refit_passes`` coarse-to-fine passes — the first frame's pose is
    refined again with the fitted body (the proposal's spread scaled by ``refit_scale``; the new
    pose is kept when its energy is lower) and the body refitted at it. The pose found with the
    initial (anthropometric) radii is biased by them, and the radii fitted at a biased pose are
    too; each pass reduces both.

    Args:
        body: the runtime :class:`~torchmocap.body.CapsuleBody` (changed in place).
        refit_passes: passes after the first fit (with a refining tracker; 0: none).
        refit_scale: factor on the proposal's spread of the refit passes (the pose is close).
    """

    #: the body's tensors the fit changes (saved in checkpoints)
    STATE = ("radii", "end_shrink", "axis_offsets")

    def __init__(self, body, refit_passes: int = 0, refit_scale: float = 0.25) -> None:
        super().__init__()
        if isinstance(refit_passes, bool) or not isinstance(refit_passes, int) \
                or refit_passes < 0:
            raise ValueError(f"refit_passes: expected an int >= 0, got {refit_passes!r}")
        if not (isinstance(refit_scale, (int, float)) and not isinstance(refit_scale, bool)
                and 0 < refit_scale <= 1):
            raise ValueError(f"refit_scale: expected a number in (0, 1], got {refit_scale!r}")
        self.body = body
        self.refit_passes, self.refit_scale = refit_passes, float(refit_scale)

    def checkpoint_state(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().clone() for k, v in self.body.state_dict().items()
                if k in self.STATE}

    def fitted_mesh(self) -> tuple[nn.Module, torch.Tensor] | None:
        """The fitted surface body for the outputs (``track.glb``): ``(body, phenotype)`` of a
        fit that has one (:class:`~torchmocap.filters.AnnyBodyFit`), else None (capsules
        only)."""
        return None

    def load_checkpoint_state(self, state: dict[str, torch.Tensor]) -> None:
        for k, v in state.items():
            getattr(self.body, k).copy_(v)

    def start(self, theta0: torch.Tensor, frame0, refine: Callable | None = None
              ) -> tuple[torch.Tensor, Any, dict, list[dict] | None]:
        """Fit the body at the first pose ``theta0 (D,)`` and run the refit passes.

        Args:
            refine: the tracker's refinement of the first frame, ``refine(theta (D,), scale) ->
                (estimate (D,), result, energies (2,))`` — the energies of ``theta`` and the
                estimate with the body as it is now; None: no refit passes.

        Returns:
            the first pose (refined when a pass lowered its energy), the inference result of the
            kept refinement (None: the caller's stands), the fit's report (with ``seconds``), and
            the passes' reports (None without passes).
        """
        t0 = time.perf_counter()
        info = self(theta0, frame0)
        info["seconds"] = time.perf_counter() - t0
        if refine is None or not self.refit_passes:
            return theta0, None, info, None
        kept, passes = None, []
        for _ in range(self.refit_passes):
            t0 = time.perf_counter()
            est, res, v = refine(theta0, self.refit_scale)
            better = bool(v[1] < v[0])
            if better:
                theta0, kept = est, res
            t1 = time.perf_counter()
            fit = self(theta0, frame0)
            fit["seconds"] = time.perf_counter() - t1
            passes.append({"energy_before": float(v[0]), "energy_after": float(v[1]),
                           "kept": better, "seconds": time.perf_counter() - t0,
                           "body_fit": fit})
        return theta0, kept, info, passes


class SilhouetteBodyFit(BodyFit):
    """Fit per-segment capsule radii to one frame's silhouettes at a known pose.

    Args:
        body: the runtime :class:`~torchmocap.body.CapsuleBody` (changed in place).
        rig: the cameras of the silhouettes.
        iterations: Adam steps.
        lr: step size (in log-radius).
        min_scale, max_scale: bounds of each radius relative to its value when the fit was
            built — over all calls: a second call (a refit pass) scales the radii the first
            left, within the same total range.
        symmetric: one scale for a left/right pair of segments.
        stride: pixel stride of the soft IoU.
        tau: softness (pixels) of the soft silhouettes (small: a wide sigmoid biases thin limbs
            towards thicker capsules).
        prior_weight: pull of every log-scale towards 0 (holds segments the silhouettes do not
            see, e.g. capsules hidden inside the torso).
        fg_samples: foreground pixels per view of the silhouette energy that is reported.
        offsets: bones (capsule names, e.g. ``head_top``) whose axis offsets are fitted too
            (default: none — radii only).
        max_offset: bound (metres) of every offset coordinate.
        offset_lr: Adam step size of the offsets (metres).
        offset_prior: pull of the offsets towards 0 (per square metre, against the IoU).
        hull_filter: fit to the masks intersected with the reprojection of their visual hull
            (needs at least two valid views; with fewer the masks are used as given).
        hull_voxel: voxel edge of that hull (metres).
        hull_margin: the hull is carved in the box around the capsules at the pose, padded by
            this (metres) plus the largest radius.
        refit_passes, refit_scale: the coarse-to-fine passes of :meth:`BodyFit.start`.

    A fit that lowers the hard IoU of the masks it fitted (the soft IoU's optimum need not be
    the hard IoU's) is undone: the body is left as it was and ``kept`` is ``False``. A fit
    whose IoU stays far below a person's (:func:`~torchmocap.likelihoods.silhouette.check_fit_iou`)
    gives a warning: the masks or the cameras are wrong.

    ``forward(theta (D,), frame) -> info`` with ``iou_before``/``iou_after`` (mean over views),
    ``kept``,
    ``energy_before``/``energy_after``, the fitted ``scales`` per segment (this call's) and
    ``total_scales`` (against the radii the fit was built with), and, with ``offsets``,
    the fitted ``offsets`` (metres, parent frame) per bone; with ``hull_filter``, ``hull``:
    whether it was applied, the views carved, the fraction of the foreground kept and the IoUs
    with the filtered masks.
    """

    def __init__(self, body, rig, iterations: int = 60, lr: float = 0.05,
                 min_scale: float = 0.6, max_scale: float = 1.8, symmetric: bool = True,
                 stride: int = 1, tau: float = 0.15, prior_weight: float = 0.02,
                 fg_samples: int = 400, offsets=(), max_offset: float = 0.08,
                 offset_lr: float = 0.005, offset_prior: float = 0.1,
                 hull_filter: bool = False, hull_voxel: float = 0.02,
                 hull_margin: float = 0.3, refit_passes: int = 0,
                 refit_scale: float = 0.25) -> None:
        super().__init__(body, refit_passes, refit_scale)
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
            raise ValueError(f"iterations: expected an int >= 0, got {iterations!r}")
        if not (0 < min_scale <= 1 <= max_scale and math.isfinite(max_scale)):
            raise ValueError(f"min_scale, max_scale: expected 0 < min_scale <= 1 <= max_scale, "
                             f"got {min_scale}, {max_scale}")
        if not (isinstance(lr, (int, float)) and lr > 0):
            raise ValueError(f"lr: expected a number > 0, got {lr!r}")
        self.rig = rig
        self.iterations, self.lr = iterations, float(lr)
        self.min_scale, self.max_scale = float(min_scale), float(max_scale)
        self.fg_samples = int(fg_samples)
        self.stride, self.tau = int(stride), float(tau)
        self.prior_weight = float(prior_weight)
        if isinstance(offsets, str):
            offsets = [offsets]
        unknown = [b for b in offsets if b not in body.bone_names]
        if unknown:
            raise ValueError(f"offsets: unknown bones {unknown}; bones: {body.bone_names}")
        for name, v in (("max_offset", max_offset), ("offset_lr", offset_lr)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or \
                    not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
        if isinstance(offset_prior, bool) or not isinstance(offset_prior, (int, float)) or \
                not offset_prior >= 0 or not math.isfinite(offset_prior):
            raise ValueError(f"offset_prior: expected a finite number >= 0, got {offset_prior!r}")
        if not isinstance(hull_filter, bool):
            raise ValueError(f"hull_filter: expected a bool, got {hull_filter!r}")
        for name, v, positive in (("hull_voxel", hull_voxel, True),
                                  ("hull_margin", hull_margin, False)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < 0 or (positive and v == 0):
                raise ValueError(f"{name}: expected a finite number {'> 0' if positive else '>= 0'}"
                                 f", got {v!r}")
        self.hull_filter = hull_filter
        self.hull_voxel, self.hull_margin = float(hull_voxel), float(hull_margin)
        self.offset_bones = list(dict.fromkeys(offsets))
        self.max_offset, self.offset_lr = float(max_offset), float(offset_lr)
        self.offset_prior = float(offset_prior)
        self.register_buffer("offset_index", torch.tensor(
            [body.bone_names.index(b) for b in self.offset_bones], dtype=torch.long))
        # the bounds hold against these radii (the body's when the fit was built) over every
        # call: refit passes scale what the previous pass left, within the same total range
        self.register_buffer("initial_radii", body.radii.detach().clone(), persistent=False)
        names = [_segment(n) if symmetric else n for n in body.bone_names]
        self.segments = list(dict.fromkeys(names))
        self.register_buffer("segment_index", torch.tensor([self.segments.index(n)
                                                            for n in names]))

    def forward(self, theta: torch.Tensor, frame) -> dict:
        if getattr(frame, "silhouettes", None) is None:
            raise ValueError("frame: the body fit needs silhouettes")
        body, rig = self.body, self.rig
        dt, dev = body.radii.dtype, body.radii.device
        valid = None
        if getattr(frame, "view_dropped", None) is not None:
            valid = ~frame.view_dropped.bool()
        r0 = body.radii.detach().clone()
        off0 = body.axis_offsets.detach().clone()
        fit_off = len(self.offset_bones) > 0
        with torch.no_grad():
            kin = body.skeleton(theta.to(dt)[None], check_finite=False)
            ends0 = body.endpoints(kin)  # (1, B, 2, 3) with the body's current offsets
            # where each fitted capsule moves per metre of offset: its parent joint's rotation
            R = kin.rotations[0, body.parent_index[self.offset_index]]  # (F, 3, 3)
        ends = ends0
        masks, hull_info = frame.silhouettes, None
        if self.hull_filter:
            masks, hull_info = self._hull_filtered(masks, valid, ends0, r0)
        hard = prepare_silhouettes(masks, self.fg_samples, blur=0.0, view_valid=valid, dtype=dt)

        def moved(delta):  # endpoints with ``delta (F, 3)`` added to the fitted offsets
            shift = (R @ delta[:, :, None])[..., 0]  # (F, 3) world
            full = torch.zeros(ends0.shape[1], 3, dtype=dt, device=dev).index_add(
                0, self.offset_index.to(dev), shift)
            return ends0 + full[None, :, None, :]

        def energy(radii, obs, smooth_, ends=ends0):
            return silhouette_energy(ends, radii, rig, obs, smooth=smooth_)[0]

        st = self.stride
        target = masks[:, ::st, ::st].to(dt)  # (C, H', W')
        vw = (torch.ones(target.shape[0], dtype=dt, device=dev) if valid is None
              else valid.to(dev, dt))

        def soft_iou(radii, ends=ends):
            m = soft_capsule_silhouettes(ends, radii, rig, stride=st, tau=self.tau)[0]
            inter = (m * target).flatten(1).sum(-1)
            union = (m + target - m * target).flatten(1).sum(-1).clamp_min(1.0)
            return ((inter / union) * vw).sum() / vw.sum().clamp_min(1.0)

        def set_radii(radii):
            body.end_shrink.copy_(torch.where(body.end_shrink > 0, radii,
                                              torch.zeros_like(radii)))
            body.radii.copy_(radii)

        def iou(radii, delta=None):
            """IoU with the masks as given (and, with the hull filter, the filtered ones)."""
            set_radii(radii)
            if delta is not None:
                body.axis_offsets.copy_(off0.index_add(0, self.offset_index, delta))
            model = render_capsule_silhouettes(body, rig, theta.to(dt))
            out = []
            for m in ([frame.silhouettes] if hull_info is None or not hull_info["applied"]
                      else [frame.silhouettes, masks]):
                v = silhouette_iou(model, m)
                keep = (torch.ones_like(v, dtype=torch.bool) if valid is None
                        else valid.to(v.device))
                out.append(float(v[keep].mean()) if bool(keep.any()) else float("nan"))
            return out

        with torch.no_grad():
            e0 = float(energy(r0, hard, False))
        iou0, *iou0_f = iou(r0)
        log_s = torch.zeros(len(self.segments), dtype=dt, device=dev, requires_grad=True)
        delta = torch.zeros(len(self.offset_bones), 3, dtype=dt, device=dev,
                            requires_grad=fit_off)
        # per segment: the room left to the bounds by the scale earlier calls applied
        done = torch.where(self.initial_radii > 0, r0 / self.initial_radii.to(r0).clamp_min(1e-12),
                           torch.ones_like(r0)).log()
        seg = self.segment_index.to(dev)
        n_seg = len(self.segments)
        lo = torch.full((n_seg,), -math.inf, dtype=dt, device=dev).scatter_reduce(
            0, seg, math.log(self.min_scale) - done, "amax")
        hi = torch.full((n_seg,), math.inf, dtype=dt, device=dev).scatter_reduce(
            0, seg, math.log(self.max_scale) - done, "amin")
        hi = torch.maximum(hi, lo)  # a segment already outside (set by hand): held at its bound
        groups = [{"params": [log_s], "lr": self.lr}]
        if fit_off:
            groups.append({"params": [delta], "lr": self.offset_lr})
        opt = torch.optim.Adam(groups)
        # the bound applies to the fitted offset itself (the body's offset plus the change)
        d_lo = -self.max_offset - off0[self.offset_index]
        d_hi = self.max_offset - off0[self.offset_index]

        def objective(ls, d):
            e = moved(d) if fit_off else ends0
            return soft_iou(r0 * ls[self.segment_index].exp(), e)

        with torch.no_grad():
            start = float(objective(log_s, delta))
        best, best_d, best_v = log_s.detach().clone(), delta.detach().clone(), start
        for _ in range(self.iterations):
            opt.zero_grad()
            with torch.enable_grad():
                v = objective(log_s, delta)
                loss = self.prior_weight * log_s.square().mean() - v
                if fit_off:
                    total = off0[self.offset_index] + delta
                    loss = loss + self.offset_prior * total.square().sum()
                loss.backward()
            opt.step()
            with torch.no_grad():
                log_s.copy_(torch.minimum(torch.maximum(log_s, lo), hi))
                if fit_off:
                    delta.copy_(torch.minimum(torch.maximum(delta, d_lo), d_hi))
                v = float(objective(log_s, delta))
            if v > best_v:
                best, best_d, best_v = log_s.detach().clone(), delta.detach().clone(), v
        radii = r0 * best[self.segment_index].exp()
        with torch.no_grad():
            e1 = float(energy(radii, hard, False, moved(best_d) if fit_off else ends0))
        # leaves the fitted radii (and offsets) in the body
        iou1, *iou1_f = iou(radii.detach(), best_d if fit_off else None)
        # the soft objective's optimum is not the hard IoU's: a fit that lowers the hard IoU
        # of the masks it fitted is undone (the body is left as it was)
        kept = (iou1_f or [iou1])[0] >= (iou0_f or [iou0])[0]
        if not kept:
            set_radii(r0)
            body.axis_offsets.copy_(off0)
            best, e1, iou1, iou1_f = torch.zeros_like(best), e0, iou0, iou0_f
        check_fit_iou(iou1, "body_fit")
        total = body.radii / self.initial_radii.to(body.radii).clamp_min(1e-12)
        first = [self.segment_index.tolist().index(i) for i in range(len(self.segments))]
        info = {"iou_before": iou0, "iou_after": iou1, "kept": kept, "energy_before": e0,
                "energy_after": e1,
                "scales": {n: round(float(math.exp(float(best[i]))), 4)
                           for i, n in enumerate(self.segments)},
                "total_scales": {n: round(float(total[first[i]]), 4)
                                 for i, n in enumerate(self.segments)}}
        if hull_info is not None:
            if iou0_f:
                hull_info.update(iou_before=iou0_f[0], iou_after=iou1_f[0])
            info["hull"] = hull_info
        if fit_off:
            info["offsets"] = {b: [round(float(x), 4) for x in body.axis_offsets[int(k)]]
                               for b, k in zip(self.offset_bones, self.offset_index)}
        return info

    def _hull_filtered(self, masks: torch.Tensor, valid: torch.Tensor | None,
                       ends: torch.Tensor, radii: torch.Tensor) -> tuple[torch.Tensor, dict]:
        return hull_filtered_masks(self.rig, masks, valid, ends, radii, self.hull_margin,
                                   self.hull_voxel)

    def extra_repr(self) -> str:
        out = (f"iterations={self.iterations}, scale=[{self.min_scale}, {self.max_scale}], "
               f"segments={len(self.segments)}")
        if self.offset_bones:
            out += f", offsets={self.offset_bones}, max_offset={self.max_offset}"
        if self.hull_filter:
            out += f", hull_filter=True, hull_voxel={self.hull_voxel}"
        return out
