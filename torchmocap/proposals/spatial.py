"""Projected spatial prior and data-driven importance distributions (Hauberg & Pedersen 2011).

:class:`SpatialPriorProposal` draws every tracked joint's position around its ancestor's
(``x_l ~ N(F_l(θ_{t−1}), σ_l² I)``, eq. 6) and projects the set onto the pose manifold — the
least-squares fit of the skeleton to the drawn positions within the joint limits, warm-started
at the ancestor (eq. 7, :func:`~torchmocap.ik.project_to_skeleton`). With data-driven
``criteria`` each joint is first **rejection-sampled on its own** until its position satisfies
all of them, then the whole set is projected (the approximation of eqs. 11–12 and 14): a
silhouette criterion (:class:`InSilhouette`: the joint projects into the foreground of every
view that sees it) and a depth criterion (:class:`NearPointCloud`: the joint lies within
``r_l`` of the observed point cloud — small for hands, large for the spine — via a k-d tree).
``L`` three-dimensional rejection problems instead of one ``3L``-dimensional one.

Per-joint tries are capped (``max_tries``); a joint that never satisfies the criteria keeps its
last draw and is counted (``stats["failed_joints"]``). A frame without usable data for a criterion
(no foreground pixel, no depth point) switches that criterion off — the proposal falls back to the
plain spatial prior for the frame and says so (``stats["fallback_<criterion>"]``; the tracking
CLI reports the frames and warns).

The density of a projected draw has no closed form: ``log_q`` is not reported, and an SIR filter
treats the correction factor as 1 (approximate; for the paper's rejection-truncated proposals
the exact factor is a constant). Shapes: ``P`` particles, ``L`` tracked joints, ``D`` DoF.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence

import torch

from torchmocap.proposals.angular import free_dofs
from torchmocap.proposals.base import Proposal, ProposalContext, Proposed, select_ancestors

__all__ = ["InSilhouette", "JointCriterion", "NearPointCloud", "PoseInSilhouette",
           "SpatialPriorProposal", "tracked_joints"]


def tracked_joints(skeleton, free: torch.Tensor) -> list[int]:
    """Indices of the joints whose position moves when the DoFs ``free`` move (the joints
    below any joint that owns a free DoF), in skeleton order."""
    owners = {j for j in range(len(skeleton.joint_names))
              if any(d in free.tolist() for d in skeleton.joint_dofs(skeleton.joint_names[j]))}
    out = []
    for j in range(len(skeleton.joint_names)):
        k = skeleton.parents[j]
        moved = False
        while k >= 0:
            if k in owners:
                moved = True
                break
            k = skeleton.parents[k]
        if moved or (j in owners and skeleton.parents[j] < 0):
            out.append(j)
    return out


class JointCriterion:
    """Base class of per-joint data-driven criteria: ``prepare(frame) -> state | None`` (None:
    no usable data in this frame) and ``__call__(points (N, 3), joints (N,), state) -> (N,)``
    bool."""

    requires: tuple[str, ...] = ()
    name = "criterion"

    def prepare(self, frame):
        return frame

    def __call__(self, points, joints, state):
        raise NotImplementedError


class InSilhouette(JointCriterion):
    """The point projects inside the image and onto the foreground of every view of the rig
    that is not dropped in this frame (eqs. 4, 12).

    Args:
        rig: the runtime cameras of the silhouettes.
    """

    requires = ("silhouettes",)
    name = "silhouette"

    def __init__(self, rig) -> None:
        if rig is None:
            raise ValueError("rig: the silhouette criterion needs the cameras")
        self.rig = rig

    def prepare(self, frame):
        masks = getattr(frame, "silhouettes", None)
        if masks is None:
            return None
        valid = torch.ones(masks.shape[0], dtype=torch.bool, device=masks.device)
        if getattr(frame, "view_dropped", None) is not None:
            valid = ~frame.view_dropped.bool().to(masks.device)
        fg = masks.bool()
        valid = valid & fg.flatten(1).any(1)
        if not bool(valid.any()):
            return None
        return fg, valid

    def __call__(self, points, joints, state):
        fg, valid = state
        C, H, W = fg.shape
        pix, _, vis = self.rig.project(points.to(self.rig.K.dtype))  # (C, N, 2), (C, N)
        u = (pix[..., 0] + 0.5).floor().long()
        v = (pix[..., 1] + 0.5).floor().long()
        inside = vis & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        c = torch.arange(C, device=fg.device)[:, None].expand_as(u)
        on = torch.zeros_like(inside)
        on[inside] = fg[c[inside], v[inside], u[inside]]
        return (on | ~valid.to(on.device)[:, None]).all(0)


class NearPointCloud(JointCriterion):
    """The joint lies within ``r_l`` of the observed depth points (eqs. 13–14); nearest
    neighbours from a k-d tree (``scipy.spatial.cKDTree``) built once per frame.

    Args:
        radii: ``{joint: r}`` in metres; joints not named use ``default_radius``. The defaults
            follow the paper (small for hands, large for the spine): the skin-to-joint depth of
            each body part plus a margin.
        default_radius: radius of the joints not in ``radii``.
        skeleton: the runtime skeleton (joint names).
    """

    requires = ("depth",)
    name = "depth"
    DEFAULT_RADII = {"pelvis": 0.20, "spine": 0.20, "neck": 0.12, "head": 0.14,
                     "head_top": 0.10, "l_shoulder": 0.10, "r_shoulder": 0.10,
                     "l_elbow": 0.07, "r_elbow": 0.07, "l_wrist": 0.05, "r_wrist": 0.05,
                     "l_hand": 0.05, "r_hand": 0.05, "l_hip": 0.14, "r_hip": 0.14,
                     "l_knee": 0.09, "r_knee": 0.09, "l_ankle": 0.07, "r_ankle": 0.07,
                     "l_toe": 0.05, "r_toe": 0.05}

    def __init__(self, skeleton, radii: Mapping[str, float] | None = None,
                 default_radius: float = 0.10) -> None:
        r = dict(self.DEFAULT_RADII)
        r.update(dict(radii or {}))
        for k, v in r.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"radii.{k}: expected a distance > 0 (metres), got {v!r}")
        if not default_radius > 0:
            raise ValueError(f"default_radius: expected a distance > 0, got {default_radius!r}")
        self.radius = torch.tensor([float(r.get(n, default_radius))
                                    for n in skeleton.joint_names])

    def prepare(self, frame):
        pts = getattr(frame, "depth", None)
        if pts is None:
            return None
        pts = pts[torch.isfinite(pts).all(-1)]
        if pts.shape[0] == 0:
            return None
        if pts.device.type != "cpu":  # no round trip to the host: brute force on the device
            return pts.detach()
        from scipy.spatial import cKDTree

        return cKDTree(pts.detach().double().numpy())

    def __call__(self, points, joints, state):
        radius = self.radius.to(points)[joints]
        if isinstance(state, torch.Tensor):
            return nearest_distance(points, state.to(points)) < radius
        d, _ = state.query(points.detach().cpu().double().numpy(), k=1)
        d = torch.as_tensor(d, dtype=points.dtype, device=points.device)
        return d < radius


def nearest_distance(points: torch.Tensor, cloud: torch.Tensor, chunk: int = 4096
                     ) -> torch.Tensor:
    """Distance ``(N,)`` of each of ``points (N, 3)`` to its nearest neighbour in
    ``cloud (K, 3)``, by brute force in chunks of ``chunk`` cloud points (what
    :class:`NearPointCloud` uses off the CPU, where a k-d tree would need a copy to the host)."""
    best = torch.full(points.shape[:1], torch.inf, dtype=points.dtype, device=points.device)
    for s in range(0, cloud.shape[0], chunk):
        best = torch.minimum(best, torch.cdist(points, cloud[s:s + chunk]).amin(1))
    return best


class SpatialPriorProposal(Proposal):
    """Projected spatial prior (eqs. 6–7), optionally data-driven (eqs. 12, 14).

    Args:
        skeleton: the tracking model (runtime).
        position_std: std (metres) of every joint's position, or ``{joint: std}`` (others
            ``default_std``).
        joints: the tracked joints — ``"all"``, ``"upper_body"`` or names; only their DoFs
            move (the others keep the ancestor's values) and only the joints they move are
            drawn and fitted.
        criteria: data-driven per-joint criteria (:class:`InSilhouette`, :class:`NearPointCloud`);
            empty: the plain projected prior.
        max_tries: per-joint rejection cap.
        iterations, tol, prior_weight: projection settings
            (:func:`~torchmocap.ik.project_to_skeleton`).
        default_std: see ``position_std``.
        speed_gain: each joint's std grows with its speed over the last two estimates
            (``context.history``): ``σ_l' = sqrt(σ_l² + (speed_gain · |F_l(θ_{t−1}) −
            F_l(θ_{t−2})|)²)`` — a hand moving 10 cm per frame gets a wide cloud, a shoulder
            moving 1 cm keeps ``σ_l``. 0 (default): the paper's fixed spread. The spread is the
            transition prior's too (the SIR weights assume the proposal's prior is the model's).
    """

    def __init__(self, skeleton, position_std: float | Mapping[str, float] = 0.03,
                 joints: str | Sequence[str] | None = "all",
                 criteria: Sequence[JointCriterion] = (), max_tries: int = 50,
                 iterations: int = 15, tol: float = 1e-3, prior_weight: float = 1e-3,
                 default_std: float = 0.03, speed_gain: float = 0.0) -> None:
        super().__init__()
        if isinstance(speed_gain, bool) or not isinstance(speed_gain, (int, float)) \
                or not (math.isfinite(speed_gain) and speed_gain >= 0):
            raise ValueError(f"speed_gain: expected a finite number >= 0, got {speed_gain!r}")
        self.speed_gain = float(speed_gain)
        if isinstance(max_tries, bool) or not isinstance(max_tries, int) or max_tries < 1:
            raise ValueError(f"max_tries: expected an int >= 1, got {max_tries!r}")
        for c in criteria:
            if not isinstance(c, JointCriterion):
                raise TypeError(f"criteria: expected JointCriterion objects, got "
                                f"{type(c).__name__}")
        self.skeleton = skeleton
        self.num_dofs = skeleton.num_dofs
        self.criteria = list(criteria)
        self.max_tries = max_tries
        self.iterations, self.tol, self.prior_weight = iterations, float(tol), float(prior_weight)
        self.register_buffer("free", free_dofs(skeleton, joints))
        joint_idx = tracked_joints(skeleton, self.free)
        if not joint_idx:
            raise ValueError(f"joints: {joints!r} move no joint")
        self.register_buffer("joint_index", torch.tensor(joint_idx))
        names = skeleton.joint_names
        if isinstance(position_std, Mapping):
            stds = [float(position_std.get(names[j], default_std)) for j in joint_idx]
        else:
            stds = [float(position_std)] * len(joint_idx)
        if any(not (math.isfinite(s) and s > 0) for s in stds):
            raise ValueError(f"position_std: expected stds > 0 (metres), got {position_std!r}")
        self.register_buffer("std", torch.tensor(stds))
        frozen = torch.ones(self.num_dofs, dtype=torch.bool)
        frozen[self.free] = False
        self.register_buffer("frozen", frozen)
        self._free_list = self.free.tolist()
        self._states: dict = {}

    @property
    def requires(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(dict.fromkeys(m for c in self.criteria for m in c.requires))

    def coordinates(self, theta: torch.Tensor) -> torch.Tensor:
        return theta.index_select(-1, self.free.to(theta.device))

    def _prepared(self, frame):
        # keyed on the frame object itself (held here): an id() key can be reused by the next
        # frame once this one is freed, which served a stale frame's data
        if self._states.get("frame") is not frame:
            self._states = {"frame": frame, "states": [c.prepare(frame) for c in self.criteria]}
        return self._states["states"]

    def sample(self, context: ProposalContext, num: int,
               generator: torch.Generator | None = None) -> Proposed:
        from torchmocap.ik.projection import project_to_skeleton

        t0 = time.perf_counter()
        base = select_ancestors(context, num, self.num_dofs, generator)
        sk = self.skeleton
        mu = sk(base, check_finite=False).positions[:, self.joint_index]  # (P, L, 3)
        std = self._spread(context).to(mu)[None, :, None] * float(context.scale)
        P, L = mu.shape[:2]
        x = mu + torch.randn(mu.shape, generator=generator, dtype=mu.dtype,
                             device=mu.device) * std
        stats: dict = {}
        active = []
        if self.criteria:
            if context.frame is None:
                raise ValueError("context.frame: a data-driven proposal needs the observations")
            for c, st in zip(self.criteria, self._prepared(context.frame)):
                if st is None:
                    stats[f"fallback_{c.name}"] = 1  # no usable data: this criterion is off
                else:
                    active.append((c, st))
        if active:
            x, tries, failed = self._reject(x, mu, std.expand(P, L, 1), active, generator)
            stats["failed_joints"] = failed
            stats["joint_tries"] = float(tries.float().mean())
        # project onto the manifold over the tracked DoFs only; the others keep each
        # ancestor's values
        res = project_to_skeleton(sk, x, base, joints=self.joint_index.tolist(),
                                  prior_weight=self.prior_weight, iterations=self.iterations,
                                  tol=self.tol, free_dofs=self._free_list)
        theta = res.theta.to(base.dtype)
        fr = self.frozen.to(base.device)
        theta[:, fr] = base[:, fr]
        stats["projection_residual_mm"] = float(res.residual.mean()) * 1000
        stats["seconds"] = time.perf_counter() - t0
        return Proposed(particles=theta, stats=stats)

    def _spread(self, context: ProposalContext) -> torch.Tensor:
        """Per-joint std ``(L,)``: ``position_std``, widened by ``speed_gain`` times each
        joint's displacement between the last two estimates when the tracker passes them."""
        std = self.std
        history = context.history
        if self.speed_gain == 0 or history is None or history.shape[0] < 2:
            return std
        with torch.no_grad():
            pos = self.skeleton(history[-2:], check_finite=False).positions[:, self.joint_index]
            speed = (pos[1] - pos[0]).norm(dim=-1).to(std)
        return torch.sqrt(std.square() + (self.speed_gain * speed).square())

    def _reject(self, x, mu, std, active, generator):
        """Per-joint rejection sampling, in rounds of growing batches (1, 2, 4, ... candidates
        for every joint still rejected): the first accepted candidate of a joint's batch is its
        draw, so the result has the distribution of one-at-a-time sampling — the same
        ``N(mu_l, std_l^2 I)`` restricted to the criteria — in ``O(log max_tries)`` rounds of
        criterion evaluations instead of ``max_tries``. A joint still rejected after
        ``max_tries`` draws keeps its last draw.

        Shapes: ``x, mu, std (P, L, 3)``; returns ``x (P, L, 3)``, ``tries (P, L)`` (draws used,
        the accepted one included) and the number of joints that failed.
        """
        P, L = x.shape[:2]
        jidx = self.joint_index.to(x.device).expand(P, L)

        def ok(pts, js):  # every criterion, each on the points the previous ones passed
            good = torch.ones(pts.shape[0], dtype=torch.bool, device=pts.device)
            for c, st in active:
                idx = good.nonzero().squeeze(1)
                if not idx.numel():
                    break
                good[idx] = c(pts[idx], js[idx], st).to(good.device)
            return good

        bad = ~ok(x.reshape(-1, 3), jidx.reshape(-1)).reshape(P, L)
        tries = torch.ones(P, L, dtype=torch.long, device=x.device)
        used, batch = 1, 1
        while used < self.max_tries and bool(bad.any()):
            b = min(batch, self.max_tries - used)
            idx = bad.nonzero()  # (n, 2)
            n = idx.shape[0]
            cand = mu[bad][:, None] + torch.randn(n, b, 3, generator=generator, dtype=x.dtype,
                                                  device=x.device) * std[bad][:, None]
            good = ok(cand.reshape(-1, 3), jidx[bad].repeat_interleave(b)).reshape(n, b)
            hit = good.any(1)
            first = torch.where(hit, good.to(torch.uint8).argmax(1), b - 1)  # else the last
            x[idx[:, 0], idx[:, 1]] = cand[torch.arange(n, device=x.device), first]
            tries[idx[:, 0], idx[:, 1]] += first + 1
            bad[idx[hit, 0], idx[hit, 1]] = False
            used += b
            batch *= 2
        return x, tries, int(bad.sum())

    def extra_repr(self) -> str:
        return (f"joints={self.joint_index.numel()}, free_dofs={self.free.numel()}, "
                f"criteria={[c.name for c in self.criteria]}, max_tries={self.max_tries}, "
                f"speed_gain={self.speed_gain}")


