"""A joint's own body parts (never occluders of the joint)."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body.parts import own_parts
from torchmocap.skeleton import human31


def test_feature_human31_elbow_and_hips():
    sk = human31()
    own = own_parts(sk.parents)
    i = sk.joint_index
    # the elbow sits in its upper arm (carried by the shoulder) and its forearm (its own)
    assert bool(own[i("l_elbow"), i("l_shoulder")]) and bool(own[i("l_elbow"), i("l_elbow")])
    # ... and is never "its own" for the other arm or the legs
    for other in ("r_shoulder", "r_elbow", "l_hip", "l_knee", "r_knee"):
        assert not bool(own[i("l_elbow"), i(other)])
    # the root owns its children's parts (the hips, the spine)
    for child in ("l_hip", "r_hip", "spine"):
        assert bool(own[i("pelvis"), i(child)])
    assert bool(own.diagonal().all())


def test_feature_matches_a_brute_force_definition():
    g = torch.Generator().manual_seed(3)
    for _ in range(5):  # random trees, parents before children
        J = 12
        parents = [-1] + [int(torch.randint(0, j, (1,), generator=g)) for j in range(1, J)]
        own = own_parts(parents)
        for j in range(J):
            anc = [j]
            while parents[anc[-1]] >= 0 and len(anc) < 3:
                anc.append(parents[anc[-1]])
            want = set(anc) | {k for k in range(J) if parents[k] == j}
            assert {k for k in range(J) if own[j, k]} == want


def test_exception():
    with pytest.raises(ValueError, match="parents"):
        own_parts([-1, 0, 5])
    with pytest.raises(ValueError, match="parents"):
        own_parts([-1, 1])
