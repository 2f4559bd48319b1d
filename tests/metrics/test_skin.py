"""Eq. 16 of Hauberg & Pedersen: marker-to-skin distances against closed forms."""

from __future__ import annotations

import pytest
import torch

from torchmocap.metrics import marker_skin_distance


def test_closed_form_two_capsules():
    # capsule 0: axis (0,0,0)-(0,0,1), r = 0.1; capsule 1: axis (1,0,0)-(2,0,0), r = 0.2
    ends = torch.tensor([[[[0.0, 0, 0], [0, 0, 1]], [[1.0, 0, 0], [2, 0, 0]]]],
                        dtype=torch.float64)
    radii = torch.tensor([0.1, 0.2], dtype=torch.float64)
    markers = torch.tensor([[[0.1, 0, 0.5],        # on the skin of 0
                             [0.5, 0, 0.5],        # 0.4 outside 0 (1 is farther)
                             [0.0, 0, 0.5],        # on the axis of 0: 0.1 inside
                             [1.5, 0.5, 0],        # 0.3 outside 1
                             [0.0, 0, 1.3]]],      # beyond the cap of 0: 0.2
                           dtype=torch.float64)
    d = marker_skin_distance(markers, ends, radii)
    # (on the axis the distance is smoothed by 1e-6 so that its gradient exists)
    torch.testing.assert_close(d, torch.tensor([[0.0, 0.4, 0.1, 0.3, 0.2]], dtype=torch.float64),
                               atol=2e-6, rtol=0)
    # frames are independent: moving frame 1's body moves only its distances
    two = marker_skin_distance(markers.expand(2, -1, -1),
                               torch.cat([ends, ends + torch.tensor([0.0, 0, 0.05])]), radii)
    torch.testing.assert_close(two[0], d[0])
    assert not torch.allclose(two[1], d[0])


def test_exception():
    ends = torch.zeros(2, 1, 2, 3)
    with pytest.raises(ValueError, match="markers: expected shape"):
        marker_skin_distance(torch.zeros(2, 3), ends, torch.ones(1))
    with pytest.raises(ValueError, match="endpoints: expected 3 frames"):
        marker_skin_distance(torch.zeros(3, 4, 3), ends, torch.ones(1))
