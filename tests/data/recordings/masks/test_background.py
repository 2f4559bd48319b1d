"""Background model: the median where the plate agrees, the registered and gain-corrected plate
where it does not (a subject standing still), the median again where the plate has its own
clutter away from the subject."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.recordings.masks import (
    BackgroundModel,
    MaskSettings,
    estimate_background,
    warp_images,
)
from torchmocap.data.recordings.masks.background import robust_sigma

H, W, T = 60, 80, 9
SUBJECT = (slice(15, 45), slice(20, 35))  # rows, columns: stands still in every frame
GHOST = (slice(4, 14), slice(55, 75))  # an object in the plate only


def _texture(seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, 8, 10, generator=g, dtype=torch.float64)
    x = torch.nn.functional.interpolate(x, size=(H, W), mode="bicubic", align_corners=False)
    return (40 + 170 * x[0]).clamp(0, 255)


def _scene():
    g = torch.Generator().manual_seed(1)
    B = _texture()
    frames = B.expand(T, 3, H, W) + 1.5 * torch.randn(T, 3, H, W, generator=g,
                                                     dtype=torch.float64)
    frames[:, :, SUBJECT[0], SUBJECT[1]] = torch.tensor([200.0, 40, 40])[:, None, None]
    for t in range(3):  # something passing by in a minority of frames
        frames[t, :, 45:55, 10 + 20 * t:25 + 20 * t] = 250.0
    frames = frames.round().clamp(0, 255).to(torch.uint8)[:, None]  # (T, 1, 3, H, W)
    # the plate: shifted 0.7 px to the right, brighter, noisy, with its own object
    shift = torch.tensor([[[1.0, 0.0, -0.7], [0.0, 1.0, 0.0]]], dtype=torch.float64)
    plate = warp_images(B[None].float(), shift, (H, W))[0][0].double()
    plate[:, :, 0] = plate[:, :, 1]  # the warp's empty first column
    plate = 1.05 * plate - 3 + 1.5 * torch.randn(3, H, W, generator=g, dtype=torch.float64)
    plate[:, GHOST[0], GHOST[1]] = torch.tensor([30.0, 60, 220])[:, None, None]
    return B, frames, plate.clamp(0, 255).float()


def _keypoints():
    """A 'person' of keypoints along the subject block's outline, in every frame."""
    pts = [(20, 15), (34, 15), (27, 22), (20, 30), (34, 30), (22, 44), (32, 44), (27, 36)]
    kp = torch.tensor([[u, v, 0.9] for u, v in pts], dtype=torch.float64)
    return kp.expand(T, 1, len(pts), 3)


VALID = torch.ones(1, H, W, dtype=torch.bool)


class TestEstimateBackground:
    def test_smoke(self):
        _, frames, _ = _scene()
        bg = estimate_background(frames, VALID, None, MaskSettings())
        assert isinstance(bg, BackgroundModel)
        assert bg.colour.shape == (1, 3, H, W) and bg.noise.shape == (1, H, W)
        assert not bool(bg.from_plate.any()) and bg.info[0]["plate"] is False
        # median only: the still subject is part of the background
        assert float((bg.colour[0, 0, SUBJECT[0], SUBJECT[1]] - 200).abs().max()) < 2

    def test_feature_plate_where_median_disagrees(self):
        B, frames, plate = _scene()
        bg = estimate_background(frames, VALID, [plate], MaskSettings(plate_near_subject=False))
        info = bg.info[0]
        A = torch.tensor(info["registration"])
        assert float((A - torch.tensor([[1.0, 0, 0.7], [0, 1, 0]])).abs().max()) < 0.1
        assert info["gain"] == pytest.approx([1 / 1.05] * 3, abs=0.02)
        assert 1.0 < info["noise_plate"] < 4.0
        inner = (slice(18, 42), slice(23, 32))
        assert bool(bg.from_plate[0, inner[0], inner[1]].all())
        # behind the subject the corrected plate shows the true background
        err = (bg.colour[0, :, inner[0], inner[1]] - B[:, inner[0], inner[1]]).abs()
        assert float(err.mean()) < 2.0
        # the plate's own object is taken for background (what the multi-view check is for)
        assert bool(bg.from_plate[0, GHOST[0], GHOST[1]].all())
        # elsewhere the median (not the moving object) is used
        assert float(bg.from_plate[0].double().mean()) < 0.3
        assert float((bg.colour[0, :, 47:53, 12:60] - B[:, 47:53, 12:60]).abs().mean()) < 2.0

    def test_feature_plate_only_near_the_subject(self):
        B, frames, plate = _scene()
        bg = estimate_background(frames, VALID, [plate], MaskSettings(), _keypoints())
        assert bool(bg.from_plate[0, 18:42, 23:32].all())
        assert not bool(bg.from_plate[0, GHOST[0], GHOST[1]].any())
        assert float((bg.colour[0, :, GHOST[0], GHOST[1]] - B[:, GHOST[0], GHOST[1]]).abs()
                     .mean()) < 2.0
        assert bg.info[0]["plate_outside_subject"] > 0.02

    def test_feature_rejected_registration(self):
        """A plate that would need a large warp is used as it is, and the report says so."""
        _, frames, plate = _scene()
        bg = estimate_background(frames, VALID, [plate], MaskSettings(max_plate_motion=0.001))
        assert bg.info[0]["registration"] == "rejected"


def test_robust_sigma():
    g = torch.Generator().manual_seed(0)
    x = 3.0 * torch.randn(2, 100_000, generator=g)
    x[:, :10_000] = 200.0  # 10 % outliers
    s = robust_sigma(x + 10)
    assert float((s - 3.0).abs().max()) < 0.6  # biased up by the outliers, not ruined
    assert float(robust_sigma(x[:, 20_000:])[0]) == pytest.approx(3.0, rel=0.02)
