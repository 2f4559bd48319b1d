"""Kinematic jump sampling (KJS): forwards/backwards flips of limbs under monocular perspective
(Sminchisescu & Triggs 2003, §3, Fig. 5).

For a pose and a camera, every link of a limb can be turned towards or away from the camera
without changing the image of its end joint (:func:`~torchmocap.geometry.flip_child`); the
*interpretation tree* of a limb (:func:`~torchmocap.ik.interpretation_tree`) enumerates every
combination of flips down the chain, pruning branches whose camera ray misses the sphere of the
moved parent. Each leaf (a list of 3D joint positions) becomes joint angles by the limb's inverse
kinematics (:func:`~torchmocap.ik.solve_limb`); leaves outside the joint limits or that the limb
cannot reproduce (residual above ``ik_tol``) are pruned. The closed form enumerates every exact
solution of a leaf, so when all of them violate a limit no exact in-limit solution exists and the
leaf is pruned without the Levenberg–Marquardt fallback (``ik_method="auto"`` runs it anyway —
about 20x slower — and can only return an inexact in-limit pose, which the residual test
prunes). Limbs hang from the trunk
independently, so the jumps of several limbs combine as the **product** of their trees.

Chains (``chains``) are limb names of :data:`~torchmocap.ik.HUMAN31_LIMBS` (``l_arm``, ``r_arm``,
``l_leg``, ``r_leg``), optionally restricted to some links: ``"l_leg"`` flips every link
(hip→knee, knee→ankle, ankle→toe: 8 leaves), ``"l_leg:1,2"`` only the shank and the foot
(4 leaves), as a string or a mapping ``{limb: l_leg, links: [1, 2]}``. A limb whose end joint
has no DoF (the human31 arms: the wrist is rigid) is flipped at its hinge and end only
(shoulder→elbow, elbow→wrist: 4 leaves); its tip (the hand) follows the forearm, so a flipped
forearm moves the hand's image slightly (human31 cannot keep it).

Chain selection (Fig. 5, ``SelectSamplingChain``) per mode, from its covariance ``Sigma = V diag
(sigma^2) V^T`` (``context.covariances`` ``(K, D, D)``):
``vote(C) = sum_{i in dofs(C)} sum_j sigma_j |v_j[i]|`` — the uncertainty of the chain's DoFs along
the principal directions, weighted by their standard deviations (absolute values: the sign of an
eigenvector is arbitrary). ``select``: ``"vote"`` takes the ``num_chains`` best chains,
``"vote_random"`` draws them with probability proportional to the votes, ``"random"`` uniformly,
``"all"`` takes every chain (a fixed partition, as the paper's Table 1). Without covariances the
voting modes fall back to ``"random"``.

:class:`KinematicJumpProposal` applies the jumps to the modes of ``context.previous`` — or, with a
``base`` proposal (covariance-scaled sampling), to each of the base's samples: Fig. 5's
``KinematicDiffusionJumpSampling`` (CSS sample → interpretation tree → every leaf). It returns
exactly ``num`` poses: more leaves than ``num`` are subsampled at random, fewer are repeated
cyclically. ``stats``: ``leaves`` (tree leaves enumerated, summed over the starts), ``valid``
(rays hit in front of the camera), ``kept`` (valid, and the limb IK exact within the joint
limits), ``pruned`` (``leaves - kept``), ``unique`` (distinct poses returned), ``starts``,
``votes`` (how often each chain was chosen), ``component`` (``(P,)`` mode of each sample) and
``jumped`` (``(P,)`` bool: some link of the sample is flipped).

Example:
    >>> from torchmocap.skeleton import human31
    >>> from torchmocap.cameras import make_ring_rig
    >>> sk, rig = human31(), make_ring_rig(1)
    >>> th = sk.zero_pose(); th[sk.dof_index("l_knee_flex")] = 1.0
    >>> th[sk.dof_index("l_hip_flex")] = 0.6
    >>> jumps = kinematic_jumps(sk, th, ["l_leg"], rig.camera_centers()[0].float())
    >>> jumps.theta.shape[-1], bool(jumps.kept >= 1)
    (31, True)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from torchmocap.ik.flip_tree import interpretation_tree
from torchmocap.ik.limb import HUMAN31_LIMBS, LimbSpec, _plan, solve_limb
from torchmocap.proposals.base import Proposal, ProposalContext, Proposed
from torchmocap.proposals.covariance_scaled import mode_set

__all__ = [
    "JumpChain",
    "KinematicJumpProposal",
    "KinematicJumps",
    "LimbFlips",
    "chain_votes",
    "kinematic_jumps",
    "limb_flips",
    "parse_chain",
    "select_chains",
]

SELECT = ("vote", "vote_random", "random", "all")


@dataclass(frozen=True)
class JumpChain:
    """A flippable chain: a limb and the links that may flip (``None`` = all of them).

    Link ``k`` joins the ``k``-th and ``k+1``-th joint of the limb's tree (root first): for a leg
    0 = thigh (hip→knee), 1 = shank (knee→ankle), 2 = foot (ankle→toe)."""

    limb: str
    links: tuple[int, ...] | None = None

    @property
    def name(self) -> str:
        if self.links is None:
            return self.limb
        return f"{self.limb}:{','.join(str(k) for k in self.links)}"


def parse_chain(c) -> JumpChain:
    """A :class:`JumpChain` from ``"l_leg"``, ``"l_leg:1,2"``, ``{limb: ..., links: [...]}`` or a
    :class:`JumpChain`."""
    if isinstance(c, JumpChain):
        return c
    if isinstance(c, str):
        limb, _, links = c.partition(":")
        lk = tuple(int(v) for v in links.split(",") if v.strip()) if links else None
        return JumpChain(limb.strip(), lk)
    if isinstance(c, Mapping):
        unknown = set(c) - {"limb", "links"}
        if unknown or "limb" not in c:
            raise ValueError(f"chains: a mapping needs 'limb' (and optionally 'links'), got "
                             f"{dict(c)}")
        lk = c.get("links")
        return JumpChain(str(c["limb"]), None if lk is None else tuple(int(v) for v in lk))
    raise TypeError(f"chains: expected a limb name, 'limb:links' or a mapping, got "
                    f"{type(c).__name__}")


def _limb_spec(limb: str) -> LimbSpec:
    if limb not in HUMAN31_LIMBS:
        raise KeyError(f"chains: unknown limb {limb!r}; known: {list(HUMAN31_LIMBS)}")
    return HUMAN31_LIMBS[limb]


def _tree_joints(skeleton, limb: str) -> list[int]:
    """Joint indices of a limb's interpretation tree: root, hinge, end (+ tip when the end
    joint has DoFs to turn it)."""
    plan = _plan(skeleton, _limb_spec(limb))
    n = 3 if not plan.end_dofs else len(plan.target_joints) + 1
    return [plan.root] + plan.target_joints[: n - 1]


@dataclass
class LimbFlips:
    """The flips of one limb for a batch of poses (:func:`limb_flips`).

    Attributes:
        theta: ``(B, L, D)`` poses of every leaf (leaf 0 = no flip = the input pose).
        kept: ``(B, L)`` bool, the leaf survived pruning (ray hits, joint limits, IK residual).
        valid: ``(B, L)`` bool, every ray of the leaf met its sphere in front of the camera.
        within_limits: ``(B, L)`` bool, the IK solution is inside the joint limits.
        residual: ``(B, L)`` IK residual (metres).
        positions: ``(B, L, K+1, 3)`` the leaves' joint positions (root first).
        flips: ``(L, K)`` bool flip pattern of each leaf.
        joints: ``K+1`` joint indices of the tree.
        dofs: the limb's DoF indices.
    """

    theta: torch.Tensor
    kept: torch.Tensor
    valid: torch.Tensor
    within_limits: torch.Tensor
    residual: torch.Tensor
    positions: torch.Tensor
    flips: torch.Tensor
    joints: list[int]
    dofs: list[int]


def limb_flips(skeleton, theta: torch.Tensor, chain, camera_center: torch.Tensor,
               ik_method: str = "closed_form", ik_tol: float = 1e-3,
               min_flip: float = 0.0) -> LimbFlips:
    """Every forwards/backwards flip of one limb, as full poses.

    Args:
        skeleton: the model (human31 limbs).
        theta: ``(B, D)`` poses.
        chain: a limb name, ``"limb:links"`` or :class:`JumpChain`.
        camera_center: ``(3,)`` optical centre (world, metres).
        ik_method: :func:`~torchmocap.ik.solve_limb` method.
        ik_tol: largest IK residual (metres) of a kept leaf.
        min_flip: a flip that moves its child joint by less than this (metres) is not a new
            interpretation: near tangency the two ray–sphere roots nearly coincide (a link
            almost perpendicular to its camera ray), and the leaf is dropped in favour of the
            one without that flip. 0 (default) keeps every leaf, as the paper's trees.

    Returns:
        :class:`LimbFlips` with ``L = 2^(number of flippable links)`` leaves per pose.
    """
    if not (isinstance(min_flip, (int, float)) and math.isfinite(min_flip) and min_flip >= 0):
        raise ValueError(f"min_flip: expected a number >= 0 (metres), got {min_flip!r}")
    ch = parse_chain(chain)
    spec = _limb_spec(ch.limb)
    plan = _plan(skeleton, spec)
    joints = _tree_joints(skeleton, ch.limb)
    K = len(joints) - 1
    if theta.dim() != 2:
        raise ValueError(f"theta: expected shape (B, D), got {tuple(theta.shape)}")
    if ch.links is not None and (not ch.links or min(ch.links) < 0 or max(ch.links) >= K):
        raise ValueError(f"chains: links of {ch.limb!r} must be in 0..{K - 1}, got {ch.links}")
    B, D = theta.shape
    kin = skeleton(theta)
    pos = kin.positions[:, joints]  # (B, K+1, 3)
    tree = interpretation_tree(pos, camera_center.to(theta))
    flips = tree.flips
    distinct = torch.ones(tree.valid.shape, dtype=torch.bool, device=theta.device)
    if min_flip > 0:  # leaf i against leaf i XOR 2^k: the same tree without flipping link k
        leaf_i = torch.arange(flips.shape[0], device=theta.device)
        for k in range(K):
            moved = (tree.positions[:, :, k + 1]
                     - tree.positions[:, leaf_i ^ (1 << k), k + 1]).norm(dim=-1)
            distinct &= ~(flips[:, k].to(theta.device)[None] & (moved < min_flip))
    if ch.links is not None:
        fixed = [k for k in range(K) if k not in ch.links]
        leaf = ~flips[:, fixed].any(-1) if fixed else torch.ones(flips.shape[0], dtype=torch.bool)
        leaf = leaf.to(flips.device)
        idx = leaf.nonzero()[:, 0]
        flips = flips[idx]
        positions = tree.positions[:, idx]
        valid = tree.valid[:, idx]
        distinct = distinct[:, idx]
    else:
        positions, valid = tree.positions, tree.valid
    L = flips.shape[0]
    targets = positions[:, :, 1:]  # (B, L, K, 3) hinge, end[, tip]
    res = solve_limb(skeleton, theta[:, None], spec, targets, method=ik_method, tol=None)
    out = res.theta.reshape(B, L, D)
    within = res.within_limits.reshape(B, L)
    resid = res.residual.reshape(B, L)
    kept = valid & within & (resid <= ik_tol) & distinct
    # leaf 0 is the input pose itself
    out[:, 0] = theta
    kept[:, 0] = True
    return LimbFlips(out, kept, valid, within, resid, positions, flips, joints, list(plan.dofs))


def _combine_leaves(x: torch.Tensor, per: Sequence[LimbFlips], include_original: bool = True
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every combination of the leaves of several limbs' trees, for a batch of poses.

    Args:
        x: ``(B, D)`` the poses the trees were grown from.
        per: one :class:`LimbFlips` of ``x`` per limb (distinct limbs).
        include_original: keep the combination without any flip.

    Returns:
        ``poses (B, C, D)``, ``kept (B, C)`` (every limb's leaf kept, and some flip unless
        ``include_original``), ``flips (C, sum K)`` (the limbs' flip patterns side by side) and
        ``flipped (C,)`` (some link flipped), ``C = prod L`` combinations in the order of
        ``itertools.product`` over the limbs' leaves (the first limb's leaf slowest).
    """
    B, D = x.shape
    dev = x.device
    sizes = [p.flips.shape[0] for p in per]
    grid = torch.meshgrid(*[torch.arange(n, device=dev) for n in sizes], indexing="ij")
    combos = torch.stack([g.reshape(-1) for g in grid], 1)  # (C, limbs)
    flipped = combos.ne(0).any(1)
    poses = x[:, None].expand(B, combos.shape[0], D).clone()
    kept = torch.ones(B, combos.shape[0], dtype=torch.bool, device=dev)
    patterns = []
    for s, p in enumerate(per):
        leaf = combos[:, s]
        dofs = torch.tensor(p.dofs, dtype=torch.long, device=dev)
        poses[:, :, dofs] = p.theta.index_select(1, leaf).index_select(2, dofs)
        kept &= p.kept.index_select(1, leaf)
        patterns.append(p.flips.to(dev).index_select(0, leaf))
    if not include_original:
        kept &= flipped[None]
    flips = torch.cat(patterns, 1) if patterns else torch.zeros(combos.shape[0], 0,
                                                                dtype=torch.bool, device=dev)
    return poses, kept, flips, flipped


