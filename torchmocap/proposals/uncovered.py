"""Data-driven limb jumps into foreground the model does not explain yet.

The silhouette-driven proposal of Hauberg & Pedersen (eq. 12, :class:`~torchmocap.proposals.
InSilhouette`) only *rejects* joint positions that leave the foreground; a limb that already lies
in front of the torso passes, so nothing pulls it towards foreground no part of the model covers
(a raised arm of a subject fitted from a standing start). :class:`UncoveredLimbProposal` adds the
missing pull. Per frame it carves the visual hull of the masks (:func:`foreground_points`: voxel
centres inside the foreground of every usable view — a point consistent with all views, unlike a
pixel, and free of single-view mask noise). For a particle chosen to jump it picks a limb and
**regrows** it through the hull voxels that the rest of the model leaves unexplained
(:func:`draw_limb_targets`):

1. ``d_n`` = distance of hull voxel ``n`` to the skin of every capsule *not* of the limb
   (:func:`unexplained_distance`); a voxel with ``d_n > margin`` is unexplained, weight
   ``d_n − margin`` (foreground far from the model pulls hardest);
2. the limb's end (wrist, ankle) aims at the farthest unexplained voxel in reach within a cone
   around a voxel drawn by weight (the limb's extremity), the hinge (elbow, knee) is drawn on the
   circle of positions joining root and end, a 2-DoF end's tip (toe) among the voxels the two
   new bones leave unexplained;
3. the drawn joint positions are projected onto the skeleton by the limb's closed-form inverse
   kinematics (:func:`~torchmocap.ik.solve_limb`, the best solution within the joint limits),
   and clamped into the limits.

Every other particle (and the non-limb DoFs of a jumper) is the ``base`` proposal's draw, so the
proposal is a mixture ``(1 − jump_prob) q_base + jump_prob q_jump``; it is the mutation kernel of
annealing as well (its coordinates and std are the base's). The jump density has no closed form:
``log_q`` is not reported. ``stats``: ``jumped`` (particles regrown), ``jump_no_candidate``
(jumpers whose limb root saw no unexplained voxel: left as the base drew them), ``hull_points``
and ``fallback_hull`` (1 when a frame has no usable view or an empty hull: no jumps).

Shapes: ``P`` particles, ``N`` hull voxels, ``B`` capsules, ``K`` joints of a limb chain.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import torch

from torchmocap.body.capsules import segment_distance
from torchmocap.ik.limb import HUMAN31_LIMBS, LimbSpec, solve_limb
from torchmocap.proposals.base import Proposal, ProposalContext, Proposed

__all__ = ["UncoveredLimbProposal", "draw_limb_targets", "foreground_points",
           "unexplained_distance"]


def foreground_points(rig, masks: torch.Tensor, bounds: torch.Tensor, voxel: float,
                      view_valid: torch.Tensor | None = None,
                      largest_component: bool = True) -> torch.Tensor:
    """Centres ``(N, 3)`` of the visual-hull voxels of ``masks (C, H, W)`` in ``bounds (3, 2)``.

    Views with ``view_valid`` False (dropped) or an empty mask do not carve. With
    ``largest_component`` only the largest 26-connected part is kept (the subject; noise blobs
    that happen to agree across views are dropped). Empty ``(0, 3)`` when no view is usable.
    """
    from torchmocap.cameras import visual_hull

    if not isinstance(masks, torch.Tensor) or masks.dim() != 3:
        raise ValueError(f"masks: expected a (C, H, W) tensor, got "
                         f"{getattr(masks, 'shape', type(masks).__name__)}")
    if masks.shape[0] != rig.num_cameras:
        raise ValueError(f"masks: expected {rig.num_cameras} views (the rig's cameras), got "
                         f"{masks.shape[0]}")
    if not (isinstance(voxel, (int, float)) and math.isfinite(voxel) and voxel > 0):
        raise ValueError(f"voxel: expected a size > 0 (metres), got {voxel!r}")
    fg = masks.bool()
    ok = fg.flatten(1).any(1)
    if view_valid is not None:
        ok = ok & view_valid.bool().to(ok.device)
    idx = ok.nonzero()[:, 0].tolist()
    dt = rig.K.dtype
    if not idx:
        return torch.zeros(0, 3, dtype=dt, device=masks.device)
    sub = rig if len(idx) == rig.num_cameras else rig.subset(idx)
    hull = visual_hull(sub.double(), fg[idx], bounds.detach().double().cpu(), float(voxel))
    if largest_component:
        hull = hull.largest_component()
    return hull.centers().to(dtype=dt, device=masks.device)


def unexplained_distance(points: torch.Tensor, endpoints: torch.Tensor, radii: torch.Tensor,
                         keep: torch.Tensor | None = None) -> torch.Tensor:
    """Distance ``(P, N)`` (metres; negative inside) of ``points (N, 3)`` to the skin of the
    capsules ``endpoints (P, B, 2, 3)`` with ``radii (B,)`` selected by ``keep (B,)`` bool
    (default all); ``+inf`` when none is kept."""
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {tuple(points.shape)}")
    if endpoints.dim() != 4 or endpoints.shape[-2:] != (2, 3):
        raise ValueError(f"endpoints: expected shape (P, B, 2, 3), got "
                         f"{tuple(endpoints.shape)}")
    if keep is not None:
        endpoints, radii = endpoints[:, keep], radii[keep]
    P, N = endpoints.shape[0], points.shape[0]
    if endpoints.shape[1] == 0 or N == 0:
        return torch.full((P, N), torch.inf, dtype=points.dtype, device=points.device)
    pts = points.to(endpoints.dtype).expand(P, N, 3)
    d = segment_distance(pts, endpoints) - radii.to(endpoints)[None, None]
    return d.amin(-1)


def _draw(weight: torch.Tensor, generator: torch.Generator | None
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Index ``(P,)`` drawn by row from ``weight (P, N)`` and whether the row had any mass."""
    has = weight.sum(1) > 0
    idx = torch.zeros(weight.shape[0], dtype=torch.long, device=weight.device)
    if bool(has.any()):
        idx[has] = torch.multinomial(weight[has], 1, generator=generator)[:, 0]
    return idx, has


