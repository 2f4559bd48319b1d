"""Regions of interest: boxes to crops (closed forms, margins, clipping), keypoints and masks of
a crop back in the full image (round trips against the pixels themselves), and errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmocap.detectors import (
    DetectorInputError,
    box_to_region,
    check_box,
    crop_image,
    keypoint_box,
    paste_region,
    region_to_image,
)


class TestBoxToRegion:
    def test_feature_closed_form(self):
        # pixel i covers [i - 0.5, i + 0.5): a box from 10.0 to 20.0 touches pixels 10..20
        assert box_to_region((10.0, 5.0, 20.0, 8.0), (640, 480)) == (10, 5, 21, 9)
        assert box_to_region((9.6, 4.4, 20.4, 8.6), (640, 480)) == (10, 4, 21, 10)
        # a margin of 0.5 widens a 100 x 200 box by 50 and 100 pixels on each side
        assert box_to_region((100.0, 100.0, 200.0, 300.0), (640, 480), margin=0.5) == \
            (50, 0, 251, 401)

    def test_feature_clipped_and_outside(self):
        assert box_to_region((-50.0, -20.0, 700.0, 900.0), (640, 480)) == (0, 0, 640, 480)
        assert box_to_region((-50.0, 10.0, -1.0, 20.0), (640, 480)) is None
        assert box_to_region((650.0, 10.0, 700.0, 20.0), (640, 480)) is None

    def test_exception(self):
        with pytest.raises(DetectorInputError, match=r"box: expected u_min < u_max"):
            box_to_region((20.0, 5.0, 10.0, 8.0), (640, 480))
        with pytest.raises(DetectorInputError, match=r"box: expected 4 finite numbers"):
            box_to_region((1.0, 2.0, float("nan"), 8.0), (640, 480))
        with pytest.raises(DetectorInputError, match=r"box: expected 4 finite"):
            check_box([1.0, 2.0, 3.0])
        with pytest.raises(DetectorInputError, match=r"box: expected \(u_min"):
            check_box("abcd")
        with pytest.raises(DetectorInputError, match=r"margin: expected a fraction"):
            box_to_region((1.0, 2.0, 3.0, 4.0), (640, 480), margin=-0.1)
        with pytest.raises(DetectorInputError, match=r"size: expected a positive"):
            box_to_region((1.0, 2.0, 3.0, 4.0), (0, 480))


class TestCropAndBack:
    def test_feature_round_trip_on_pixels(self):
        """A pixel found at (u, v) in the crop is the image's pixel (u + x0, v + y0); a mask of
        the crop pasted back covers exactly the region."""
        g = torch.Generator().manual_seed(0)
        image = torch.randint(0, 256, (120, 160, 3), generator=g, dtype=torch.uint8).numpy()
        region = box_to_region((30.2, 40.7, 90.1, 100.0), (160, 120), margin=0.1)
        crop = crop_image(image, region)
        assert crop.shape == (region[3] - region[1], region[2] - region[0], 3)
        assert np.shares_memory(crop, image)  # a view
        pts = torch.tensor([[3.0, 7.0, 0.8], [0.0, 0.0, 1.0],
                            [crop.shape[1] - 1.0, crop.shape[0] - 1.0, 0.5]])
        full = region_to_image(pts, region)
        for (u, v, c), (U, V, C) in zip(pts.tolist(), full.tolist()):
            assert (C == c) and (crop[int(v), int(u)] == image[int(V), int(U)]).all()
        mask = paste_region(torch.ones(crop.shape[:2]), region, (160, 120))
        x0, y0, x1, y1 = region
        assert mask.shape == (120, 160) and float(mask.sum()) == (x1 - x0) * (y1 - y0)
        assert bool((mask[y0:y1, x0:x1] == 1).all())

    def test_cardinality(self):
        x = torch.zeros(2, 5, 33, 3, dtype=torch.float64)
        y = region_to_image(x, (4, 6, 10, 12))
        assert y.shape == x.shape and y.dtype == torch.float64
        assert bool((y[..., 0] == 4).all() and (y[..., 1] == 6).all() and (y[..., 2] == 0).all())
        assert region_to_image(x[..., :2], None) is not None
        assert paste_region(torch.zeros(3, 4), None, (4, 3)).shape == (3, 4)

    def test_exception(self):
        img = np.zeros((10, 20, 3), np.uint8)
        with pytest.raises(DetectorInputError, match=r"region: expected 0 <= x0 < x1 <= 20"):
            crop_image(img, (0, 0, 21, 5))
        with pytest.raises(DetectorInputError, match=r"region: expected integer pixel ranges"):
            crop_image(img, (0.5, 0, 10, 5))
        with pytest.raises(DetectorInputError, match=r"keypoints: expected shape"):
            region_to_image(torch.zeros(33, 4), (0, 0, 5, 5))
        with pytest.raises(DetectorInputError, match=r"crop: expected shape \(5, 5\)"):
            paste_region(torch.zeros(4, 5), (0, 0, 5, 5), (20, 10))
        with pytest.raises(DetectorInputError, match=r"crop: expected shape \(10, 20\)"):
            paste_region(torch.zeros(4, 5), None, (20, 10))


class TestKeypointBox:
    def test_feature(self):
        kp = torch.tensor([[10.0, 50.0, 0.9], [30.0, 20.0, 0.8], [500.0, 900.0, 0.05],
                           [20.0, 80.0, 0.7]], dtype=torch.float64)
        assert keypoint_box(kp, 0.1) == (10.0, 20.0, 30.0, 80.0)
        assert keypoint_box(kp[None], 0.1) == (10.0, 20.0, 30.0, 80.0)  # one person (1, K, 3)
        assert keypoint_box(kp, 0.85) is None  # a single keypoint spans no box
        assert keypoint_box(torch.zeros(25, 3)) is None  # nothing detected

    def test_exception(self):
        with pytest.raises(DetectorInputError, match=r"keypoints: expected shape \(K, 3\)"):
            keypoint_box(torch.zeros(2, 25, 3))
