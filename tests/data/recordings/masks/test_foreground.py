"""Shadow-robust colour difference: closed forms of the decomposition, and the masks it gives."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.recordings.masks import (
    BackgroundModel,
    MaskSettings,
    clean_masks,
    colour_distortion,
    foreground_masks,
)


def _background(H=40, W=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    return 60 + 150 * torch.rand(1, 3, H, W, generator=g, dtype=torch.float64)


class TestColourDistortion:
    def test_smoke(self):
        a, cd, db = colour_distortion(torch.zeros(2, 3, 4, 5, dtype=torch.uint8),
                                      torch.ones(3, 4, 5))
        assert a.shape == cd.shape == db.shape == (2, 4, 5) and a.dtype == torch.float32

    def test_feature_closed_forms(self):
        B = _background().float()
        # a shadow keeps the chromaticity: alpha is the darkening, no chromatic distortion
        a, cd, db = colour_distortion(0.55 * B, B)
        torch.testing.assert_close(a, torch.full_like(a, 0.55))
        assert float(cd.max()) < 0.05
        torch.testing.assert_close(db, -0.45 * B.norm(dim=1), rtol=1e-5, atol=1e-3)
        # adding a colour orthogonal to B leaves alpha at 1 and the distortion is its length
        n = torch.randn(B.shape, generator=torch.Generator().manual_seed(1))
        n = n - (n * B).sum(1, keepdim=True) / (B * B).sum(1, keepdim=True) * B
        a, cd, _ = colour_distortion(B + n, B)
        torch.testing.assert_close(a, torch.ones_like(a), atol=1e-5, rtol=0)
        torch.testing.assert_close(cd, n.norm(dim=1), atol=2e-3, rtol=1e-4)

    def test_gradcheck(self):
        B = _background(4, 5).requires_grad_()
        I = (_background(4, 5, seed=2)).requires_grad_()
        assert torch.autograd.gradcheck(lambda i, b: colour_distortion(i, b)[1:], (I, B))


class TestForegroundMasks:
    def _scene(self):
        B = _background(60, 80).float()[0]
        frame = B.clone()
        frame[:, 10:50, 5:30] *= 0.6  # a shadow
        frame[:, 20:40, 45:70] = torch.tensor([200.0, 30.0, 30.0])[:, None, None]  # a red thing
        frame[:, 5:8, 60:63] = torch.tensor([20.0, 200.0, 20.0])[:, None, None]  # a speck
        bg = BackgroundModel(B[None], torch.full((1, 60, 80), 2.0),
                             torch.zeros(1, 60, 80, dtype=torch.bool), [])
        return frame[None, None], bg

    def test_feature_shadow_is_background(self):
        frame, bg = self._scene()
        fg = foreground_masks(frame, bg, MaskSettings())[0, 0]
        assert not bool(fg[10:50, 5:30].any())
        assert bool(fg[20:40, 45:70].all())
        # a deeper shadow than shadow_min allows is foreground
        deep = foreground_masks(frame, bg, MaskSettings(shadow_min=0.7))[0, 0]
        assert bool(deep[10:50, 5:30].all())

    def test_feature_cleanup(self):
        frame, bg = self._scene()
        frame[0, 0, :, 28:32, 55:60] = bg.colour[0, :, 28:32, 55:60]  # a hole in the red thing
        st = MaskSettings(open_size=0.04, close_size=0.0, min_area=0.001)
        valid = torch.ones(1, 60, 80, dtype=torch.bool)
        raw = foreground_masks(frame, bg, st)
        assert not bool(raw[0, 0, 28:32, 55:60].any()) and bool(raw[0, 0, 5:8, 60:63].all())
        clean = clean_masks(raw, valid, st)[0, 0]
        assert bool(clean[20:40, 45:70].all())  # hole filled
        assert not bool(clean[:15].any())  # the 3x3 speck is opened away
        valid[0, :, 60:] = False  # a smaller view: nothing outside it
        assert not bool(clean_masks(raw, valid, st)[0, 0, :, 60:].any())

    @pytest.mark.parametrize("noise", [1.0, 4.0])
    def test_feature_threshold_scales_with_noise(self, noise):
        """False positives on pure noise stay rare when the model's noise matches the data's."""
        B = _background(100, 100).float()[0]
        g = torch.Generator().manual_seed(3)
        frame = (B + noise * torch.randn(B.shape, generator=g)).clamp(0, 255)
        bg = BackgroundModel(B[None], torch.full((1, 100, 100), noise),
                             torch.zeros(1, 100, 100, dtype=torch.bool), [])
        fg = foreground_masks(frame[None, None], bg, MaskSettings())
        assert float(fg.double().mean()) < 2e-3
