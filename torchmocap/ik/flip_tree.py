"""Interpretation trees: every flip combination of a kinematic chain under perspective
(Sminchisescu & Triggs 2003, §3).

Given the world positions of a non-branching chain ``J_0 (root), J_1, ..., J_K`` and a camera
centre ``c``, every joint ``J_{k+1}`` must stay on its camera ray ``c + s d_{k+1}`` (so that its
image projection is unchanged) at distance ``L_k = |J_{k+1} - J_k|`` from the *current
hypothesis* of its parent ``J_k'``. Descending the chain from the fixed root, each link has two
candidates — the two roots of the ray–sphere intersection around ``J_k'`` — so there are
``2^K`` leaves; a ray that misses the sphere of a moved parent prunes the whole subtree (and so
does a root behind the camera).

Leaf ``i`` flips link ``k`` when bit ``k`` of ``i`` is set (``flips[i, k] = (i >> k) & 1``; link
0 = root to ``J_1``). "Not flipped" keeps the original orientation of the link relative to the
ray: the child stays on the far side of the closest approach to its parent if it was there
originally (``d.(J_{k+1} - J_k) >= 0``) and on the near side otherwise. Leaf 0 is therefore the
original configuration, returned bit-exactly; a flip of a link whose parent has not moved is
the reflection of :func:`~torchmocap.geometry.flips.flip_child`.

Joint-limit pruning needs joint angles: solve the limb inverse kinematics of every leaf
(:func:`torchmocap.ik.solve_limb`) and use its ``within_limits`` flag.

Example:
    >>> chain = torch.tensor([[0.0, 0.0, 1.4], [0.0, 0.1, 1.12], [0.0, -0.1, 0.9],
    ...                       [0.0, -0.2, 0.85]])
    >>> tree = interpretation_tree(chain, torch.tensor([0.0, -4.0, 1.5]))
    >>> tree.positions.shape, tree.valid.shape, tree.flips.shape
    (torch.Size([8, 4, 3]), torch.Size([8]), torch.Size([8, 3]))
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchmocap.geometry._checks import check_finite
from torchmocap.geometry.flips import _safe_sqrt, ray_sphere_discriminant

__all__ = ["InterpretationTree", "interpretation_tree", "flip_patterns", "MAX_TREE_LINKS"]

#: Largest number of links accepted (``2^16`` leaves per chain).
MAX_TREE_LINKS = 16


@dataclass
class InterpretationTree:
    """All image-consistent flip configurations of a chain.

    Attributes:
        positions: ``(*, 2^K, K+1, 3)`` joint positions of every leaf (root first, metres).
            Pruned leaves hold finite placeholders (the closest points of the missed rays).
        valid: ``(*, 2^K)`` bool, every ray of the leaf met its sphere in front of the camera.
        flips: ``(2^K, K)`` bool flip pattern, ``flips[i, k] = (i >> k) & 1``.
    """

    positions: torch.Tensor
    valid: torch.Tensor
    flips: torch.Tensor

    @property
    def num_valid(self) -> torch.Tensor:
        """``(*)`` number of valid leaves."""
        return self.valid.sum(-1)


def flip_patterns(num_links: int, device: torch.device | str | None = None) -> torch.Tensor:
    """``(2^K, K)`` bool table, row ``i`` = bits of ``i`` (link 0 = least significant bit)."""
    if not 1 <= num_links <= MAX_TREE_LINKS:
        raise ValueError(f"num_links: expected 1..{MAX_TREE_LINKS}, got {num_links}")
    i = torch.arange(2**num_links, device=device)[:, None]
    k = torch.arange(num_links, device=device)
    return ((i >> k) & 1).bool()


def interpretation_tree(positions: torch.Tensor, camera_center: torch.Tensor) -> InterpretationTree:
    """Enumerate the ``2^K`` forwards/backwards flip configurations of a chain.

    Args:
        positions: ``(*, K+1, 3)`` world positions of the chain's joints, root first (metres);
            ``1 <= K <= 16``. The root stays fixed; bone lengths are taken from these positions.
        camera_center: ``(3,)`` or ``(*, 3)`` optical centre (broadcast against the batch).

    Returns:
        :class:`InterpretationTree` — every valid leaf projects every joint onto its original
        image point and keeps every bone length.

    Raises:
        ValueError: wrong shapes, non-finite input, too many links, or a joint at the camera
            centre.

    Example:
        >>> pos = torch.randn(5, 4, 3) * 0.3 + torch.tensor([0.0, 0.0, 4.0])
        >>> interpretation_tree(pos, torch.zeros(3)).positions.shape
        torch.Size([5, 8, 4, 3])
    """
    if not isinstance(positions, torch.Tensor):
        raise TypeError(f"positions: expected a torch.Tensor, got {type(positions).__name__}")
    if positions.dim() < 2 or positions.shape[-1] != 3 or positions.shape[-2] < 2:
        raise ValueError(f"positions: expected shape (*, K+1, 3) with K >= 1, got "
                         f"{tuple(positions.shape)}")
    K = positions.shape[-2] - 1
    if K > MAX_TREE_LINKS:
        raise ValueError(f"positions: at most {MAX_TREE_LINKS} links (2^{MAX_TREE_LINKS} leaves), "
                         f"got {K}")
    if not isinstance(camera_center, torch.Tensor):
        raise TypeError(f"camera_center: expected a torch.Tensor, got "
                        f"{type(camera_center).__name__}")
    if camera_center.dim() < 1 or camera_center.shape[-1] != 3:
        raise ValueError(f"camera_center: expected shape (3,) or (*, 3), got "
                         f"{tuple(camera_center.shape)}")
    check_finite(positions, "positions")
    check_finite(camera_center, "camera_center")
    c = camera_center.to(positions.dtype)
    batch = torch.broadcast_shapes(positions.shape[:-2], c.shape[:-1])
    X = positions.expand(*batch, K + 1, 3)
    c = c.expand(*batch, 3)
    ray = X[..., 1:, :] - c[..., None, :]  # (*, K, 3)
    depth0 = ray.norm(dim=-1)  # original depths along the rays
    if ray.numel() and not bool((depth0 > 0).all()):
        raise ValueError("positions: a joint coincides with camera_center (no camera ray)")
    d = ray / depth0[..., None]
    bone = X[..., 1:, :] - X[..., :-1, :]
    L = bone.norm(dim=-1)  # (*, K)
    far = (d * bone).sum(-1) >= 0  # original child beyond the closest approach to its parent

    nodes = X[..., None, :1, :]  # (*, N=1, 1, 3)
    valid = torch.ones(*batch, 1, dtype=torch.bool, device=X.device)
    for k in range(K):
        parent = nodes[..., k, :]  # (*, N, 3)
        anchor = X[..., None, k + 1, :]  # (*, 1, 3) the original child, a point on its ray
        dk = d[..., None, k, :]
        delta, t = ray_sphere_discriminant(anchor, dk, parent, L[..., None, k])
        root = _safe_sqrt(delta)
        fk = far[..., None, k]
        lam_same = torch.where(fk, t + root, t - root)  # (*, N)
        lam_other = torch.where(fk, t - root, t + root)
        hit = delta >= 0
        # the unmoved parent (node 0): the original child exactly, and its reflection
        t0 = t[..., 0]
        lam_same = torch.cat([torch.zeros_like(t0)[..., None], lam_same[..., 1:]], -1)
        lam_other = torch.cat([(2 * t0)[..., None], lam_other[..., 1:]], -1)
        hit = torch.cat([torch.ones_like(hit[..., :1]), hit[..., 1:]], -1)
        lam = torch.cat([lam_same, lam_other], -1)  # (*, 2N): bit k = 0 then 1
        child = anchor + lam[..., None] * dk
        in_front = depth0[..., None, k] + lam > 0
        hit2 = torch.cat([hit, hit], -1)
        valid = torch.cat([valid, valid], -1) & hit2 & in_front
        nodes = torch.cat([nodes, nodes], -3)
        nodes = torch.cat([nodes, child[..., None, :]], -2)  # (*, 2N, k+2, 3)
    return InterpretationTree(nodes, valid, flip_patterns(K, X.device))
