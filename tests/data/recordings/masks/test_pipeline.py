"""``compute_masks`` on real frames (pose2sim_balancing, four views), and on small synthetic
inputs for the argument checks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchmocap.cameras import make_ring_rig
from torchmocap.data.recordings.masks import (
    MaskError,
    MaskSettings,
    cached_masks,
    clean_masks,
    compute_masks,
    content_key,
    estimate_background,
    foreground_masks,
    hull_filter,
    hull_regions,
    working_images,
    working_sizes,
)
from torchmocap.data.recordings.masks.inputs import resize_views

SCALE = 0.25


def _hits(mask: torch.Tensor, points: np.ndarray, scale: float = SCALE) -> np.ndarray:
    """Whether full-resolution pixels ``points (N, 2)`` fall inside ``mask (h, w)`` (pixels
    outside the image count as outside)."""
    h, w = mask.shape
    uv = np.round((np.asarray(points) + 0.5) * scale - 0.5).astype(int)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    out = np.zeros(len(uv), dtype=bool)
    out[ok] = mask.numpy()[uv[ok, 1], uv[ok, 0]]
    return out


def _subject_rate(masks, keypoints) -> float:
    hits = [_hits(masks[t, c], keypoints[t, c][keypoints[t, c, :, 2] >= 0.3, :2].numpy())
            for t in range(masks.shape[0]) for c in range(masks.shape[1])]
    return float(np.concatenate(hits).mean())


def _bystander_hits(masks, bystander) -> np.ndarray:
    return np.concatenate([_hits(masks[t, c], bystander[t][c])
                           for t in range(masks.shape[0]) for c in range(masks.shape[1])])


@pytest.fixture(scope="module")
def real(pose2sim_frames, pose2sim_rig, pose2sim_plates, pose2sim_keypoints):
    """Default masks of the real frames at scale 0.25, and the report."""
    images, _ = pose2sim_frames
    return compute_masks(images, pose2sim_rig, pose2sim_plates, pose2sim_keypoints,
                         {"scale": SCALE})


class TestRealRecording:
    def test_cardinality(self, real, pose2sim_frames, pose2sim_rig):
        masks, report = real
        T, C = pose2sim_frames[0].shape[:2]
        assert masks.shape == (T, C, 480, 272) and masks.dtype == torch.bool
        assert report["working_sizes"] == [[270, 480], [270, 480], [272, 480], [272, 480]]
        # cam01/cam02 decode 1080 wide: their last two working columns are padding
        assert not bool(masks[:, :2, :, 270:].any())
        json.dumps(report)  # JSON-safe
        seen = working_images(pose2sim_frames[0][:1], pose2sim_rig, SCALE)
        assert seen.shape == (1, C, 480, 272, 3) and seen.dtype == torch.uint8
        assert not bool(seen[:, :2, :, 270:].any()) and bool(seen[:, 2:, :, 270:].any())

    def test_feature_masks_cover_the_subject(self, real, pose2sim_keypoints):
        """Every view has a subject-sized mask (not empty, not the whole image), and the
        subject's detected keypoints fall inside it (measured 93.5 % at scale 0.25; the
        misses are extremities on the mask's edge and a nose the detector wrote at u = 0)."""
        masks, report = real
        frac = masks.flatten(2).double().mean(-1)  # (T, C)
        assert bool((frac > 0.02).all()) and bool((frac < 0.2).all()), frac
        assert _subject_rate(masks, pose2sim_keypoints) > 0.88
        assert report["multiview"]["empty_frames"] == []
        assert report["multiview"]["bounds_from"] == ["keypoints"]

    def test_feature_bystander_is_not_foreground(self, real, pose2sim_bystander):
        """The woman behind the treadmill (raw detections of cam01/cam02) is not in the
        masks: measured 1.0 % of her 298 confident keypoints inside (none in cam01)."""
        hits = _bystander_hits(real[0], pose2sim_bystander)
        assert hits.size > 150
        assert hits.mean() < 0.1

    def test_feature_multiview_check_removes_the_bystander(
            self, pose2sim_frames, pose2sim_rig, pose2sim_plates, pose2sim_keypoints,
            pose2sim_bystander):
        """With the plate used wherever it disagrees with the median (the plates' own people
        are then foreground too), the bystander is in the masks before the multi-view check
        (measured 90 % of her keypoints inside) and mostly gone after it (7 % left: none in
        cam01, 17 % in cam02 where she stands right beside the subject and a plate's person
        stood there too), while the subject stays (94 % before, 93.5 % after)."""
        images, sizes = pose2sim_frames
        st = MaskSettings(scale=SCALE, plate_near_subject=False)
        out = working_sizes(sizes, SCALE)
        frames = resize_views(images, sizes, out)
        h, w = frames.shape[-2:]
        valid = (torch.arange(w)[None, None] < out[:, 0, None, None]) & \
            (torch.arange(h)[None, :, None] < out[:, 1, None, None])
        plates = [resize_views(p[None, None], torch.tensor([[1088, 1920]]), torch.tensor(
            [[round(1088 * float(out[c, 0] / sizes[c, 0])), 480]]))[0, 0].float()
                  for c, p in enumerate(pose2sim_plates)]
        kp = pose2sim_keypoints.clone()
        kp[..., :2] = (kp[..., :2] + 0.5) * SCALE - 0.5
        fg = clean_masks(foreground_masks(frames, estimate_background(frames, valid, plates, st),
                                          st), valid, st)
        rig = pose2sim_rig.scaled_images(SCALE)
        bounds, skeletons, _ = hull_regions(rig, kp, st)
        after, info = hull_filter(fg, rig, bounds, st, skeletons)
        before_hits = _bystander_hits(fg, pose2sim_bystander)
        after_hits = _bystander_hits(after, pose2sim_bystander)
        assert before_hits.mean() > 0.75
        assert after_hits.mean() < 0.2
        assert info["min_views"] == 3
        assert _subject_rate(after, pose2sim_keypoints) > 0.88

    def test_feature_plates_are_registered(self, real):
        """cam01/cam02's videos are the calibration's 1088-wide images scaled by 1080/1088 (not
        cropped): registration finds that scale; cam03/cam04 need no warp."""
        bg = real[1]["background"]
        for c in (0, 1):
            A = np.array(bg[c]["registration"])
            assert A[0, 0] == pytest.approx(1088 / 1080, abs=2e-3)
            assert A[1, 1] == pytest.approx(1088 / 1080, abs=2e-3)
        for c in (2, 3):
            A = np.array(bg[c]["registration"])
            assert np.abs(A[:, :2] - np.eye(2)).max() < 1e-3 and np.abs(A[:, 2]).max() < 0.1

    def test_feature_cache(self, tmp_path, pose2sim_frames, pose2sim_rig, pose2sim_plates,
                           pose2sim_keypoints):
        """Cached masks equal recomputed ones; a changed setting computes anew."""
        images, kp = pose2sim_frames[0][:2], pose2sim_keypoints[:2]
        calls = []

        def run(settings):
            def fn():
                calls.append(settings)
                return compute_masks(images, pose2sim_rig, pose2sim_plates, kp, settings)
            key = (images, pose2sim_rig, pose2sim_plates, kp, MaskSettings.from_dict(settings))
            return cached_masks(tmp_path, key, fn)

        m1, r1 = run({"scale": SCALE})
        m2, r2 = run({"scale": SCALE})
        assert len(calls) == 1 and not r1["cache"]["hit"] and r2["cache"]["hit"]
        again, _ = compute_masks(images, pose2sim_rig, pose2sim_plates, kp, {"scale": SCALE})
        assert torch.equal(m2, again) and torch.equal(m1, again) and bool(again.any())
        assert r2["mask_fraction"] == r1["mask_fraction"]
        m3, r3 = run({"scale": SCALE, "threshold": 6.0})
        assert len(calls) == 2 and not r3["cache"]["hit"] and not torch.equal(m3, m1)
        assert r3["cache"]["key"] != r1["cache"]["key"]

    def test_feature_preview(self, tmp_path, pose2sim_frames, pose2sim_rig, pose2sim_plates,
                             pose2sim_keypoints):
        from PIL import Image

        images, _ = pose2sim_frames
        path = tmp_path / "preview.png"
        masks, report = compute_masks(images[:2], pose2sim_rig, pose2sim_plates,
                                      pose2sim_keypoints[:2], {"scale": SCALE}, preview=path,
                                      preview_frame=1)
        with Image.open(path) as im:
            assert im.size == (4 * 272 + 3 * 4, 480)
        assert "preview" in report["timing_s"]


