"""Plate registration: known warps of a real picture are recovered (affine and gain/offset),
also with an occluding outlier; the real plates of cam01/cam02 are scaled by 1088/1080."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.recordings.masks import register_images, warp_images


@pytest.fixture(scope="module")
def picture(pose2sim_plates):
    """A real grey picture (cam03's plate, 1/4 size: 480 x 272)."""
    x = pose2sim_plates[2].permute(2, 0, 1)[None].float()
    x = torch.nn.functional.interpolate(x, size=(480, 272), mode="area")
    return x[0].mean(0)


class TestWarpImages:
    def test_feature_identity_and_shift(self, picture):
        eye = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=torch.float64)
        out, inside = warp_images(picture[None, None], eye, (480, 272))
        torch.testing.assert_close(out[0, 0], picture, atol=5e-3, rtol=0)
        assert bool(inside.all())
        shift = eye.clone()
        shift[0, 0, 2] = 3.0  # output pixel x takes the image at x + 3
        out, inside = warp_images(picture[None, None], shift, (480, 272))
        torch.testing.assert_close(out[0, 0, :, :200], picture[:, 3:203], atol=5e-3, rtol=0)
        assert not bool(inside[0, :, -3:].any()) and bool(inside[0, :, :268].all())


class TestRegisterImages:
    def test_smoke(self, picture):
        out = register_images(picture[None], picture[None], torch.ones(1, 480, 272,
                                                                     dtype=torch.bool))
        assert out["affine"].shape == (1, 2, 3) and out["gain"].shape == (1,)
        torch.testing.assert_close(out["affine"][0], torch.eye(2, 3, dtype=torch.float64),
                                   atol=1e-4, rtol=0)

    @pytest.mark.parametrize("occlude", [False, True])
    def test_feature_recovers_known_warp(self, picture, occlude):
        """template = 1.1 · image(A x) + 5 (image larger than the template by a crop);
        a grey block over 15 % of the template is an outlier that must not bias the fit."""
        A = torch.tensor([[[1.008, 0.002, 1.3], [-0.003, 0.994, -0.8]]], dtype=torch.float64)
        warped, _ = warp_images(picture[None, None], A, (470, 262))
        template = warped[:, 0] * 1.1 + 5.0
        valid = torch.ones(1, 470, 262, dtype=torch.bool)
        valid[:, -2:] = valid[:, :, -2:] = False  # samples near the image's edge
        if occlude:
            template[:, 100:250, 60:170] = 128.0
        out = register_images(template, picture[None], valid)
        corners = torch.tensor([[0.0, 0.0, 1.0], [261.0, 469.0, 1.0]], dtype=torch.float64)
        err = (corners @ (out["affine"][0] - A[0]).T).norm(dim=-1).max()
        assert float(err) < 0.05  # pixels, at the corners
        assert float(out["gain"][0]) == pytest.approx(1.1, abs=5e-3)
        assert float(out["offset"][0]) == pytest.approx(5.0, abs=1.0)
        if occlude:
            assert 0.75 < float(out["inliers"][0]) < 0.95
