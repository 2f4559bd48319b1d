"""BVH reader and writer: channel orders, 6-channel joints, end sites, units, round trips."""

from __future__ import annotations

import math
import os

import pytest
import torch

from torchmocap.io import MotionFormatError, read_bvh, write_bvh
from torchmocap.io.bvh import parse_bvh
from torchmocap.io.motion import y_up_to_z_up

# a root, a 6-channel child (per-frame translation replacing its offset) with its own channel
# order, a 3-channel grandchild and an end site; lengths in cm
TOY = """HIERARCHY
ROOT Base
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Slider
  {
    OFFSET 0 10 0
    CHANNELS 6 Xrotation Yposition Zrotation Xposition Zposition Yrotation
    JOINT Tip
    {
      OFFSET 0 20 0
      CHANNELS 3 Yrotation Zrotation Xrotation
      End Site
      {
        OFFSET 5 0 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
1 2 3 0 0 0 0 7 0 0 0 0 0 0 0
0 0 0 90 0 0 0 10 90 0 0 0 0 0 0
"""


def _rz(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]],
                        dtype=torch.float64)


@pytest.fixture
def toy(tmp_path):
    p = tmp_path / "toy.bvh"
    p.write_text(TOY)
    with pytest.warns(UserWarning, match="unknown length unit"):
        read_bvh(p)  # no map knows this skeleton: warns and assumes metres
    return read_bvh(p, unit=0.01)