def _synthetic(T=2, C=4, H=48, W=64):
    g = torch.Generator().manual_seed(0)
    return torch.randint(0, 255, (T, C, H, W, 3), dtype=torch.uint8, generator=g), \
        make_ring_rig(C, image_size=(W, H))


class TestComputeMasks:
    def test_smoke(self):
        images, rig = _synthetic()
        masks, report = compute_masks(images, rig, settings={"scale": 0.5, "multiview": False})
        assert masks.shape == (2, 4, 24, 32)
        assert set(report["timing_s"]) == {"resize", "background", "foreground"}

    def test_exception(self):
        images, rig = _synthetic()
        plates = images[0]
        with pytest.raises(MaskError, match=r"images: expected a tensor of shape \(T, 4, H, W"):
            compute_masks(images[:, :3], rig)
        with pytest.raises(MaskError, match="images: expected uint8"):
            compute_masks(images.float(), rig)
        with pytest.raises(MaskError, match="do not hold the rig's image sizes"):
            compute_masks(images[:, :, :40], rig)
        with pytest.raises(MaskError, match="rig: expected a CameraRig"):
            compute_masks(images, "rig")
        with pytest.raises(MaskError, match=r"backgrounds: expected shape \(4, H, W, 3\)"):
            compute_masks(images, rig, plates[:3])
        with pytest.raises(MaskError, match=r"backgrounds: expected 4 plates"):
            compute_masks(images, rig, [])
        with pytest.raises(MaskError, match=r"backgrounds\[1\]: expected a non-empty"):
            compute_masks(images, rig, [plates[0], plates[1, :0], None, None])
        with pytest.raises(MaskError, match=r"backgrounds\[0\]: a 64x24 plate does not fit"):
            compute_masks(images, rig, [plates[0, :24], None, None, None])
        with pytest.raises(MaskError, match=r"backgrounds\[0\]: a 96x48 plate does not fit"):
            compute_masks(images, rig, [torch.cat([plates[0], plates[0][:, :32]], 1), None,
                                        None, None])
        with pytest.raises(MaskError, match=r"backgrounds\[2\]: the plate is blank"):
            compute_masks(images, rig, [None, None, torch.zeros(48, 64, 3, dtype=torch.uint8),
                                        None])
        with pytest.raises(MaskError, match=r"backgrounds\[0\]: expected uint8"):
            compute_masks(images, rig, [plates[0].float(), None, None, None])
        with pytest.raises(MaskError, match=r"keypoints: expected shape \(2, 4, K, 3\)"):
            compute_masks(images, rig, keypoints=torch.zeros(2, 3, 25, 3))
        bad = torch.zeros(2, 4, 25, 3)
        bad[0, 0, 0] = torch.tensor([float("nan"), 1.0, 0.9])
        with pytest.raises(MaskError, match="keypoints: expected finite pixel"):
            compute_masks(images, rig, keypoints=bad)
        bad[0, 0, 0] = torch.tensor([1.0, 1.0, -0.5])
        with pytest.raises(MaskError, match="keypoints: expected finite confidences"):
            compute_masks(images, rig, keypoints=bad)
        with pytest.raises(MaskError, match=r"masks\.scale: expected a finite number"):
            compute_masks(images, rig, settings={"scale": 0})
        with pytest.raises(MaskError, match=r"masks: unknown setting\(s\) \['treshold'\]"):
            compute_masks(images, rig, settings={"treshold": 3})
        with pytest.raises(MaskError, match=r"masks\.min_views: expected at most"):
            compute_masks(images, rig, settings={"min_views": 5})
        with pytest.raises(MaskError, match="preview_frame"):
            compute_masks(images, rig, preview="x.png", preview_frame=2)

    def test_device(self, device):
        """Inputs on ``device`` (a float32 rig, float32 keypoints): masks come back there."""
        images, rig = _synthetic()
        pts = torch.tensor([[0.0, 0.0, 0.5], [0.1, 0.0, 1.0], [-0.1, 0.1, 1.5]],
                           dtype=torch.float64)
        pix = rig.project(pts)[0]  # (C, 3, 2)
        kp = torch.cat([pix, torch.full((4, 3, 1), 0.9, dtype=torch.float64)], -1)
        kp = kp.float().expand(2, 4, 3, 3).contiguous()
        masks, report = compute_masks(images.to(device), rig.float().to(device),
                                      images[0].to(device), kp.to(device),
                                      {"scale": 0.5, "voxel_size": 0.1})
        assert masks.device.type == device.type and masks.shape == (2, 4, 24, 32)
        assert report["multiview"]["bounds_from"] == ["keypoints"]

    def test_feature_codec_crop_plate(self):
        """A plate 8 px wider than its camera's frames (a codec crop) is accepted, cropped on
        the right: with plates equal to the empty scene, a static scene has no foreground."""
        images, rig = _synthetic(T=3)
        static = images[:1].expand(3, -1, -1, -1, -1).contiguous()
        plates = [torch.cat([static[0, c], static[0, c, :, -8:]], 1) for c in range(4)]
        masks, report = compute_masks(static, rig, plates, settings={
            "scale": 1.0, "multiview": False, "register_plates": False})
        assert not bool(masks.any())
        assert [b["plate"] for b in report["background"]] == [True] * 4

    def test_feature_key_sensitivity(self):
        images, rig = _synthetic()
        k = content_key(images, rig, MaskSettings())
        assert k == content_key(images.clone(), rig, MaskSettings())
        changed = images.clone()
        changed[0, 0, 0, 0, 0] ^= 1
        assert content_key(changed, rig, MaskSettings()) != k
        assert content_key(images, rig, MaskSettings(threshold=5.0)) != k
        assert content_key(images, rig.scaled_images(0.5), MaskSettings()) != k