@dataclass
class KinematicJumps:
    """The product of the trees of several chains for one pose (:func:`kinematic_jumps`).

    Attributes:
        theta: ``(N, D)`` kept full-body poses (the input pose first when kept).
        flips: ``(N, sum_c K_c)`` bool, the flip pattern of each pose (chains concatenated).
        leaves: ``prod_c L_c`` combinations enumerated.
        valid: combinations whose rays all hit in front of the camera.
        kept: ``N``: valid combinations whose limb IK is exact (``ik_tol``) within the joint
            limits (minus the unflipped one without ``include_original``).
    """

    theta: torch.Tensor
    flips: torch.Tensor
    leaves: int
    valid: int
    kept: int


def kinematic_jumps(skeleton, theta: torch.Tensor, chains: Sequence, camera_center: torch.Tensor,
                    ik_method: str = "closed_form", ik_tol: float = 1e-3,
                    include_original: bool = True, min_flip: float = 0.0) -> KinematicJumps:
    """All kept combinations of flips of ``chains`` (product of their trees) for one pose.

    Args:
        skeleton: the model.
        theta: ``(D,)`` pose.
        chains: chain specs (:func:`parse_chain`), on distinct limbs.
        camera_center: ``(3,)``.
        ik_method, ik_tol: see :func:`limb_flips`.
        include_original: keep the combination without any flip (the input pose).
        min_flip: see :func:`limb_flips`.

    Returns:
        :class:`KinematicJumps`.
    """
    chs = [parse_chain(c) for c in chains]
    limbs = [c.limb for c in chs]
    if len(set(limbs)) != len(limbs):
        raise ValueError(f"chains: each limb at most once, got {[c.name for c in chs]}")
    if theta.dim() != 1:
        raise ValueError(f"theta: expected shape (D,), got {tuple(theta.shape)}")
    per = [limb_flips(skeleton, theta[None], c, camera_center, ik_method, ik_tol, min_flip)
           for c in chs]
    n_leaves = math.prod(p.flips.shape[0] for p in per)
    n_valid = math.prod(int(p.valid[0].sum()) for p in per)
    poses, kept, flips, _ = _combine_leaves(theta[None], per, include_original)
    th, fl = poses[0][kept[0]], flips[kept[0]]
    return KinematicJumps(th, fl, n_leaves, n_valid, th.shape[0])


