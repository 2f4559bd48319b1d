"""Mask preview: tints, keypoints, padding and the grid layout; the PNG is written atomically."""

from __future__ import annotations

import numpy as np
import torch

from torchmocap.data.recordings.masks import mask_preview, write_mask_preview


def _inputs(C=3, H=20, W=30):
    images = torch.full((C, H, W, 3), 100, dtype=torch.uint8)
    masks = torch.zeros(C, H, W, dtype=torch.bool)
    masks[:, 5:10, 5:10] = True
    removed = torch.zeros(C, H, W, dtype=torch.bool)
    removed[:, 12:15, 20:25] = True
    return images, masks, removed


class TestMaskPreview:
    def test_cardinality(self):
        images, masks, removed = _inputs()
        assert mask_preview(images, masks).shape == (20, 3 * 30 + 2 * 4, 3)
        assert mask_preview(images, masks, columns=2).shape == (2 * 20 + 4, 2 * 30 + 4, 3)

    def test_feature_colours(self):
        images, masks, removed = _inputs()
        kp = torch.tensor([[[25.0, 3.0, 0.9], [2.0, 2.0, 0.1]]] * 3)
        sizes = torch.tensor([[30, 20], [30, 20], [26, 20]])  # view 2 is 26 px wide
        g = mask_preview(images, masks, removed, sizes, kp).astype(int)
        kept, gone, rest = g[7, 7], g[13, 22], g[0, 15]
        assert kept[1] > kept[0] + 50 and kept[1] > kept[2] + 50  # green
        assert gone[0] > gone[1] + 50 and gone[2] > gone[1] + 50  # magenta
        assert (rest == 60).all()  # dimmed image
        assert g[3, 25].tolist() == [255, 230, 0]  # a confident keypoint
        assert g[2, 2].tolist() == [60, 60, 60]  # a low-confidence one is not drawn
        x2 = 2 * (30 + 4)
        assert (g[:, x2 + 26:x2 + 30] == 0).all()  # padding of the narrower view

    def test_feature_write(self, tmp_path):
        from PIL import Image

        images, masks, removed = _inputs()
        path = write_mask_preview(tmp_path / "sub" / "p.png", images, masks, removed)
        with Image.open(path) as im:
            assert np.array_equal(np.asarray(im), mask_preview(images, masks, removed))
        assert [p.name for p in path.parent.iterdir()] == ["p.png"]