class PoseInSilhouette:
    """Rejection criterion of Hauberg & Pedersen's "failed experiment" (§2, eq. 4): a whole
    pose is accepted when *every* tracked joint projects into the foreground of every view.

    ``__call__(theta (K, D), context) -> (K, L)`` bool, for
    :class:`~torchmocap.proposals.RejectionProposal` (which accepts a candidate when all are
    True).

    Args:
        skeleton, rig: runtime dependencies.
        joints: the tracked joints (as in :class:`SpatialPriorProposal`).
    """

    requires = ("silhouettes",)

    def __init__(self, skeleton, rig, joints: str | Sequence[str] | None = "all") -> None:
        self.skeleton = skeleton
        self.check = InSilhouette(rig)
        self.joint_index = torch.tensor(tracked_joints(skeleton, free_dofs(skeleton, joints)))
        self._state: dict = {}

    def __call__(self, theta: torch.Tensor, context: ProposalContext) -> torch.Tensor:
        if context.frame is None:
            raise ValueError("context.frame: the silhouette criterion needs the observations")
        if self._state.get("frame") is not context.frame:  # the object, not its id (reused)
            self._state = {"frame": context.frame, "state": self.check.prepare(context.frame)}
        st = self._state["state"]
        K, L = theta.shape[0], self.joint_index.numel()
        if st is None:  # no usable silhouette: everything passes (and the frame says so)
            return torch.ones(K, L, dtype=torch.bool, device=theta.device)
        pos = self.skeleton(theta, check_finite=False).positions[:, self.joint_index]
        return self.check(pos.reshape(-1, 3), self.joint_index.repeat(K), st).reshape(K, L)