def draw_limb_targets(points: torch.Tensor, weight: torch.Tensor, root: torch.Tensor,
                      current: torch.Tensor, lengths: torch.Tensor, radii: torch.Tensor,
                      shell: float, margin: float, generator: torch.Generator | None = None,
                      cone_deg: float = 20.0, tip_length: float = 0.0
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Target positions of a limb's joints drawn from weighted points (step 2 of the module
    docstring), the far end first.

    1. **end** (wrist, ankle): a point within the limb's reach of the root
       (``|l1 - l2| <= |x - root| <= l1 + l2 + tip_length + shell``) drawn by ``weight`` gives a
       direction; the end aims at the farthest candidate within ``cone_deg`` of it (the limb's
       extremity in that direction — a limb's own voxels lie all along it), pulled in to the
       reach ``l1 + l2`` when beyond it;
    2. **hinge** (elbow, knee): a point on the circle of joints that connect root and end
       (``| |x - root| - l1 | <= shell`` and ``| |x - end| - l2 | <= shell``), drawn by
       ``weight`` plus a small constant (any point of the foreground will do); none: the
       current hinge (the limb's IK then keeps its swivel);
    3. **tip** (``K = 3``; toe): a point at ``l3`` from the end drawn by ``weight`` among those the
       two placed bones do not cover (within their ``radius + margin``); none: the end plus the
       current end-to-tip vector.

    Args:
        points: ``(N, 3)`` candidate positions (hull voxel centres).
        weight: ``(P, N)`` non-negative draw weights (0: not a candidate for the end or tip).
        root: ``(P, 3)`` the limb root (shoulder, hip), which stays.
        current: ``(P, K, 3)`` the limb's current hinge, end (and tip) positions.
        lengths: ``(K,)`` bone lengths ``l1`` (root–hinge), ``l2`` (hinge–end)[, ``l3``].
        radii: ``(K,)`` capsule radii of those bones.
        shell: half-width (metres) of the shells.
        margin: see step 3.
        generator: randomness.
        cone_deg: half-angle of the cone of step 1: about twice the angle a limb's radius
            subtends over its length (5 cm over 30 cm: 10 degrees).
        tip_length: with ``K = 2``, the length of the rigid tip beyond the end (the human31
            hand): voxels that far are still in reach (the end then aims at them, stretched).

    Returns:
        ``targets (P, K, 3)`` and ``found (P,)`` bool (an end was drawn; rows without one repeat
        ``current``).
    """
    if points.dim() != 2 or points.shape[-1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {tuple(points.shape)}")
    if weight.dim() != 2 or weight.shape[1] != points.shape[0]:
        raise ValueError(f"weight: expected shape (P, {points.shape[0]}), got "
                         f"{tuple(weight.shape)}")
    P = weight.shape[0]
    if lengths.dim() != 1 or lengths.numel() not in (2, 3) or radii.shape != lengths.shape:
        raise ValueError(f"lengths, radii: expected two (K,) tensors with K = 2 or 3, got "
                         f"{tuple(lengths.shape)} and {tuple(radii.shape)}")
    K = lengths.numel()
    if root.shape != (P, 3) or current.shape != (P, K, 3):
        raise ValueError(f"root, current: expected shapes ({P}, 3) and ({P}, {K}, 3), got "
                         f"{tuple(root.shape)} and {tuple(current.shape)}")
    if not bool(torch.isfinite(weight).all()) or bool((weight < 0).any()):
        raise ValueError("weight: expected finite values >= 0")
    if not (shell > 0 and margin >= 0):
        raise ValueError(f"shell, margin: expected shell > 0 and margin >= 0, got {shell}, "
                         f"{margin}")
    if not (0 < cone_deg < 90 and tip_length >= 0):
        raise ValueError(f"cone_deg, tip_length: expected 0 < cone_deg < 90 and tip_length "
                         f">= 0, got {cone_deg}, {tip_length}")
    dt, dev = root.dtype, root.device
    zero = torch.zeros((), dtype=dt, device=dev)
    pts = points.to(dt)
    w = weight.to(dt)
    l1, l2 = float(lengths[0]), float(lengths[1])
    l3_reach = float(tip_length) if K == 2 else 0.0
    out = current.to(dt).clone()
    # 1. the end: a direction drawn by weight, then the farthest candidate in its cone
    d_root = torch.cdist(root, pts)  # (P, N)
    reach = (d_root >= abs(l1 - l2)) & (d_root <= l1 + l2 + l3_reach + shell)
    cand = torch.where(reach, w, zero)
    idx, found = _draw(cand, generator)
    to = pts - root[:, None]  # (P, N, 3)
    unit = to / d_root[..., None].clamp_min(1e-9)
    cos = (unit * unit[torch.arange(P, device=dev), idx][:, None]).sum(-1)
    far = torch.where((cos >= math.cos(math.radians(cone_deg))) & (cand > 0), d_root,
                      torch.full((), -1.0, dtype=dt, device=dev))
    idx = far.argmax(1)
    to = pts[idx] - root
    n = to.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    end = root + to * (n.clamp(max=l1 + l2) / n)
    end = torch.where(found[:, None], end, out[:, 1])
    # 2. the hinge, on the circle between root and end
    ring = ((d_root - l1).abs() <= shell) & ((torch.cdist(end, pts) - l2).abs() <= shell)
    idx, has = _draw(torch.where(ring, w + 1e-3, zero), generator)
    hinge = torch.where((has & found)[:, None], pts[idx], out[:, 0])
    out[:, 0], out[:, 1] = hinge, end
    if K == 3:  # 3. the tip, among the points the two new bones leave unexplained
        segs = torch.stack([torch.stack([root, hinge], 1), torch.stack([hinge, end], 1)], 1)
        near = segment_distance(pts.expand(P, -1, -1), segs) - radii[:2].to(dt)  # (P, N, 2)
        free = near.amin(-1) > margin
        l3 = float(lengths[2])
        shell3 = ((torch.cdist(end, pts) - l3).abs() <= shell) & free
        idx, has = _draw(torch.where(shell3, w, zero), generator)
        to = pts[idx] - end
        tip = end + l3 * to / to.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        keep = end + (current[:, 2] - current[:, 1]).to(dt)
        out[:, 2] = torch.where((has & found)[:, None], tip, keep)
    return out, found


class UncoveredLimbProposal(Proposal):
    """``base`` draws, with a fraction of the particles' limbs regrown into foreground that the
    rest of the model does not explain (see the module docstring).

    Args:
        base: the proposal of every particle (and the mutation kernel's coordinates and std),
            e.g. :class:`~torchmocap.proposals.GaussianDiffusionProposal`.
        skeleton, body, rig: runtime dependencies (the body's current radii are used, so a
            body fit shows).
        chains: limbs that may jump (names of :data:`~torchmocap.ik.HUMAN31_LIMBS` or
            :class:`~torchmocap.ik.LimbSpec`).
        jump_prob: probability that a particle's draw regrows one limb (chosen uniformly).
        voxel: hull voxel size (metres).
        margin: a voxel closer than this to the skin of the rest of the model is explained
            (metres; also the slack around a placed bone).
        shell: half-width of the bone-length shell in which a joint's target is drawn
            (default ``voxel``).
        reach_padding: the hull is carved in the box of the first call's joints grown by the
            longest limb chain plus this (metres).
        largest_component: keep the largest connected part of the hull only.
        cone_deg: the end of a limb aims at the farthest unexplained voxel within this angle of
            a drawn one (:func:`draw_limb_targets`).
        tries: draws per jumping particle; the first whose limb lies within the joint limits
            is kept (none: the particle keeps the base's draw, ``stats["jump_infeasible"]``).
    """

    def __init__(self, base: Proposal, skeleton, body, rig,
                 chains: Sequence[str | LimbSpec] = ("l_arm", "r_arm", "l_leg", "r_leg"),
                 jump_prob: float = 0.2, voxel: float = 0.03, margin: float = 0.04,
                 shell: float | None = None, reach_padding: float = 0.1,
                 largest_component: bool = True, tries: int = 8,
                 cone_deg: float = 20.0) -> None:
        super().__init__()
        if not isinstance(base, Proposal):
            raise TypeError(f"base: expected a Proposal, got {type(base).__name__}")
        if rig is None or body is None:
            raise ValueError("rig, body: the uncovered-limb proposal needs the cameras and the "
                             "capsule body")
        for name, v, lo_ok in (("jump_prob", jump_prob, True), ("voxel", voxel, False),
                               ("margin", margin, True), ("reach_padding", reach_padding, True)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v < 0 or (v == 0 and not lo_ok):
                raise ValueError(f"{name}: expected a number {'>=' if lo_ok else '>'} 0, got "
                                 f"{v!r}")
        if jump_prob > 1:
            raise ValueError(f"jump_prob: expected a probability in [0, 1], got {jump_prob!r}")
        shell = float(voxel) if shell is None else shell
        if isinstance(shell, bool) or not isinstance(shell, (int, float)) or not shell > 0:
            raise ValueError(f"shell: expected a number > 0 (metres), got {shell!r}")
        if isinstance(tries, bool) or not isinstance(tries, int) or tries < 1:
            raise ValueError(f"tries: expected an int >= 1, got {tries!r}")
        self.tries = tries
        if isinstance(cone_deg, bool) or not isinstance(cone_deg, (int, float)) \
                or not 0 < cone_deg < 90:
            raise ValueError(f"cone_deg: expected an angle in (0, 90) degrees, got {cone_deg!r}")
        self.cone_deg = float(cone_deg)
        if isinstance(chains, str) or not chains:
            raise ValueError(f"chains: expected a non-empty list of limbs, got {chains!r}")
        self.base, self.skeleton, self.body, self.rig = base, skeleton, body, rig
        self.jump_prob, self.voxel, self.margin = float(jump_prob), float(voxel), float(margin)
        self.shell, self.reach_padding = float(shell), float(reach_padding)
        self.largest_component = bool(largest_component)
        self.num_dofs = skeleton.num_dofs
        self._chains = []
        rest = skeleton.joint_positions(skeleton.zero_pose(dtype=torch.float64))
        bones = list(body.bone_names)
        for c in chains:
            if isinstance(c, str) and c not in HUMAN31_LIMBS:
                raise ValueError(f"chains: unknown limb {c!r}; known: {list(HUMAN31_LIMBS)}")
            if not isinstance(c, (str, LimbSpec)):
                raise TypeError(f"chains: expected limb names or LimbSpecs, got "
                                f"{type(c).__name__}")
            spec = HUMAN31_LIMBS[c] if isinstance(c, str) else c
            try:
                names = [spec.root, spec.hinge, spec.end]
                end_dofs = skeleton.joint_dofs(spec.end)
                if spec.tip is not None and end_dofs:  # the tip only matters for a 2-DoF end
                    names.append(spec.tip)
                idx = [skeleton.joint_index(n) for n in names]
                brad = [bones.index(n) for n in names[1:]]
            except (KeyError, ValueError) as e:
                raise ValueError(f"chains: limb {c!r} does not fit the skeleton ({e})") from None
            lengths = (rest[idx[1:]] - rest[idx[:-1]]).norm(dim=-1).float()
            tip_len = 0.0
            if spec.tip is not None and len(idx) == 3:  # a rigid tip beyond a 0-DoF end
                tip_len = float((rest[skeleton.joint_index(spec.tip)] - rest[idx[2]]).norm())
            # the capsules that move with the limb: every bone below its root
            moving = torch.zeros(len(bones), dtype=torch.bool)
            for b, child in enumerate(bones):  # the bone parent(child) -> child
                j = skeleton.parents[skeleton.joint_index(child)]
                while j >= 0 and j != idx[0]:
                    j = skeleton.parents[j]
                moving[b] = j == idx[0]
            self._chains.append({"name": c if isinstance(c, str) else spec.root,
                                 "spec": spec, "joints": idx, "bones": brad,
                                 "lengths": lengths, "moving": moving, "tip": tip_len})
        self.reach = max(float(c["lengths"].sum()) + c["tip"] for c in self._chains)
        self._state: dict = {}

    @property
    def requires(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(dict.fromkeys(tuple(self.base.requires) + ("silhouettes",)))

    def coordinates(self, theta: torch.Tensor) -> torch.Tensor:
        return self.base.coordinates(theta)

    @property
    def coordinate_std(self) -> torch.Tensor | None:
        return self.base.coordinate_std

    def _points(self, frame, theta: torch.Tensor) -> torch.Tensor:
        """The frame's hull voxels (carved once per frame around the first call's poses)."""
        if self._state.get("frame") is frame:  # the object, not its id (reused once freed)
            return self._state["points"]
        masks = getattr(frame, "silhouettes", None)
        if masks is None:
            pts = theta.new_zeros(0, 3)
        else:
            pos = self.skeleton(theta.reshape(-1, self.num_dofs),
                                check_finite=False).positions.reshape(-1, 3)
            pad = self.reach + self.reach_padding
            bounds = torch.stack([pos.amin(0) - pad, pos.amax(0) + pad], 1)
            valid = None
            if getattr(frame, "view_dropped", None) is not None:
                valid = ~frame.view_dropped.bool()
            pts = foreground_points(self.rig, masks, bounds, self.voxel, valid,
                                    self.largest_component).to(theta)
        self._state = {"frame": frame, "points": pts}
        return pts

    def _regrow(self, theta: torch.Tensor, chain: dict, pts: torch.Tensor,
                generator: torch.Generator | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Regrow ``chain`` of poses ``theta (n, D)`` through ``pts (N, 3)``: ``tries`` draws per
        pose, the first whose limb IK lies within the joint limits kept. Returns the poses
        ``(n, D)``, ``ok (n,)`` (regrown) and ``none (n,)`` (no unexplained voxel in reach)."""
        n, T = theta.shape[0], self.tries
        kin = self.skeleton(theta, check_finite=False)
        radii = self.body.radii.detach().to(theta)
        keep = ~chain["moving"].to(theta.device)
        w = (unexplained_distance(pts, self.body.endpoints(kin), radii, keep)
             - self.margin).clamp_min(0)
        none = ~(w > 0).any(1)
        pos = kin.positions
        rep = lambda x: x.repeat_interleave(T, 0)  # noqa: E731  (n, ...) -> (n T, ...)
        targets, found = draw_limb_targets(pts, rep(w), rep(pos[:, chain["joints"][0]]),
                                           rep(pos[:, chain["joints"][1:]]),
                                           chain["lengths"].to(theta), radii[chain["bones"]],
                                           self.shell, self.margin, generator, self.cone_deg,
                                           chain["tip"])
        res = solve_limb(self.skeleton, rep(theta), chain["spec"], targets,
                         method="closed_form")
        good = (found & res.within_limits).reshape(n, T)
        first = torch.where(good, torch.arange(T, 0, -1, device=good.device), 0).argmax(1)
        pick = torch.arange(n, device=good.device) * T + first
        return res.theta[pick], good.any(1), none

    def sample(self, context: ProposalContext, num: int,
               generator: torch.Generator | None = None) -> Proposed:
        t0 = time.perf_counter()
        out = self.base.sample(context, num, generator)
        stats = dict(out.stats)
        theta = out.particles
        if self.jump_prob == 0:
            return out
        if context.frame is None:
            raise ValueError("context.frame: the uncovered-limb proposal needs the "
                             "observations")
        pts = self._points(context.frame, context.previous)
        stats["hull_points"] = int(pts.shape[0])
        jumped = missed = infeasible = 0
        if pts.shape[0] == 0:
            stats["fallback_hull"] = 1
        else:
            P = theta.shape[0]
            dev = theta.device
            u = torch.rand(P, generator=generator, device=dev, dtype=torch.float64)
            which = torch.randint(len(self._chains), (P,), generator=generator, device=dev)
            jump = u < self.jump_prob
            theta = theta.clone()
            for c, ch in enumerate(self._chains):
                sel = (jump & (which == c)).nonzero()[:, 0]
                if sel.numel() == 0:
                    continue
                new, ok, none = self._regrow(theta[sel], ch, pts, generator)
                theta[sel[ok]] = new[ok].to(theta.dtype)
                jumped += int(ok.sum())
                missed += int(none.sum())
                infeasible += int((~ok & ~none).sum())
        stats["jumped"] = jumped
        stats["jump_no_candidate"] = missed
        stats["jump_infeasible"] = infeasible
        stats["seconds"] = time.perf_counter() - t0  # the base's draw included
        return Proposed(particles=theta, stats=stats)

    def extra_repr(self) -> str:
        return (f"chains={[c['name'] for c in self._chains]}, jump_prob={self.jump_prob}, "
                f"voxel={self.voxel}, margin={self.margin}, shell={self.shell}")
