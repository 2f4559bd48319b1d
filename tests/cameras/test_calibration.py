"""Calibration readers/writers and the visual hull on the real bodytrack frame."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchmocap.cameras import (
    CameraError,
    CameraRig,
    estimate_up_direction,
    make_ceiling_rig,
    make_ring_rig,
    read_bouguet_cal,
    read_bouguet_rig,
    read_rig,
    visual_hull,
    write_rig,
)

F64 = torch.float64

# real-frame hull bounds (metres, world of the bodytrack calibration: z up, floor at z = 0)
BOUNDS = [[-1.5, 1.5], [-1.0, 2.0], [-0.2, 2.3]]


def _cal_text(values):
    return "\n".join(f"{v:.10f}" if isinstance(v, float) else str(v) for v in values) + "\n"


class TestBouguet:
    def test_feature_real_files(self, bodytrack_calibs):
        rig = read_bouguet_rig(bodytrack_calibs, unit="mm")
        assert rig.num_cameras == 4 and rig.names == ["Camera1", "Camera2", "Camera3", "Camera4"]
        torch.testing.assert_close(rig.K[0, 0, 0], torch.tensor(584.2422154909, dtype=F64))
        torch.testing.assert_close(rig.dist[0], torch.tensor([-0.3172978596, 0.1387289551, 0, 0, 0],
                                                             dtype=F64))
        c = rig.camera_centers()
        # cameras ~2.5 m above the floor in the corners of a ~5 m x 4.5 m office
        assert bool(((c[:, 2] > 2.4) & (c[:, 2] < 2.7)).all())
        assert bool((c[:, :2].norm(dim=-1) > 2.5).all()) and bool((c[:, :2].norm(dim=-1) < 4).all())
        # world up is +z: camera heights agree (spread < 6 cm) and all cameras look down
        assert (c[:, 2].max() - c[:, 2].min()) < 0.06
        assert bool((rig.optical_axes()[:, 2] < -0.4).all())
        metres = read_bouguet_rig(bodytrack_calibs, unit="m")
        torch.testing.assert_close(metres.t, rig.t * 1000)

    def test_feature_up_direction(self, bodytrack_calibs):
        rig = read_bouguet_rig(bodytrack_calibs, unit="mm")
        up = estimate_up_direction(rig)
        angle = math.degrees(math.acos(float(up[2])))
        assert angle < 2.0, up  # the bodytrack world is Z-up
        for synth in (make_ring_rig(4), make_ceiling_rig(4), make_ring_rig(2)):
            torch.testing.assert_close(estimate_up_direction(synth),
                                       torch.tensor([0.0, 0, 1], dtype=F64), atol=1e-9, rtol=0)
        # a rig mounted upside down in the world (z flipped) reports -z
        flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64))  # rotation by pi about x
        upside = CameraRig(rig.K, rig.R @ flip, rig.t, (640, 480), rig.dist)
        assert float(estimate_up_direction(upside)[2]) < -0.99

    def test_exception_wrong_count(self, tmp_path):
        p = tmp_path / "bad.cal"
        p.write_text("1\n2\n3\n")
        with pytest.raises(CameraError, match=r"bad\.cal:3: expected 25 numbers"):
            read_bouguet_cal(p)

    def test_exception_not_a_number_and_non_finite(self, tmp_path, bodytrack_calibs):
        lines = bodytrack_calibs[0].read_text().splitlines()
        bad = list(lines)
        bad[6] = "abc"
        p = tmp_path / "nan.cal"
        p.write_text("\n".join(bad))
        with pytest.raises(CameraError, match=r"nan\.cal:7: not a number"):
            read_bouguet_cal(p)
        bad[6] = "inf"
        p.write_text("\n".join(bad))
        with pytest.raises(CameraError, match=r"nan\.cal:7: kc\[1\] is not finite"):
            read_bouguet_cal(p)

    def test_exception_transposed_and_non_rotation(self, tmp_path, bodytrack_calibs):
        v = [float(x) for x in bodytrack_calibs[0].read_text().split()]
        R = np.array(v[10:19]).reshape(3, 3)
        tr = v[:10] + R.T.ravel().tolist() + v[19:]
        p = tmp_path / "transposed.cal"
        p.write_text(_cal_text(tr))
        with pytest.raises(CameraError, match=r"transposed\.cal:23-25: Rodrigues .* transposed"):
            read_bouguet_cal(p)
        scaled = v[:10] + (R * 1.01).ravel().tolist() + v[19:]
        p.write_text(_cal_text(scaled))
        with pytest.raises(CameraError, match=r"transposed\.cal:11-19: .* not a rotation"):
            read_bouguet_cal(p)
        with pytest.raises(CameraError, match="unknown unit"):
            read_bouguet_cal(bodytrack_calibs[0], unit="furlong")


class TestYamlJson:
    @pytest.mark.parametrize("suffix", [".json", ".yaml"])
    def test_feature_round_trip(self, tmp_path, suffix, bodytrack_calibs):
        rig = read_bouguet_rig(bodytrack_calibs, unit="mm")
        path = write_rig(rig, tmp_path / f"rig{suffix}")
        back = read_rig(path)
        for name in ("K", "dist", "R", "t", "image_size"):
            torch.testing.assert_close(getattr(back, name), getattr(rig, name), rtol=0, atol=1e-12)
        assert back.names == rig.names
        assert not list(tmp_path.glob(".*tmp"))  # atomic write leaves no temp file

    def test_feature_atomic_write_keeps_old_file_on_failure(self, tmp_path, monkeypatch):
        rig = make_ring_rig(2)
        path = write_rig(rig, tmp_path / "rig.json")
        before = path.read_text()

        def boom(*a, **k):
            raise OSError("disk full")

        monkeypatch.setattr("os.replace", boom)
        with pytest.raises(OSError, match="disk full"):
            write_rig(make_ring_rig(3), path)
        assert path.read_text() == before and len(list(tmp_path.iterdir())) == 1

    def test_feature_opencv_filestorage(self, tmp_path):
        text = """%YAML:1.0
