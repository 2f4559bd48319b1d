"""Binary morphology against scipy.ndimage (an independent implementation)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from torchmocap.data.recordings.masks.morphology import (
    closing,
    dilate,
    drop_small_components,
    erode,
    fill_holes,
    opening,
)


def _masks(density=0.2, shape=(6, 37, 53), seed=0):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed)) < density


def _square(r):
    s = np.zeros((3, 2 * r + 1, 2 * r + 1), dtype=bool)
    s[1] = True
    return s


class TestMorphology:
    def test_smoke(self):
        m = _masks()
        for fn in (dilate, erode, opening, closing):
            assert fn(m, 2).shape == m.shape and fn(m, 2).dtype == torch.bool
        assert torch.equal(dilate(m, 0), m) and torch.equal(erode(m, 0), m)

    @pytest.mark.parametrize("r", [1, 2, 5])
    def test_feature_matches_scipy(self, r):
        m = _masks(0.3)
        a = m.numpy()
        assert np.array_equal(dilate(m, r).numpy(), ndimage.binary_dilation(a, _square(r)))
        # the border does not erode: outside counts as foreground
        assert np.array_equal(erode(m, r).numpy(),
                              ndimage.binary_erosion(a, _square(r), border_value=1))
        o = ndimage.binary_dilation(ndimage.binary_erosion(a, _square(r), border_value=1),
                                    _square(r))
        assert np.array_equal(opening(m, r).numpy(), o)
        c = ndimage.binary_erosion(ndimage.binary_dilation(a, _square(r)), _square(r),
                                   border_value=1)
        assert np.array_equal(closing(m, r).numpy(), c)

    def test_feature_fill_holes(self):
        m = _masks(0.45)
        want = np.stack([ndimage.binary_fill_holes(x) for x in m.numpy()])
        assert np.array_equal(fill_holes(m).numpy(), want)
        ring = torch.zeros(2, 9, 9, dtype=torch.bool)
        ring[0, 2:7, 2:7] = True
        ring[0, 3:6, 3:6] = False
        ring[1, 0:5, 0:5] = True  # an open ring on the border: its inside reaches the border
        ring[1, 0:4, 0:4] = False
        out = fill_holes(ring)
        assert bool(out[0, 2:7, 2:7].all()) and int(out[1].sum()) == int(ring[1].sum())

    def test_feature_drop_small_components(self):
        m = _masks(0.25)
        labels, n = ndimage.label(m.numpy(), _square(1))
        sizes = np.bincount(labels.ravel())
        want = (sizes >= 4)[labels] & (labels > 0)
        assert np.array_equal(drop_small_components(m, 4).numpy(), want)
        assert torch.equal(drop_small_components(m, 1), m)
        # components are per image: the same pixels in two images are two components
        two = torch.zeros(2, 5, 5, dtype=torch.bool)
        two[:, 1:3, 1:3] = True
        assert not bool(drop_small_components(two, 5).any())
