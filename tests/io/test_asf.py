"""ASF/AMC reader: units, axis pre-rotation C M C^-1, dof order, CMU BVH/AMC agreement, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.io import MotionFormatError, read_amc, read_asf, read_bvh
from torchmocap.io.asf import parse_asf
from torchmocap.io.motion import y_up_to_z_up

TINY_ASF = """# tiny test skeleton
:version 1.10
:name TINY
:units
  mass 1.0
  length 0.45
  angle deg
:documentation
  two bones
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name a
     direction 1 0 0
     length 2
     axis 0 0 90  XYZ
    dof rx rz
    limits (-180 180)
           (-180 180)
  end
  begin
     id 2
     name b
     direction 1 0 0
     length 1
     axis 0 0 0 XYZ
  end
:hierarchy
  begin
    root a
    a b
  end
"""

TINY_AMC = """:FULLY-SPECIFIED
:DEGREES
1
root 1 2 3 0 0 0
a 90 0
2
root 0 0 0 0 0 90
a 30 40
"""

UNIT = 0.0254 / 0.45


def _R(axis: str, deg: float) -> torch.Tensor:
    a = math.radians(deg)
    c, s = math.cos(a), math.sin(a)
    m = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
         "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    return torch.tensor(m, dtype=torch.float64)


@pytest.fixture
def tiny(tmp_path):
    (tmp_path / "t.asf").write_text(TINY_ASF)
    (tmp_path / "t.amc").write_text(TINY_AMC)
    return read_amc(tmp_path / "t.amc", tmp_path / "t.asf", fps=60)


class TestTiny:
    def test_smoke(self, tiny):
        assert tiny.joint_names == ["root", "a", "b", "b_end"]
        assert tiny.parents == [-1, 0, 1, 2]
        assert tiny.num_frames == 2 and tiny.fps == 60 and tiny.source_format == "asf"
        assert tiny.unit == pytest.approx(0.0564444444)
        assert [a.shape[0] for a in tiny.axes] == [3, 2, 0, 0]

    def test_feature_axis_prerotation_and_dof_order(self, tiny):
        # local = C M C^-1 with C = Rz(90) (axis 0 0 90 XYZ) and M = Rz(rz) Rx(rx) (dof rx rz)
        C = _R("z", 90)
        p = tiny.global_positions()
        va = torch.tensor([2.0, 0, 0], dtype=torch.float64)
        vb = torch.tensor([1.0, 0, 0], dtype=torch.float64)
        for k, (rx, rz, root_rz) in enumerate([(90, 0, 0), (30, 40, 90)]):
            L = C @ _R("z", rz) @ _R("x", rx) @ C.T
            Rroot = _R("z", root_rz)
            root = torch.tensor([1.0, 2, 3] if k == 0 else [0.0, 0, 0], dtype=torch.float64)
            b = root + Rroot @ L @ va
            end = b + Rroot @ L @ vb
            assert torch.allclose(p[k, 0], y_up_to_z_up(root) * UNIT, atol=1e-12)
            assert torch.allclose(p[k, 2], y_up_to_z_up(b) * UNIT, atol=1e-12)
            assert torch.allclose(p[k, 3], y_up_to_z_up(end) * UNIT, atol=1e-12)

    def test_feature_rest_clip(self, tmp_path):
        asf = parse_asf(TINY_ASF, "t.asf")
        rest = asf.rest_clip().global_positions()[0]
        assert torch.allclose(rest[3], y_up_to_z_up(torch.tensor([3.0, 0, 0],
                                                                 dtype=torch.float64)) * UNIT)

    def test_feature_radians(self, tmp_path):
        # "angle rad" covers the ASF axis angles and the AMC values alike
        (tmp_path / "r.asf").write_text(TINY_ASF.replace("angle deg", "angle rad").replace(
            "axis 0 0 90", f"axis 0 0 {math.pi / 2}"))
        (tmp_path / "r.amc").write_text(TINY_AMC.replace("a 90 0", f"a {math.pi / 2} 0").replace(
            ":DEGREES", ":RADIANS"))
        deg = tmp_path / "d.asf"
        deg.write_text(TINY_ASF)
        (tmp_path / "d.amc").write_text(TINY_AMC)
        a = read_amc(tmp_path / "r.amc", tmp_path / "r.asf").slice(0, 1)
        b = read_amc(tmp_path / "d.amc", deg).slice(0, 1)
        assert torch.allclose(a.global_positions(), b.global_positions(), atol=1e-12)
        # the AMC's own :RADIANS header governs its values even when the ASF says deg
        c = read_amc(tmp_path / "r.amc", deg).slice(0, 1)
        assert torch.allclose(c.global_positions(), b.global_positions(), atol=1e-12)


class TestErrors:
    @pytest.mark.parametrize("amc, match, line", [
        (TINY_AMC.replace("a 30 40", "zz 30 40"), "bone 'zz' is not in the ASF", 8),
        (TINY_AMC.replace("a 30 40", "a 30"), "expected 2 numbers, found 1", 8),
        (TINY_AMC.replace("a 30 40", "a 30 inf"), "not finite", 8),
        (TINY_AMC.replace("a 30 40\n", ""), r"lacks bones \['a'\] \(truncated", 6),
        (TINY_AMC.replace("2\nroot", "5\nroot"), "frame 5 follows frame 1", 6),
        ("root 0 0 0 0 0 0\n", "before the first frame number", 1),
        ("", "no frames", None),
    ])
    def test_exception_amc(self, tmp_path, amc, match, line):
        (tmp_path / "t.asf").write_text(TINY_ASF)
        (tmp_path / "bad.amc").write_text(amc)
        with pytest.raises(MotionFormatError, match=match) as e:
            read_amc(tmp_path / "bad.amc", tmp_path / "t.asf")
        assert e.value.path.endswith("bad.amc") and e.value.line == line
        assert f"bad.amc{'' if line is None else f':{line}'}: " in str(e.value)

    @pytest.mark.parametrize("old, new, match", [
        ("    a b\n", "    a b\n    b a\n", "two parents"),
        (":hierarchy", ":hierarchz", "missing :hierarchy"),
        ("dof rx rz", "dof rx l", "unsupported dof 'l'"),
        ("axis 0 0 90  XYZ", "axis 0 0 90 XYY", "permutation of XYZ"),
        ("length 2", "length two", "not a number"),
        ("direction 1 0 0\n     length 1", "direction 0 0 0\n     length 1", "zero direction"),
        ("    root a\n", "    root a\n    a zz\n", "unknown bone 'zz'"),
        ("  end\n:hierarchy", ":hierarchy", "unfinished bone block"),
    ])
    def test_exception_asf(self, old, new, match):
        assert old in TINY_ASF
        with pytest.raises(MotionFormatError, match=match):
            parse_asf(TINY_ASF.replace(old, new, 1), "t.asf")

    def test_exception_mismatched_real_pair(self, cmu, tmp_path):
        # the CMU AMC against an ASF whose lfemur has two dofs: wrong value count, named
        bad = (cmu / "01.asf").read_text(encoding="latin-1").replace(
            "dof rx ry rz\n    limits (-160.0 20.0)\n           (-70.0 70.0)\n           "
            "(-60.0 70.0)", "dof rx ry\n    limits (-160.0 20.0)\n           (-70.0 70.0)", 1)
        (tmp_path / "bad.asf").write_text(bad)
        with pytest.raises(MotionFormatError, match=r"01_01\.amc:31: bone 'lfemur'"):
            read_amc(cmu / "01_01.amc", tmp_path / "bad.asf")


class TestCMU:
    def test_feature_units_and_structure(self, cmu):
        asf = read_asf(cmu / "01.asf")
        assert asf.unit == pytest.approx(1 / 0.45 * 0.0254)  # 0.05644 m per unit
        assert asf.angle == "deg" and len(asf.bones) == 30
        assert asf.bones["lfemur"].axis == (0.0, 0.0, 20.0)
        assert asf.bones["lfemur"].dof == ("rx", "ry", "rz")
        clip = read_amc(cmu / "01_01.amc", asf)
        assert clip.num_frames == 120 and clip.num_joints == 38  # trimmed copy (2751 in all)
        assert clip.skeleton_family == "cmu_asf"

    def test_feature_bvh_matches_amc(self, cmu):
        """cgspeed 01_01.bvh vs 01.asf + 01_01.amc (data README facts).

        1. BVH frame k+1 = AMC frame k: Hips/root, both legs (hip, knee, ankle, toe base, toe
           tip) and the lower back (Spine = upperback start, Spine1 = thorax start) coincide to
           < 1 mm in every frame (measured ~5 um: the BVH prints 4 decimals).
        2. Above the upper back (neck base, upper neck, head base, head top, clavicle bases,
           shoulders, elbows, wrists) AMC - BVH = R_thorax(t) @ v_thorax to < 1 mm, where
           v_thorax = 2.06488 units * direction = 11.65 cm is the ASF thorax bone the converter
           dropped and R_thorax(t) the thorax's world rotation (= the BVH Spine1's); the offset is
           not a constant: it turns with the chest.
        """
        amc = read_amc(cmu / "01_01.amc", cmu / "01.asf")
        bvh = read_bvh(cmu / "01_01.bvh")
        assert bvh.num_frames == amc.num_frames + 1
        pa = amc.global_positions()
        pb = bvh.global_positions()[1:]
        a, b = amc.joint_index, bvh.joint_index
        same = {"root": "Hips", "upperback": "Spine", "thorax": "Spine1"}
        for s, side in (("l", "Left"), ("r", "Right")):
            same.update({f"{s}femur": f"{side}UpLeg", f"{s}tibia": f"{side}Leg",
                         f"{s}foot": f"{side}Foot", f"{s}toes": f"{side}ToeBase",
                         f"{s}toes_end": f"{side}ToeBase_end"})
        for ja, jb in same.items():
            err = (pa[:, a(ja)] - pb[:, b(jb)]).norm(dim=-1).max()
            assert err < 1e-3, (ja, jb, float(err))
        # not trivially equal: the first BVH frame (synthetic T-pose) does not match AMC frame 0
        assert (bvh.global_positions()[0, b("LeftFoot")] - pa[0, a("lfoot")]).norm() > 0.05

        asf = read_asf(cmu / "01.asf")
        th = asf.bones["thorax"]
        v = y_up_to_z_up(torch.tensor(th.direction, dtype=torch.float64) * th.length * asf.unit)
        assert float(v.norm()) == pytest.approx(0.1165, abs=5e-4)
        R_thorax = amc.global_rotations()[:, a("thorax")]
        R_spine1 = bvh.global_rotations()[1:, b("Spine1")]
        assert (R_thorax - R_spine1).abs().max() < 1e-4
        shift = (R_thorax @ v[:, None])[..., 0]  # (T, 3)
        above = {"lowerneck": "Neck", "upperneck": "Neck1", "head": "Head",
                 "head_end": "Head_end"}
        for s, side in (("l", "Left"), ("r", "Right")):
            above.update({f"{s}clavicle": f"{side}Shoulder", f"{s}humerus": f"{side}Arm",
                          f"{s}radius": f"{side}ForeArm", f"{s}wrist": f"{side}Hand"})
        for ja, jb in above.items():
            d = pa[:, a(ja)] - pb[:, b(jb)]
            assert (d.norm(dim=-1) - 0.1165).abs().max() < 1e-3  # displaced by 11.65 cm ...
            assert (d - shift).norm(dim=-1).max() < 1e-3, ja  # ... the rotated thorax vector
        assert (shift[:, 2] / shift.norm(dim=-1)).min() < 0.999  # it really turns over the take


class TestHDM05:
    def test_feature_latin1_crlf(self, hdm05):
        amc = hdm05 / "HDM_bd_kickLFront1Reps_001_120.amc"
        raw = amc.read_bytes()
        assert b"\r\n" in raw and any(c > 127 for c in raw[:200])
        with pytest.raises(UnicodeDecodeError):
            raw.decode("utf-8")
        clip = read_amc(amc, hdm05 / "HDM_bd.asf")
        assert clip.skeleton_family == "hdm05_asf"
        assert clip.num_frames == 40 and clip.fps == 120  # trimmed copy (161 in all)
        assert clip.unit == pytest.approx(0.0254 / 0.45)

    def test_feature_skip_frames(self, hdm05):
        amc = hdm05 / "HDM_bk_hopBothLegs1hops_017_120.amc"
        full = read_amc(amc, hdm05 / "HDM_bk.asf")
        cut = read_amc(amc, hdm05 / "HDM_bk.asf", skip_frames=10)
        assert cut.num_frames == full.num_frames - 10
        assert torch.equal(cut.rotations, full.rotations[10:])