class TestRead:
    def test_smoke_toy(self, toy):
        assert toy.joint_names == ["Base", "Slider", "Tip", "Tip_end"]
        assert toy.parents == [-1, 0, 1, 2]
        assert toy.num_frames == 2 and toy.fps == 25.0
        assert [a.shape[0] for a in toy.axes] == [3, 3, 3, 0]
        assert toy.skeleton_family is None and toy.source_format == "bvh"

    def test_feature_six_channel_joint_translation(self, toy):
        p = toy.global_positions()
        # frame 0: root at (1,2,3) cm, Slider translated to (0,7,0) cm (not its OFFSET 0 10 0)
        base = y_up_to_z_up(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)) * 0.01
        assert torch.allclose(p[0, 0], base)
        assert torch.allclose(p[0, 1], base + y_up_to_z_up(torch.tensor([0, 0.07, 0.0],
                                                                          dtype=torch.float64)))
        # frame 1: root Zrotation 90 then Slider Yposition 10, Zrotation 90: tip along -x, end -y
        src = torch.tensor([0.0, 10, 0], dtype=torch.float64)
        R0 = _rz(90)
        slider = R0 @ src
        tip = slider + R0 @ _rz(90) @ torch.tensor([0.0, 20, 0], dtype=torch.float64)
        end = tip + R0 @ _rz(90) @ torch.tensor([5.0, 0, 0], dtype=torch.float64)
        for j, v in ((1, slider), (2, tip), (3, end)):
            assert torch.allclose(p[1, j], y_up_to_z_up(v) * 0.01, atol=1e-12)

    def test_feature_channel_order_is_matrix_order(self, tmp_path):
        # "Zrotation Xrotation Yrotation" means L = Rz Rx Ry (checked on an asymmetric pose)
        text = TOY.replace("0 0 0 90 0 0 0 10 90 0 0 0 0 0 0",
                           "0 0 0 30 40 50 0 10 0 0 0 0 0 0 0")
        p = tmp_path / "o.bvh"
        p.write_text(text)
        clip = read_bvh(p, unit=1.0)
        a, b, c = (math.radians(v) for v in (30, 40, 50))

        def rot(axis, t):
            from torchmocap.geometry import axis_angle_rotation
            e = torch.zeros(3, dtype=torch.float64)
            e["xyz".index(axis)] = 1
            return axis_angle_rotation(e, torch.tensor(t, dtype=torch.float64))

        L = rot("z", a) @ rot("x", b) @ rot("y", c)
        from torchmocap.io.motion import Y_UP_TO_Z_UP as A
        assert torch.allclose(clip.rotations[1, 0], A @ L @ A.T, atol=1e-12)

    def test_feature_real_channel_orders(self, cmu):
        clip = read_bvh(cmu / "131_01.bvh")
        assert clip.channels[clip.joint_index("LeftElbow")] == ("Zrotation", "Xrotation",
                                                                "Yrotation")
        assert clip.channels[clip.joint_index("LeftKnee")] == ("Zrotation", "Yrotation",
                                                               "Xrotation")
        assert clip.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
        ends = [n for n in clip.joint_names if n.endswith("_end")]
        assert len(ends) == 7 and "Head_end" in ends
        for n in ends:
            assert clip.axes[clip.joint_index(n)].shape[0] == 0
        assert clip.num_frames == 120 and clip.fps == 120.0  # trimmed copy (994 in all)

    def test_feature_unit(self, cmu):
        a = read_bvh(cmu / "cmu21_kick.bvh")  # family unit: cm
        b = read_bvh(cmu / "cmu21_kick.bvh", unit=0.02)
        assert a.unit == 0.01
        assert torch.allclose(b.global_positions(), 2 * a.global_positions(), atol=1e-12)

    def test_feature_skip_frames_only_when_asked(self, cmu):
        full = read_bvh(cmu / "01_01.bvh")
        assert full.num_frames == 121  # frame 0 (synthetic T-pose) is kept by default
        skipped = read_bvh(cmu / "01_01.bvh", skip_frames=1)
        assert skipped.num_frames == 120
        assert torch.equal(skipped.rotations[0], full.rotations[1])
        # frame 0 is synthetic: almost every joint at its rest rotation; captured frames are not
        eye = torch.eye(3, dtype=torch.float64)
        at_rest = (full.rotations - eye).abs().amax((-1, -2)) < 1e-12
        assert int(at_rest[0].sum()) >= 30 and int(at_rest[1].sum()) <= 12

    def test_feature_fps_snapping(self, tmp_path):
        p = tmp_path / "f.bvh"
        p.write_text(TOY.replace("Frame Time: 0.04", "Frame Time: 0.033367"))
        assert read_bvh(p, unit=1.0).fps == pytest.approx(1 / 0.033367)  # 29.97, not 30
        p.write_text(TOY.replace("Frame Time: 0.04", "Frame Time: .0083333"))
        assert read_bvh(p, unit=1.0).fps == 120.0

    def test_exception_messages_name_file_and_line(self, tmp_path):
        p = tmp_path / "bad.bvh"
        p.write_text(TOY.replace("Zrotation Xrotation Yrotation", "Zrotation Xrotation Qrotation"))
        with pytest.raises(MotionFormatError, match=r"bad\.bvh:5: unknown channel 'Qrotation'"):
            read_bvh(p, unit=1.0)
        p.write_text(TOY.split("MOTION")[0])
        with pytest.raises(MotionFormatError, match="missing MOTION"):
            read_bvh(p, unit=1.0)
        p.write_text(TOY.replace("0 0 0 90 0 0 0 10 90 0 0 0 0 0 0", "0 0 0 90 0 0 0 10 90 0 0"))
        with pytest.raises(MotionFormatError, match=r":25: frame has 11 values, expected 15"):
            read_bvh(p, unit=1.0)
        p.write_text(TOY.replace("1 2 3 0", "1 nan 3 0"))
        with pytest.raises(MotionFormatError, match=r":24: frame holds NaN"):
            read_bvh(p, unit=1.0)
        # a corrupted angle (it was skipped as 'a reference pose' when tracking)
        p.write_text(TOY.replace("0 0 0 90 0 0 0 10 90 0", "0 0 0 90 0 0 0 10 1e20 0"))
        with pytest.raises(MotionFormatError, match=r":25: frame 1: joint Slider channel "
                                                    r"Zrotation = 1e\+20 degrees is not an "
                                                    r"angle"):
            read_bvh(p, unit=1.0)
        p.write_text(TOY.replace("0 0 0 90 0 0 0 10 90 0", "0 0 0 90 0 0 0 10 720 0"))
        assert read_bvh(p, unit=1.0).num_frames == 2  # an unwrapped 720 degrees is an angle
        p.write_text(TOY.replace("Frames: 2", "Frames: 3"))
        with pytest.raises(MotionFormatError, match="truncated"):
            read_bvh(p, unit=1.0)
        with pytest.raises(MotionFormatError, match="cannot read"):
            read_bvh(tmp_path / "missing.bvh")
        assert issubclass(MotionFormatError, ValueError)

    @pytest.mark.parametrize("dt", ["1e300", "1e-300", "3600", "1e-7", "0", "-0.04", "inf"])
    def test_exception_absurd_frame_time(self, tmp_path, dt):
        """``Frame Time: 1e300`` was read as a 1e-300 fps clip (0.0 fps in torchmocap-info)."""
        p = tmp_path / "dt.bvh"
        p.write_text(TOY.replace("Frame Time: 0.04", f"Frame Time: {dt}"))
        with pytest.raises(MotionFormatError, match=r"dt\.bvh:23: frame time") as e:
            read_bvh(p, unit=1.0)
        assert e.value.line == 23

    @pytest.mark.parametrize("dt, fps", [("60", 1 / 60), ("0.00001", 100000.0)])
    def test_feature_frame_time_bounds(self, tmp_path, dt, fps):
        p = tmp_path / "dt.bvh"
        p.write_text(TOY.replace("Frame Time: 0.04", f"Frame Time: {dt}"))
        assert read_bvh(p, unit=1.0).fps == pytest.approx(fps)

    def test_parse_bvh_text(self):
        joints, values, fps = parse_bvh(TOY)
        assert [j.name for j in joints] == ["Base", "Slider", "Tip", "Tip_end"]
        assert values.shape == (2, 15) and fps == 25.0


