"""The subject's Anny shape fitted at the first frame, and the tracker's capsules fitted to it.

:class:`AnnyBodyFit` is a :class:`~torchmocap.filters.tracking.body_fit.BodyFit`: at the known
first pose ``θ₀`` it fits the Anny parametric body (:class:`~torchmocap.body.ParametricBody`) to
the subject and gives the tracker's :class:`~torchmocap.body.CapsuleBody` the girths of that
body — the fast path: the capsule likelihood keeps its speed.

1. **Joints.** The tracking skeleton (the subject's bone lengths) posed at ``θ₀`` gives the
   joints; :func:`~torchmocap.body.fit_phenotype` fits the phenotype and segment scales to them
   (age, sex, height and proportions set the bone lengths; weight and muscle barely move them).
2. **Silhouettes.** The phenotype's mesh, driven by the tracking skeleton at ``θ₀``, is
   summarised by capsules (:func:`~torchmocap.body.fit_capsules`: assignment, axes and ends
   fixed at the joint fit's phenotype); each capsule's radius is the area-weighted mean distance
   of its skin to its axis, a differentiable function of the phenotype. Adam maximises the soft
   IoU of those capsules' silhouettes
   (:func:`~torchmocap.likelihoods.silhouette.soft_capsule_silhouettes`) with the first frame's
   masks — by default the foreground the views agree on near the body (``hull_filter``,
   ``hull_reach``: clutter one view sees, a shadow on the floor, a bystander removed) — over the
   phenotype's logits, pulled towards the joint fit (``prior``) except for weight
   and muscle — the girth the joints cannot see.
3. **Capsules.** :func:`~torchmocap.body.fit_capsules` fits radii, axis offsets and ends to the
   fitted mesh at ``θ₀``; they replace the runtime body's when the capsules' hard IoU with the
   masks (the filtered ones, with the hull filter) does not drop (``kept``), as
   :class:`~torchmocap.filters.SilhouetteBodyFit` does.

The report (``forward``'s info, metrics.json ``body_fit``) holds the fitted ``phenotype``, the
standing ``height`` of the fitted body on the tracking skeleton and its ``girths``
(:func:`body_girths`), the IoUs and the times. :meth:`AnnyBodyFit.fitted_mesh` gives the fitted
body for the outputs (``track.glb``).
"""

from __future__ import annotations

import math
import time

import torch
from torch import nn

from torchmocap.body.capsule_fit import capsule_radii, fit_capsules, vertex_areas
from torchmocap.body.capsules import capsule_endpoints
from torchmocap.body.phenotype_fit import fit_phenotype
from torchmocap.filters.tracking.body_fit import BodyFit, hull_filtered_masks
from torchmocap.likelihoods.silhouette import (
    check_fit_iou,
    render_capsule_silhouettes,
    silhouette_iou,
    soft_capsule_silhouettes,
)

__all__ = ["GIRTHS", "AnnyBodyFit", "body_girths"]

#: girths reported (name → carrier joints of the slice's skin, the two joints between which
#: the horizontal slice lies at the rest pose, and the fraction from the first to the second)
GIRTHS: dict[str, tuple[tuple[str, ...], str, str, float]] = {
    "chest": (("spine",), "spine", "neck", 0.15),
    "waist": (("pelvis", "spine"), "pelvis", "spine", 0.6),
    "hips": (("pelvis", "l_hip", "r_hip"), "pelvis", "l_hip", 1.0),
    "thigh": (("l_hip",), "l_hip", "l_knee", 0.3),
    "calf": (("l_knee",), "l_knee", "l_ankle", 0.3),
    "upper_arm": (("l_shoulder",), "l_shoulder", "l_elbow", 0.5),
}


def _hull_perimeter(xy: torch.Tensor) -> float:
    """Perimeter of the convex hull of 2D points ``(N, 2)`` (a tape measure's length)."""
    pts = sorted(set(map(tuple, xy.double().tolist())))
    if len(pts) < 3:
        return float("nan")

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    hull = lower[:-1] + upper[:-1]
    return sum(math.dist(hull[i], hull[(i + 1) % len(hull)]) for i in range(len(hull)))


def body_girths(body, vertices: torch.Tensor, joints: torch.Tensor, band: float = 0.01
                ) -> dict[str, float]:
    """Tape-measure girths (metres) of an Anny body standing in the skeleton's rest pose: the
    convex-hull perimeter of the skin within ``band`` of a horizontal plane (:data:`GIRTHS`).

    Args:
        body: the :class:`~torchmocap.body.ParametricBody` of ``vertices (V, 3)``.
        joints: ``(J, 3)`` the skeleton's joints of the same pose.
    """
    parts = body.mesh_parts().cpu()
    v, jp = vertices.detach().cpu(), joints.detach().cpu()
    names = list(body.joint_names)
    out = {}
    for name, (carriers, a, b, f) in GIRTHS.items():
        z = float(jp[names.index(a), 2] + f * (jp[names.index(b), 2] - jp[names.index(a), 2]))
        sel = torch.zeros_like(parts, dtype=torch.bool)
        for c in carriers:
            sel |= parts == names.index(c)
        sel &= (v[:, 2] - z).abs() < band
        out[name] = round(_hull_perimeter(v[sel, :2]), 4)
    return out


