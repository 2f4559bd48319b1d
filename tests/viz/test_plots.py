"""Figures: files are real images, with ink exactly where the projection says."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig, read_bouguet_rig
from torchmocap.skeleton import human31
from torchmocap.viz import capsule_outlines, overlay_on_image, plot_skeleton_sequence, side_colors

F64 = torch.float64


@pytest.fixture(scope="module")
def sk():
    return human31()


def _read(path):
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


class TestSkeletonSequence:
    def test_feature_png(self, sk, tmp_path):
        T = 10
        th = sk.zero_pose((T,), dtype=F64)
        th[:, sk.dof_index("l_knee_flex")] = torch.linspace(0, 1.5, T)
        path = plot_skeleton_sequence(sk, th, [0, 5, 9], tmp_path / "seq.png")
        img = _read(path)
        assert img.shape[1] > 2 * img.shape[0]  # three panels side by side
        nonwhite = (img < 200).any(-1)
        assert nonwhite.mean() > 0.01
        # blue (left) and red (right) limb colours are both drawn
        blue = (img[..., 2] > 150) & (img[..., 0] < 80)
        red = (img[..., 0] > 180) & (img[..., 1] < 80) & (img[..., 2] < 80)
        assert blue.sum() > 50 and red.sum() > 50

    def test_feature_positions_and_default_frames(self, sk, tmp_path):
        pos = sk.joint_positions(sk.zero_pose((3,), dtype=F64))
        path = plot_skeleton_sequence(sk, pos, None, tmp_path / "p.png")
        assert _read(path).shape[1] > 2 * _read(path).shape[0]

    def test_exception(self, sk, tmp_path):
        with pytest.raises(ValueError, match="thetas"):
            plot_skeleton_sequence(sk, torch.zeros(3, 7), None, tmp_path / "x.png")
        with pytest.raises(ValueError, match="frames"):
            plot_skeleton_sequence(sk, sk.zero_pose((2,)), [5], tmp_path / "x.png")


class TestOverlay:
    def test_feature_ink_where_projected(self, sk, tmp_path):
        rig = make_ring_rig(4, image_size=(320, 240))
        kin = sk(sk.zero_pose(dtype=F64))
        image = np.zeros((240, 320), dtype=np.uint8)
        path = overlay_on_image(image, rig, 0, kin, tmp_path / "ov.png", skeleton=sk)
        img = _read(path)
        assert img.shape == (240, 320, 3)  # same pixel size as the camera image
        pix = rig.project(kin.positions)[0][0].round().long().numpy()
        for j in ("head_top", "l_knee", "r_elbow", "pelvis"):
            u, v = pix[sk.joint_index(j)]
            patch = img[v - 1:v + 2, u - 1:u + 2]
            assert patch.max() > 100, j  # a joint dot is drawn there
        # ink only near the body: the far-left quarter of the image stays black
        assert img[:, :60].max() < 20
        drawn = (img > 60).any(-1)
        us = np.nonzero(drawn)[1]
        lo, hi = pix[:, 0].min(), pix[:, 0].max()
        assert us.min() >= lo - 8 and us.max() <= hi + 8

    def test_feature_capsule_outlines(self, sk, tmp_path):
        rig = make_ring_rig(4, image_size=(320, 240))
        body = CapsuleBody(sk)
        kin = sk(sk.zero_pose(dtype=F64))
        polys = capsule_outlines(rig, 0, body.endpoints(kin), body.radii)
        assert len(polys) == body.num_bones
        # the torso outline is wider than the chest radius projected at ~4 m
        f = rig.K[0, 0, 0].item()
        chest = polys[body.bone_names.index("neck")]
        width = chest[:, 0].max() - chest[:, 0].min()
        assert width == pytest.approx(2 * body.radius("neck") * f / 4.0, rel=0.15)
        path = overlay_on_image(np.zeros((240, 320, 3)), rig, 0, kin, tmp_path / "c.png",
                                skeleton=sk, capsules=body)
        img = _read(path)
        # the capsule fill tints pixels between the legs' joints (cyan: green+blue > red)
        u, v = rig.project(kin.positions)[0][0, sk.joint_index("l_hip")].round().long().tolist()
        p = img[v + 10, u]
        assert p[1] > p[0] + 10 and p[2] > p[0] + 10

    def test_feature_real_frame(self, tmp_path, bodytrack_dir):
        cal = bodytrack_dir
        rig = read_bouguet_rig([cal / "CALIB" / f"Camera{i}.cal" for i in range(1, 5)], "mm")
        image = np.array(Image.open(cal / "CAM2" / "image0000.png"))
        mask = np.array(Image.open(cal / "FG2" / "image0000.png"))
        pts = torch.tensor([[0.15, 1.0, 0.0], [0.15, 1.0, 1.7]], dtype=F64)
        path = overlay_on_image(image, rig, 1, pts, tmp_path / "real.png", mask=mask)
        img = _read(path)
        assert img.shape == (480, 640, 3)
        # the mask is tinted yellow: red and green above blue inside the mask
        inside = mask > 0
        d = img[inside].mean(0)
        assert d[0] > d[2] + 20 and d[1] > d[2] + 20

    def test_exception(self, sk, tmp_path):
        rig = make_ring_rig(2, image_size=(320, 240))
        kin = sk(sk.zero_pose(dtype=F64))
        with pytest.raises(ValueError, match="does not match camera"):
            overlay_on_image(np.zeros((100, 100)), rig, 0, kin, tmp_path / "x.png")
        with pytest.raises(ValueError, match="one pose"):
            overlay_on_image(np.zeros((240, 320)), rig, 0, sk(sk.zero_pose((2,))),
                             tmp_path / "x.png")


def test_side_colors():
    c = side_colors(["l_knee", "r_knee", "spine", "LeftArm", "RightArm"])
    assert c[0] == c[3] and c[1] == c[4] and len(set(c)) == 3
