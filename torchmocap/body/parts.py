"""Which body parts belong to a joint (for occlusion tests).

A body part is the surface carried by one joint's frame (the segment from the joint to its
children). A joint sits inside or on the surface of its own parts, so they never hide it:
the parts of the joint itself, of its parent and grandparent (a skinned mesh may hang the skull
on the neck's frame, and the end site at the top of the head must not be hidden by it), and of
its children.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["own_parts"]


def own_parts(parents: Sequence[int]) -> Tensor:
    """``(J, J)`` bool: ``own[j, k]`` when the part carried by joint ``k`` is one of joint
    ``j``'s own (module docstring).

    Args:
        parents: ``J`` parent indices (``-1`` for a root), parents before children or not.

    Example:
        >>> own_parts([-1, 0, 1, 2]).int()        # a chain: root, a, b, c
        tensor([[1, 1, 0, 0],
                [1, 1, 1, 0],
                [1, 1, 1, 1],
                [0, 1, 1, 1]], dtype=torch.int32)
    """
    par = [int(p) for p in parents]
    J = len(par)
    if any(p < -1 or p >= J or p == j for j, p in enumerate(par)):
        raise ValueError(f"parents: expected indices in [-1, {J}) other than the joint's own, "
                         f"got {par}")
    own = torch.zeros(J, J, dtype=torch.bool)
    for j in range(J):
        k = j
        for _ in range(3):  # the joint, its parent, its grandparent
            own[j, k] = True
            k = par[k]
            if k < 0:
                break
        if par[j] >= 0:
            own[par[j], j] = True  # a joint's children's parts are its own too
    return own