class TestWrite:
    @pytest.mark.parametrize("name", ["01_01.bvh", "131_01.bvh", "60_12_scaled.bvh",
                                      "cmu21_hop.bvh"])
    def test_feature_round_trip_real(self, cmu, tmp_path, name):
        clip = read_bvh(cmu / name).slice(0, 150)
        out = write_bvh(tmp_path / "rt.bvh", clip)
        back = read_bvh(out)
        assert back.joint_names == clip.joint_names
        assert back.channels == clip.channels
        assert back.skeleton_family == clip.skeleton_family and back.unit == clip.unit
        err = (back.global_positions() - clip.global_positions()).abs().max()
        assert err < 1e-6

    def test_feature_round_trip_six_channels(self, toy, tmp_path):
        out = write_bvh(tmp_path / "toy_rt.bvh", toy, unit=0.01)
        back = read_bvh(out, unit=0.01)
        assert set(back.local_translations) == {"Slider"}
        assert (back.global_positions() - toy.global_positions()).abs().max() < 1e-9

    def test_feature_round_trip_from_asf(self, cmu, tmp_path):
        from torchmocap.io import read_amc

        clip = read_amc(cmu / "01_01.amc", cmu / "01.asf").slice(0, 60)
        out = write_bvh(tmp_path / "amc.bvh", clip, unit=0.01)
        back = read_bvh(out, unit=0.01)
        idx = [back.joint_index(n) for n in clip.joint_names]
        assert (back.global_positions()[:, idx] - clip.global_positions()).abs().max() < 1e-6

    def test_feature_atomic(self, toy, tmp_path, monkeypatch):
        target = tmp_path / "keep.bvh"
        target.write_text("old contents")

        def boom(src, dst):
            raise OSError("disk full")

        monkeypatch.setattr(os, "replace", boom)
        with pytest.raises(OSError, match="disk full"):
            write_bvh(target, toy, unit=0.01)
        assert target.read_text() == "old contents"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.bvh", "toy.bvh"]
        monkeypatch.undo()
        write_bvh(target, toy, unit=0.01)
        assert target.read_text().startswith("HIERARCHY")
        assert oct(target.stat().st_mode & 0o777) != oct(0o600)  # not mkstemp's private mode


def test_bundled_clip():
    from torchmocap.io import bundled_clip_path, chain_height

    path = bundled_clip_path()
    assert path.stat().st_size < 1_000_000
    assert (path.parent / "LICENSE.txt").read_text().count("NSF EIA-0196217") == 1
    clip = read_bvh(path)
    assert clip.skeleton_family == "cmu_max"
    assert clip.num_frames == 480 and clip.fps == 120.0 and clip.duration_s == 4.0
    assert abs(chain_height(clip) - 1.42) < 0.03
    root = clip.root_translation
    assert float((root[-1, :2] - root[0, :2]).norm()) > 1.5  # it walks (> 1.5 m in 4 s)
