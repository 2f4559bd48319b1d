"""Resampling of views of different sizes to the working resolution."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchmocap.data.recordings.masks.inputs import resize_views


def test_feature_resize_views():
    g = torch.Generator().manual_seed(0)
    images = torch.zeros(2, 2, 40, 64, 3, dtype=torch.uint8)
    images[:, 0] = torch.randint(0, 256, (2, 40, 64, 3), generator=g, dtype=torch.uint8)
    images[:, 1, :, :56] = torch.randint(0, 256, (2, 40, 56, 3), generator=g, dtype=torch.uint8)
    sizes = torch.tensor([[64, 40], [56, 40]])
    out = resize_views(images, sizes, torch.tensor([[32, 20], [28, 20]]))
    assert out.shape == (2, 2, 3, 20, 32) and out.dtype == torch.uint8
    assert not bool(out[:, 1, :, :, 28:].any())  # padding of the narrower view
    # a factor-2 antialiased bilinear reduction is the 2x2 (well, 4x4 tent) average
    want = F.interpolate(images[:, 1, :, :56].permute(0, 3, 1, 2).double(), size=(20, 28),
                         mode="bilinear", antialias=True, align_corners=False)
    assert float((out[:, 1, :, :, :28].double() - want).abs().max()) <= 1.0
    same = resize_views(images, sizes, sizes)
    assert torch.equal(same.permute(0, 1, 3, 4, 2), images)