def chain_votes(covariance: torch.Tensor, chain_dofs: Sequence[Sequence[int]]) -> torch.Tensor:
    """Fig. 5 ``SelectSamplingChain`` votes ``(K, M)`` of ``M`` chains for ``(K, D, D)`` (or
    ``(D, D)``) covariances: ``sum_{i in dofs(C)} sum_j sigma_j |v_j[i]|``."""
    cov = covariance if covariance.dim() == 3 else covariance[None]
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    lam, V = torch.linalg.eigh(cov.double())
    sigma = lam.clamp_min(0).sqrt()  # (K, D)
    contrib = (V.abs() * sigma[:, None, :]).sum(-1)  # (K, D): sum_j sigma_j |v_j[i]|
    votes = torch.stack([contrib[:, list(d)].sum(-1) for d in chain_dofs], -1)
    return votes if covariance.dim() == 3 else votes[0]


def select_chains(votes: torch.Tensor | None, num_chains: int, select: str,
                  generator: torch.Generator | None = None, num: int | None = None
                  ) -> list[int]:
    """Indices of the chains to flip for one mode (``votes (M,)`` or None)."""
    M = votes.shape[0] if votes is not None else int(num)
    k = min(num_chains, M)
    if select == "all":
        return list(range(M))
    if select in ("vote", "vote_random") and votes is not None:
        if select == "vote":
            return sorted(torch.argsort(votes, descending=True)[:k].tolist())
        p = votes.double().clamp_min(0)
        p = p / p.sum() if float(p.sum()) > 0 else torch.full_like(p, 1.0 / M)
        return sorted(torch.multinomial(p, k, replacement=False, generator=generator).tolist())
    perm = torch.randperm(M, generator=generator)
    return sorted(perm[:k].tolist())