---
image_width: 640
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1, 0.01, 0., 0., 0. ]
rvec: [0.0, 0.0, 1.5707963267948966]
tvec: [100.0, 0.0, 2000.0]
"""
        p = tmp_path / "cam.yml"
        p.write_text(text)
        rig = read_rig(p, unit="mm")
        torch.testing.assert_close(rig.K[0, 0, 2], torch.tensor(320.0, dtype=F64))
        torch.testing.assert_close(rig.t[0], torch.tensor([0.1, 0.0, 2.0], dtype=F64))
        torch.testing.assert_close(rig.R[0] @ torch.tensor([1.0, 0, 0], dtype=F64),
                                   torch.tensor([0.0, 1.0, 0.0], dtype=F64))
        assert rig.dist[0, 0].item() == pytest.approx(-0.1)

    def test_exception(self, tmp_path):
        p = tmp_path / "bad.json"
        p.write_text(json.dumps({"cameras": [{"K": [[1, 0], [0, 1]], "R": np.eye(3).tolist(),
                                              "t": [0, 0, 0], "image_size": [10, 10]}]}))
        with pytest.raises(CameraError, match=r"bad\.json: camera 0: K must have 9"):
            read_rig(p)
        p.write_text("{not json")
        with pytest.raises(CameraError, match=r"bad\.json:1: cannot parse"):
            read_rig(p)
        cam = {"K": np.eye(3).tolist(), "R": (2 * np.eye(3)).tolist(), "t": [0, 0, 0],
               "image_size": [10, 10]}
        p.write_text(json.dumps({"cameras": [cam]}))
        with pytest.raises(CameraError, match=r"bad\.json: .*not a rotation"):
            read_rig(p)
        with pytest.raises(CameraError, match="extension"):
            write_rig(make_ring_rig(1), tmp_path / "rig.txt")


def _hull(rig, masks, res=0.03):
    return visual_hull(rig, masks, BOUNDS, res)


class TestVisualHullReal:
    def test_feature_person_blob(self, bodytrack_calibs, bodytrack_masks):
        rig = read_bouguet_rig(bodytrack_calibs, unit="mm")
        assert bodytrack_masks.shape == (4, 480, 640)
        hull = _hull(rig, bodytrack_masks)
        blob = hull.largest_component()
        lo, hi = blob.extent()
        height = float(hi[2] - lo[2])
        # the up axis is z (see TestBouguet): a standing person 1.5–2 m tall on the floor z ≈ 0
        assert 1.5 < height < 2.0, height
        assert abs(float(lo[2])) < 0.1
        # horizontal extent is person-like (a 4-view hull is fatter than the body)
        assert float((hi[:2] - lo[:2]).max()) < 1.2
        assert 0.04 < blob.volume < 0.3, blob.volume
        assert blob.volume > 0.9 * hull.volume
        # the blob's voxels project inside every mask; shrinking a mask shrinks the hull
        c = blob.centers()
        pix, _, vis = rig.project(c)
        assert bool(vis.all())
        # rendered back into the views, the blob covers the silhouettes: IoU 0.74-0.80 per view
        # at 3 cm (the masks carry ~100-500 specks of noise each), recall 0.86-0.92
        sil = blob.silhouettes(rig)
        m = torch.from_numpy(bodytrack_masks > 0)
        inter = (sil & m).sum((1, 2)).double()
        iou = inter / (sil | m).sum((1, 2)).double()
        assert bool((iou > 0.68).all()), iou
        assert bool((inter / m.sum((1, 2)) > 0.82).all())
        masks2 = bodytrack_masks.copy()
        masks2[0, :, :] = 0
        assert _hull(rig, masks2).volume == 0.0
        assert visual_hull(rig, masks2, BOUNDS, 0.03, min_views=3).volume >= hull.volume

    def test_feature_wrong_calibration_gives_absurd_hull(self, bodytrack_calibs, bodytrack_masks):
        rig = read_bouguet_rig(bodytrack_calibs, unit="mm")
        good = _hull(rig, bodytrack_masks).largest_component()
        # transposed rotations (the classic row/column-major slip): camera centres move
        transposed = CameraRig(rig.K, rig.R.transpose(-1, -2), rig.t, rig.image_size[0], rig.dist)
        bad = _hull(transposed, bodytrack_masks)
        assert bad.volume < 0.01 * good.volume  # 0.16 m³ -> ~1e-4 m³: nothing consistent
        # file read in metres instead of millimetres: cameras kilometres away
        metres = read_bouguet_rig(bodytrack_calibs, unit="m")
        bad_unit = _hull(metres, bodytrack_masks)
        assert bad_unit.volume == 0.0
        assert good.volume > 0.04

    def test_exception(self, bodytrack_calibs, bodytrack_masks):
        rig = read_bouguet_rig(bodytrack_calibs, unit="mm")
        with pytest.raises(CameraError, match="masks"):
            visual_hull(rig, bodytrack_masks[:3], BOUNDS, 0.05)
        with pytest.raises(CameraError, match="masks"):
            visual_hull(rig, bodytrack_masks[:, :240], BOUNDS, 0.05)
        with pytest.raises(CameraError, match="bounds"):
            visual_hull(rig, bodytrack_masks, [[1, 0], [0, 1], [0, 1]], 0.05)


def test_visual_hull_synthetic_sphere():
    # silhouettes of a sphere rendered analytically in a ring rig: the hull contains the sphere
    # and its volume is within the 4-view over-estimate of the sphere's volume
    rig = make_ring_rig(4, radius=4.0, height=2.5, target=(0, 0, 1), image_size=(320, 240))
    centre, r = torch.tensor([0.1, -0.2, 1.0], dtype=F64), 0.3
    o, d = rig.backproject(torch.stack(torch.meshgrid(torch.arange(320.0, dtype=F64),
                                                      torch.arange(240.0, dtype=F64),
                                                      indexing="xy"), -1)
                           .reshape(1, -1, 2).expand(4, -1, 2))
    v = centre - o
    s = (v * d).sum(-1)
    dist = (v - s[..., None] * d).norm(dim=-1)
    masks = (dist < r).reshape(4, 240, 320)
    hull = visual_hull(rig, masks, [[-1, 1], [-1, 1], [0, 2]], 0.02)
    sphere = 4 / 3 * math.pi * r**3
    assert sphere < hull.volume < 1.6 * sphere
    c = hull.centers()
    assert (c.mean(0) - centre).norm() < 0.02


def test_visual_hull_of_views_of_different_sizes():
    """Views of different sizes share one array (a sequence's layout: a smaller view in the
    top-left corner). A view cropped at the right and bottom carves what lies beyond its own
    image — as an uncropped view whose mask is empty there — and never reads the padding; its
    rendered hull is False beyond its size."""
    base = make_ring_rig(3, image_size=(64, 48)).double()
    g = torch.Generator().manual_seed(0)
    # a ball of points 0.4 m wide around the rigs' target, rendered as masks
    pts = (torch.rand(4000, 3, generator=g, dtype=torch.float64) - 0.5) * 0.4 + \
        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    pix, _, _ = base.project(pts)
    masks = torch.zeros(3, 48, 64, dtype=torch.bool)
    for c in range(3):
        u, v = pix[c, :, 0].round().long().clamp(0, 63), pix[c, :, 1].round().long().clamp(0, 47)
        masks[c, v, u] = True
    bounds = [[-0.5, 0.5], [-0.5, 0.5], [0.5, 1.5]]
    cropped = CameraRig(base.K, base.R, base.t, [[64, 48], [34, 48], [64, 48]], base.dist)
    inside = masks.clone()
    inside[1, :, 34:] = False  # the cropped-away part, as an empty mask
    padded = masks.clone()
    padded[1, :, 34:] = True  # padding that must not be read
    want = visual_hull(base, inside, bounds, 0.02)
    got = visual_hull(cropped, padded, bounds, 0.02)
    assert want.volume > 0 and torch.equal(got.occupancy, want.occupancy)
    assert got.volume < visual_hull(base, masks, bounds, 0.02).volume  # the crop carved
    sil = got.silhouettes(cropped)
    assert sil.shape == (3, 48, 64) and not bool(sil[1, :, 34:].any())
    with pytest.raises(CameraError, match=r"expected \(C, 48, 64\)"):
        visual_hull(cropped, masks[:, :, :34], bounds, 0.02)