class AnnyBodyFit(BodyFit):
    """Fit the Anny body's phenotype to the first frame (joints, then silhouettes) and the
    runtime capsules to the fitted mesh (module docstring).

    Args:
        body: the runtime :class:`~torchmocap.body.CapsuleBody` (changed in place); its skeleton
            is the tracking skeleton (human31's joints).
        rig: the cameras of the silhouettes.
        cache_dir: the Anny cache folder (default: :func:`~torchmocap.body.anny_model.
            default_cache_dir`).
        joint_iterations: Adam steps of the joint fit.
        silhouette_iterations: Adam steps of the silhouette fit (0: joints only).
        lr: step size of the phenotype's logits in the silhouette fit.
        prior: pull of the silhouette fit's logits towards the joint fit's (weight and muscle
            free), per squared logit, against the soft IoU.
        stride, tau: the soft silhouettes' pixel stride and softness (pixels).
        hull_filter: fit the silhouettes to the foreground the views agree on
            (:func:`~torchmocap.filters.tracking.body_fit.hull_filtered_masks`: the masks
            intersected with the reprojection of their visual hull, carved around the body at
            the first pose); ``hull_voxel``, ``hull_margin`` (metres), ``hull_tolerance``
            (views a hull voxel may miss) and ``hull_reach`` (metres: voxels farther from the
            capsules of the joint fit's body are dropped; None: none) as there. The reported
            IoUs stay those with the masks as given; ``hull`` says what was done and the IoUs
            with the filtered masks, on which ``kept`` is then decided. Default on,
            10 cm: on the Fig. 8 outdoor sequences the body fitted to the masks as given
            matches the clean silhouettes worse than the joints alone (mean IoU 0.798 vs
            0.809; below the anthropometric capsules on dancing), fitted to these masks 0.816
            (a fit to the clean frame: 0.820; ``experiments/body/outdoor_fit.py``).
        refit_passes, refit_scale: the coarse-to-fine passes of :meth:`BodyFit.start`.
    """

    def __init__(self, body, rig, cache_dir: str | None = None, joint_iterations: int = 200,
                 silhouette_iterations: int = 30, lr: float = 0.1, prior: float = 0.01,
                 stride: int = 2, tau: float = 0.3, hull_filter: bool = True,
                 hull_voxel: float = 0.02, hull_margin: float = 0.3, hull_tolerance: int = 0,
                 hull_reach: float | None = 0.1, refit_passes: int = 0,
                 refit_scale: float = 0.25) -> None:
        super().__init__(body, refit_passes, refit_scale)
        for name, v in (("joint_iterations", joint_iterations),
                        ("silhouette_iterations", silhouette_iterations)):
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name}: expected an int >= 0, got {v!r}")
        for name, v, pos in (("lr", lr, True), ("prior", prior, False), ("tau", tau, True)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < 0 or (pos and v == 0):
                raise ValueError(f"{name}: expected a finite number {'> 0' if pos else '>= 0'}"
                                 f", got {v!r}")
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"stride: expected an int >= 1, got {stride!r}")
        if not isinstance(hull_filter, bool):
            raise ValueError(f"hull_filter: expected a bool, got {hull_filter!r}")
        for name, v, pos in (("hull_voxel", hull_voxel, True), ("hull_margin", hull_margin,
                                                                  False)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < 0 or (pos and v == 0):
                raise ValueError(f"{name}: expected a finite number {'> 0' if pos else '>= 0'}"
                                 f", got {v!r}")
        if isinstance(hull_tolerance, bool) or not isinstance(hull_tolerance, int) or \
                hull_tolerance < 0:
            raise ValueError(f"hull_tolerance: expected an int >= 0, got {hull_tolerance!r}")
        if hull_reach is not None and (isinstance(hull_reach, bool) or not isinstance(
                hull_reach, (int, float)) or not math.isfinite(hull_reach) or hull_reach <= 0):
            raise ValueError(f"hull_reach: expected a finite number > 0 or None, got "
                             f"{hull_reach!r}")
        self.hull_filter, self.hull_tolerance = hull_filter, hull_tolerance
        self.hull_reach = None if hull_reach is None else float(hull_reach)
        self.hull_voxel, self.hull_margin = float(hull_voxel), float(hull_margin)
        missing = sorted({"pelvis", "spine", "neck", "l_hip", "l_knee", "l_ankle", "l_shoulder",
                          "l_elbow"} - set(body.skeleton.joint_names))
        if missing:
            raise ValueError(f"body: the Anny body fit needs a human31 skeleton; joints {missing}"
                             " are missing")
        self.cache_dir = cache_dir
        self._parametric: nn.Module | None = None
        self.rig = rig
        self.joint_iterations, self.silhouette_iterations = joint_iterations, \
            silhouette_iterations
        self.lr, self.prior, self.stride, self.tau = float(lr), float(prior), stride, float(tau)
        self.phenotype: torch.Tensor | None = None

    @property
    def parametric(self) -> nn.Module:
        """The Anny body driven by the tracking skeleton, read from the cache at the first use
        (building the tracker needs neither the cache nor ``anny``)."""
        if self._parametric is None:
            from torchmocap.body import ParametricBody

            sk = self.body.skeleton
            self._parametric = ParametricBody(sk, cache_dir=self.cache_dir).to(
                sk.offsets.device)
        return self._parametric

    # ------------------------------------------------------------------ the fitted body
    def fitted_mesh(self) -> tuple[nn.Module, torch.Tensor] | None:
        """The Anny body and the fitted phenotype ``(6,)`` (None before the fit): drive it with
        the tracking skeleton's offsets (``body(theta, phenotype, offsets=...)``)."""
        return None if self.phenotype is None else (self.parametric, self.phenotype)

    def checkpoint_state(self) -> dict[str, torch.Tensor]:
        state = super().checkpoint_state()
        if self.phenotype is not None:
            state["phenotype"] = self.phenotype.clone()
        return state

    def load_checkpoint_state(self, state: dict[str, torch.Tensor]) -> None:
        state = dict(state)
        phen = state.pop("phenotype", None)
        super().load_checkpoint_state(state)
        self.phenotype = None if phen is None else phen.clone()
        self.body.surface_phenotype = self.phenotype

    # ------------------------------------------------------------------ the fit
    def forward(self, theta: torch.Tensor, frame) -> dict:
        if getattr(frame, "silhouettes", None) is None:
            raise ValueError("frame: the Anny body fit needs silhouettes")
        from torchmocap.body.anny_model import PHENOTYPE_NAMES

        t0 = time.perf_counter()
        caps, pb, rig = self.body, self.parametric, self.rig
        sk = caps.skeleton
        dt, dev = caps.radii.dtype, caps.radii.device
        theta = theta.to(dt)
        off = sk.offsets.to(dt)
        valid = None if getattr(frame, "view_dropped", None) is None else \
            ~frame.view_dropped.bool().to(dev)
        with torch.no_grad():
            joints = sk(theta[None], check_finite=False).positions  # (1, J, 3)
        jfit = fit_phenotype(pb, joints.float(), theta[None].float(),
                             iterations=self.joint_iterations)
        phen_j = jfit.phenotype.to(dt)
        t_joints = time.perf_counter() - t0

        def mesh(phen):
            return pb(theta, phen, offsets=off).vertices  # (V, 3)

        faces = pb.faces
        labels = pb.capsule_labels(caps.bone_names)
        r_before = caps.radii.detach().clone()
        state0 = {k: getattr(caps, k).detach().clone() for k in self.STATE}
        iou0 = self._iou(theta, frame.silhouettes, valid)
        # the capsule structure (assignment, axes, ends) at the joint fit's phenotype; the
        # radii then follow the mesh differentiably
        with torch.no_grad():
            v0 = mesh(phen_j)
        fit0 = fit_capsules(sk, v0, theta, labels=labels, faces=faces)
        z_j = torch.logit(phen_j.clamp(1e-3, 1 - 1e-3))
        z = z_j.clone().requires_grad_(self.silhouette_iterations > 0)
        hull_info = None
        t1 = time.perf_counter()
        if self.silhouette_iterations > 0:
            with torch.no_grad():
                kin = sk(theta[None], check_finite=False)
                ends_full = capsule_endpoints(  # (B, 2, 3) the axes unshrunk
                    kin.positions, caps.parent_index, caps.child_index,
                    torch.zeros_like(fit0.radii), kin.rotations, fit0.axis_offsets)[0]
                ends = capsule_endpoints(  # (1, B, 2, 3)
                    kin.positions, caps.parent_index, caps.child_index,
                    fit0.body.end_shrink.to(dt), kin.rotations, fit0.axis_offsets)
            w_area = vertex_areas(v0, faces)
            st = self.stride
            masks = frame.silhouettes
            if self.hull_filter:
                masks, hull_info = hull_filtered_masks(
                    rig, masks, valid, ends, fit0.radii, self.hull_margin, self.hull_voxel,
                    self.hull_tolerance, self.hull_reach)
                if hull_info["applied"]:  # the runtime capsules are still the unfitted ones
                    hull_info["iou_before"] = self._iou(theta, masks, valid)
            target = masks[:, ::st, ::st].to(dev, dt)
            vw = torch.ones(target.shape[0], dtype=dt, device=dev) if valid is None else \
                valid.to(dt)
            free = torch.tensor([n in ("weight", "muscle") for n in PHENOTYPE_NAMES],
                                device=dev)
            opt = torch.optim.Adam([z], lr=self.lr)

            def soft_iou(zz):
                v = mesh(torch.sigmoid(zz))
                radii = capsule_radii(v, w_area, fit0, ends_full)
                m = soft_capsule_silhouettes(ends, radii, rig, stride=st, tau=self.tau)[0]
                inter = (m * target).flatten(1).sum(-1)
                union = (m + target - m * target).flatten(1).sum(-1).clamp_min(1.0)
                return ((inter / union) * vw).sum() / vw.sum().clamp_min(1.0)

            best_z, best_v = z.detach().clone(), -math.inf
            for _ in range(self.silhouette_iterations):
                opt.zero_grad()
                v = soft_iou(z)
                if float(v.detach()) > best_v:  # the soft IoU of z before this step
                    best_v, best_z = float(v.detach()), z.detach().clone()
                pull = torch.where(free, torch.zeros_like(z), (z - z_j).square()).sum()
                (self.prior * pull - v).backward()
                opt.step()
                with torch.no_grad():
                    z.clamp_(-6, 6)
            with torch.no_grad():
                v = float(soft_iou(z))
            if v > best_v:
                best_z = z.detach().clone()
            z = best_z
        phen = torch.sigmoid(z.detach())
        t_sil = time.perf_counter() - t1
        with torch.no_grad():
            v1 = mesh(phen)
        fit = fit_capsules(sk, v1, theta, labels=labels, faces=faces)
        for k in self.STATE:
            getattr(caps, k).copy_(getattr(fit.body, k).to(getattr(caps, k)))
        iou1 = self._iou(theta, frame.silhouettes, valid)
        kept = iou1 >= iou0
        if hull_info is not None and hull_info["applied"]:
            # judged on the masks it fitted (as SilhouetteBodyFit): a body fitted to the
            # foreground the views agree on may cover less of the corruptions
            hull_info["iou_after"] = self._iou(theta, masks, valid)
            kept = hull_info["iou_after"] >= hull_info["iou_before"]
        if not kept:
            for k, v in state0.items():
                getattr(caps, k).copy_(v)
        check_fit_iou(iou1 if kept else iou0, "body_fit")
        self.phenotype = phen.detach().clone()
        # the surface term (SurfaceSilhouetteLikelihood) poses this phenotype
        caps.surface_phenotype = self.phenotype
        with torch.no_grad():
            rest = sk.zero_pose(dtype=dt, device=dev)
            vr = pb(rest, phen, offsets=off).vertices
            jr = sk(rest[None], check_finite=False).positions[0]
        height = float(vr[:, 2].max() - vr[:, 2].min())
        extra = {} if hull_info is None else {"hull": hull_info}
        return {
            "phenotype": {n: round(float(x), 4) for n, x in zip(PHENOTYPE_NAMES, phen)},
            "phenotype_joints": {n: round(float(x), 4) for n, x in zip(PHENOTYPE_NAMES, phen_j)},
            "height": round(height, 4),
            "girths": body_girths(pb, vr, jr),
            "iou_before": iou0, "iou_after": iou1 if kept else iou0, "kept": kept,
            "joint_rmse": round(jfit.joint_rmse, 5),
            "radii_scale": round(float((caps.radii / r_before.clamp_min(1e-9)).mean()), 4),
            "joints_s": round(t_joints, 3), "silhouettes_s": round(t_sil, 3), **extra}

    def _iou(self, theta: torch.Tensor, masks: torch.Tensor, valid) -> float:
        with torch.no_grad():
            model = render_capsule_silhouettes(self.body, self.rig, theta)
        v = silhouette_iou(model, masks)
        keep = torch.ones_like(v, dtype=torch.bool) if valid is None else valid.to(v.device)
        return float(v[keep].mean()) if bool(keep.any()) else float("nan")

    def extra_repr(self) -> str:
        out = (f"joint_iterations={self.joint_iterations}, "
               f"silhouette_iterations={self.silhouette_iterations}, stride={self.stride}")
        if self.hull_filter:
            out += f", hull_filter=True, hull_tolerance={self.hull_tolerance}"
        return out