class KinematicJumpProposal(Proposal):
    """Kinematic jumps of the modes — or of a base proposal's samples — (module docstring).

    Args:
        skeleton: the tracking model (runtime dependency).
        rig: the camera rig (runtime dependency); the jumps are about ``camera``'s rays.
        chains: the chain set ``C`` (limb names / ``"limb:links"`` / mappings).
        select: ``"vote"``, ``"vote_random"``, ``"random"`` or ``"all"``.
        num_chains: chains flipped together per start (product of their trees).
        camera: index of the camera in ``rig``.
        base: optional :class:`Proposal` whose samples are jumped (e.g. a
            :class:`~torchmocap.proposals.CovarianceScaledProposal`: KJS + CSS); its
            ``stats["component"]`` (per-sample mode index) selects each sample's chain vote.
        include_original: keep the unflipped start among the samples.
        ik_method, ik_tol: limb IK method and the largest residual (m) of a kept leaf.
        max_rounds: base draws to fill ``num`` samples.
        min_flip: drop near-tangent flips that move their child by less than this (metres;
            :func:`limb_flips`); 0 keeps every leaf.
    """

    def __init__(self, skeleton, rig, chains: Sequence = ("l_arm", "r_arm", "l_leg", "r_leg"),
                 select: str = "vote", num_chains: int = 1, camera: int = 0,
                 base: Proposal | None = None, include_original: bool = True,
                 ik_method: str = "closed_form", ik_tol: float = 1e-3,
                 max_rounds: int = 8, min_flip: float = 0.0) -> None:
        super().__init__()
        if not (isinstance(min_flip, (int, float)) and math.isfinite(min_flip)
                and min_flip >= 0):
            raise ValueError(f"min_flip: expected a number >= 0 (metres), got {min_flip!r}")
        self.min_flip = float(min_flip)
        if rig is None:
            raise ValueError("rig: kinematic jumps need the camera rig")
        if select not in SELECT:
            raise ValueError(f"select: expected one of {SELECT}, got {select!r}")
        for name, v, lo in (("num_chains", num_chains, 1), ("camera", camera, 0),
                            ("max_rounds", max_rounds, 1)):
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"{name}: expected an int >= {lo}, got {v!r}")
        if camera >= rig.num_cameras:
            raise ValueError(f"camera: index {camera} out of range for a "
                             f"{rig.num_cameras}-camera rig")
        if ik_method not in ("auto", "closed_form", "iterative"):
            raise ValueError(f"ik_method: expected 'auto', 'closed_form' or 'iterative', got "
                             f"{ik_method!r}")
        if not (isinstance(ik_tol, (int, float)) and ik_tol > 0):
            raise ValueError(f"ik_tol: expected a number > 0, got {ik_tol!r}")
        if base is not None and not isinstance(base, Proposal):
            raise TypeError(f"base: expected a torchmocap Proposal, got {type(base).__name__}")
        self.chains = [parse_chain(c) for c in chains]
        if not self.chains:
            raise ValueError("chains: expected at least one chain")
        limbs = [c.limb for c in self.chains]
        if len(set(limbs)) != len(limbs):
            raise ValueError(f"chains: each limb at most once, got {[c.name for c in self.chains]}")
        self.chain_dofs = []
        for c in self.chains:
            # validates the limb on this skeleton
            self.chain_dofs.append(list(_plan(skeleton, _limb_spec(c.limb)).dofs))
        self.skeleton = skeleton
        self.rig = rig
        self.select, self.num_chains, self.camera = select, num_chains, camera
        self.base = base
        self.include_original = bool(include_original)
        self.ik_method, self.ik_tol, self.max_rounds = ik_method, float(ik_tol), max_rounds

    @property
    def requires(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(getattr(self.base, "requires", ())) if self.base is not None else ()

    @property
    def coordinate_std(self):
        return None if self.base is None else self.base.coordinate_std

    def camera_center(self, like: torch.Tensor) -> torch.Tensor:
        return self.rig.camera_centers()[self.camera].to(like)

    def _chosen(self, covs: torch.Tensor | None, K: int, generator) -> list[list[int]]:
        M = len(self.chains)
        votes = None if covs is None else chain_votes(covs, self.chain_dofs)  # (K, M)
        return [select_chains(None if votes is None else votes[k], self.num_chains,
                              self.select, generator, M) for k in range(K)]

    def _jump(self, starts: torch.Tensor, comp: torch.Tensor, chosen: list[list[int]],
              stats: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Kept leaves of every start, in start order (each start's leaves in the order of the
        product of its chains' trees, the first chain slowest): poses ``(N, D)``, a flag per
        leaf (some link flipped) and the index of its start ``(N,)``."""
        c = self.camera_center(starts)
        dev = starts.device
        groups: dict[tuple[int, ...], list[int]] = {}
        for i, k in enumerate(comp.tolist()):
            groups.setdefault(tuple(chosen[k]), []).append(i)
        poses_all, jumped_all, start_all = [], [], []
        for sel, members in groups.items():
            idx = torch.tensor(members, dtype=torch.long, device=dev)
            x = starts.index_select(0, idx)
            nb = len(members)
            per = [limb_flips(self.skeleton, x, self.chains[m], c, self.ik_method, self.ik_tol,
                              self.min_flip)
                   for m in sel]
            for m in sel:
                stats["votes"][self.chains[m].name] = stats["votes"].get(
                    self.chains[m].name, 0) + nb
            stats["leaves"] += nb * math.prod(p.flips.shape[0] for p in per)
            stats["valid"] += int(torch.stack([p.valid.sum(1) for p in per]).prod(0).sum())
            poses, kept, _, flipped = _combine_leaves(x, per, self.include_original)
            b, k = kept.nonzero(as_tuple=True)  # row-major: start by start, combos in order
            poses_all.append(poses[b, k])
            jumped_all.append(flipped[k])
            start_all.append(idx[b])
            stats["kept"] += int(b.numel())
        start = torch.cat(start_all)
        order = torch.sort(start, stable=True).indices
        return (torch.cat(poses_all)[order], torch.cat(jumped_all)[order], start[order])

    def sample(self, context: ProposalContext, num: int,
               generator: torch.Generator | None = None) -> Proposed:
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise ValueError(f"num: expected an int >= 1, got {num!r}")
        D = self.skeleton.num_dofs
        modes, _ = mode_set(context, D)
        K = modes.shape[0]
        covs = context.covariances
        if covs is not None:
            covs = torch.as_tensor(covs).to(modes)
            if covs.shape == (D, D):
                covs = covs.expand(K, D, D)
            if covs.shape != (K, D, D):
                raise ValueError(f"context.covariances: expected ({K}, {D}, {D}), "
                                 f"got {tuple(covs.shape)}")
        chosen = self._chosen(covs, K, generator)
        stats: dict = {"leaves": 0, "valid": 0, "kept": 0, "starts": 0,
                       "votes": {}, "voted": int(covs is not None)}
        leaves: list[torch.Tensor] = []
        comps: list[torch.Tensor] = []
        jumps: list[torch.Tensor] = []
        if self.base is None:
            starts, comp = modes, torch.arange(K, device=modes.device)
            stats["starts"] = K
            lv, jp, st = self._jump(starts, comp, chosen, stats)
            leaves.append(lv)
            jumps.append(jp)
            comps.append(st)
        else:
            n_chains = len(self.chains) if self.select == "all" else min(
                self.num_chains, len(self.chains))
            per_start = 0.5 * 4.0**n_chains  # a first guess of the kept leaves per start
            have = 0
            for _ in range(self.max_rounds):
                n_b = max(1, math.ceil((num - have) / per_start))
                drawn = self.base.sample(context, n_b, generator)
                comp = drawn.stats.get("component")
                comp = (torch.zeros(n_b, dtype=torch.long, device=modes.device) if comp is None
                        else torch.as_tensor(comp, device=modes.device).long())
                stats["starts"] += n_b
                lv, jp, st = self._jump(drawn.particles.to(modes.dtype), comp, chosen, stats)
                leaves.append(lv)
                jumps.append(jp)
                comps.append(comp.to(st.device)[st])
                have += lv.shape[0]
                if have >= num:
                    break
                per_start = max(1.0, have / max(stats["starts"], 1))
        allx = torch.cat(leaves) if leaves else modes[:0]
        allc = torch.cat(comps) if comps else torch.zeros(0, dtype=torch.long,
                                                          device=modes.device)
        allj = torch.cat(jumps) if jumps else torch.zeros(0, dtype=torch.bool,
                                                          device=modes.device)
        n = allx.shape[0]
        if n == 0:  # nothing kept (every leaf pruned): the starts themselves
            allx, allc, n = modes, torch.arange(K, device=modes.device), K
            allj = torch.zeros(K, dtype=torch.bool, device=modes.device)
        if n >= num:
            if self.base is None:
                idx = torch.randperm(n, generator=generator,
                                     device=modes.device)[:num].sort().values
            else:  # base samples come in tree order: keep whole trees, the first ones
                idx = torch.arange(num, device=modes.device)
            unique = num
        else:
            idx = torch.arange(num, device=modes.device) % n
            unique = n
        idx = idx.to(allx.device)
        stats["pruned"] = stats["leaves"] - stats["kept"]
        stats["unique"] = unique
        stats["component"] = allc[idx]
        stats["jumped"] = allj.to(allx.device)[idx]
        return Proposed(particles=allx[idx], stats=stats)

    def extra_repr(self) -> str:
        return (f"chains={[c.name for c in self.chains]}, select={self.select!r}, "
                f"num_chains={self.num_chains}, camera={self.camera}, "
                f"include_original={self.include_original}")
