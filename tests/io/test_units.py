"""Length unit of BVH files no skeleton map knows, inferred from the subject's size."""

from __future__ import annotations

import re
import warnings

import pytest
import torch

from torchmocap.io import load_motion, read_bvh, write_bvh
from torchmocap.io.skeleton_maps import chain_height, human31_positions
from torchmocap.io.units import LENGTH_UNITS, infer_length_unit

from .synthetic_bvh import unseen_family_clip, write_unseen_family_bvh


def _read(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clip = read_bvh(path, **kw)
    return clip, [str(w.message) for w in caught]


@pytest.mark.parametrize("name,unit", list(LENGTH_UNITS.items()))
@pytest.mark.parametrize("convention", ["mixamo", "unreal"])
def test_feature_unit_inferred_for_every_common_unit(tmp_path, convention, name, unit):
    """The same motion written in m, CMU units, inches, cm and mm reads back in metres: the
    inferred unit is the one written, the joint positions are the clip's, the warning says so."""
    ref = unseen_family_clip(convention)
    path = write_unseen_family_bvh(tmp_path / "clip.bvh", convention, unit=unit)
    clip, msgs = _read(path)
    assert clip.unit == pytest.approx(unit, rel=1e-12)
    assert any(f"inferred {unit:g} m per unit ({name})" in m for m in msgs), msgs
    torch.testing.assert_close(human31_positions(clip), human31_positions(ref),
                               atol=1e-5, rtol=0)


@pytest.mark.parametrize("scale", [0.82, 1.2])
def test_feature_adult_size_range(tmp_path, scale):
    """Subjects from about 1.2 to 1.8 m ankle-head chain (the adults of CMU and HDM05) get the
    written unit in both units next to each other in size (inch vs cm, inch vs CMU unit)."""
    clip = unseen_family_clip("mixamo")
    clip.offsets = clip.offsets * scale
    clip.root_translation = clip.root_translation * scale
    h = chain_height(clip)
    assert 1.2 < h < 1.95
    for unit in (0.0254, 0.01, 0.0254 / 0.45):
        path = write_bvh(tmp_path / f"s{unit}.bvh", clip, unit=unit, precision=6)
        got, _ = _read(path)
        assert got.unit == pytest.approx(unit, rel=1e-12)


def test_feature_explicit_and_map_units_win(tmp_path, cmu):
    path = write_unseen_family_bvh(tmp_path / "clip.bvh", "mixamo", unit=0.01)
    clip, msgs = _read(path, unit=0.02)  # explicit: no inference, no warning
    assert clip.unit == 0.02 and not msgs
    kick, msgs = _read(cmu / "cmu21_kick.bvh")  # the family map's cm
    assert kick.unit == 0.01 and not msgs


def test_feature_no_guess_without_a_human_size(tmp_path):
    """An ankle-head chain of 11.2 file units: 11 m, 63 cm, 28 cm, 11 cm or 1 cm in the
    candidate units — no person's size; metres are assumed and the warning says why."""
    clip = unseen_family_clip("mixamo")
    clip.offsets = clip.offsets * 7.0
    path = write_bvh(tmp_path / "giant.bvh", clip, unit=1.0, precision=6)
    got, msgs = _read(path)
    assert got.unit == 1.0
    assert any("unknown length unit" in m and "no common unit" in m for m in msgs), msgs


def test_feature_unmappable_skeleton_is_not_guessed(tmp_path):
    """Joints that do not map onto human31: nothing to measure, metres with the warning."""
    clip = unseen_family_clip("mixamo", rename={"l_knee": "Gelenk7"})
    path = write_bvh(tmp_path / "odd.bvh", clip, unit=0.01, precision=6)
    got, msgs = _read(path)
    assert got.unit == 1.0
    assert any("unknown length unit" in m and "do not map onto human31" in m for m in msgs)
    g = infer_length_unit(got)
    assert g.unit is None and g.size is None


def test_infer_length_unit_reports_the_measure():
    clip = unseen_family_clip("unreal")  # metres
    g = infer_length_unit(clip)
    assert g.unit == 1.0 and g.name == "m"
    assert g.size == pytest.approx(chain_height(clip), rel=1e-9)
    assert "= " + f"{g.size:.2f} m" in g.describe()


def test_real_cmu21_renamed_reads_like_its_family(tmp_path, cmu):
    """A real CMU21 clip (cm) with its joints renamed Mixamo-style, so that no map detects it,
    reads in the same metres as through its family's map."""
    text = (cmu / "cmu21_hop.bvh").read_text()
    renamed = re.sub(r"^(\s*(?:ROOT|JOINT) )(\w+)", r"\1mixamorig:\2", text, flags=re.M)
    (tmp_path / "mix.bvh").write_text(renamed.replace("mixamorig:Neck1", "mixamorig:Neck"))
    a = load_motion(cmu / "cmu21_hop.bvh")
    b, msgs = _read(tmp_path / "mix.bvh")
    assert b.skeleton_family is None and b.unit == 0.01
    torch.testing.assert_close(human31_positions(b), human31_positions(a), atol=1e-9, rtol=0)


def test_feature_child_in_cm_is_not_read_as_inches(tmp_path):
    """A child-sized subject (0.85 m ankle-head chain, ~1 m tall) written in cm: inches would
    make it a 2.2 m chain (no person's), so cm is read and the warning says "a child's size"."""
    clip = unseen_family_clip("mixamo")
    scale = 0.85 / chain_height(clip)
    clip.offsets = clip.offsets * scale
    clip.root_translation = clip.root_translation * scale
    path = write_bvh(tmp_path / "child.bvh", clip, unit=0.01, precision=6)
    got, msgs = _read(path)
    assert got.unit == 0.01
    assert any("a child's size" in m and "ambiguous" not in m for m in msgs), msgs
    torch.testing.assert_close(human31_positions(got), human31_positions(clip), atol=1e-5,
                               rtol=0)


@pytest.mark.parametrize("chain,unit,alt", [(1.85, 0.0254 / 0.45, "in"), (0.76, 0.01, "in")])
def test_feature_ambiguous_sizes_are_reported(tmp_path, chain, unit, alt):
    """Where two units both give a person's size — a 1.85 m chain in CMU units is also a 0.83 m
    child in inches; a 0.76 m child in cm is also a 1.93 m adult in inches — the reading nearest
    an adult's is taken and the other is named in the guess and the warning."""
    clip = unseen_family_clip("mixamo")
    scale = chain / chain_height(clip)
    clip.offsets = clip.offsets * scale
    clip.root_translation = clip.root_translation * scale
    path = write_bvh(tmp_path / "amb.bvh", clip, unit=unit, precision=6)
    got, msgs = _read(path)
    guess = infer_length_unit(read_bvh(path, unit=1.0))
    assert [n for n, _ in guess.alternatives] == [alt] or guess.name == alt
    assert any("ambiguous: also" in m for m in msgs), msgs
    if chain > 1.5:  # the adult reading is the written one
        assert got.unit == pytest.approx(unit, rel=1e-12) and not guess.child_sized
    else:  # the child in cm is read as an adult in inches: said, not silent
        assert guess.name == "in" and guess.alternatives == (("cm", 0.01),)


@pytest.mark.parametrize("scale, error", [(1.0, None), (0.7, "warn"), (100.0, "large"),
                                          (0.1, "small"), (0.0, "zero")])
def test_check_subject_size(scale, error):
    """A person's ankle-head chain passes (a child's with a warning); a size no unit error
    could make human — x100, x0.1, all zero — is refused naming the unit setting."""
    from torchmocap.io import MotionFormatError
    from torchmocap.io.units import check_subject_size

    clip = unseen_family_clip("mixamo")
    clip.offsets = clip.offsets * scale
    clip.unit, clip.source_path = 0.01, "mine.bvh"
    h = chain_height(clip)
    if error is None:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert check_subject_size(clip, unit_setting="data.clip.unit") == pytest.approx(h)
    elif error == "warn":
        with pytest.warns(UserWarning, match=r"mine\.bvh: .* a child's size; if the subject is "
                                             r"an adult, set data\.clip\.unit"):
            check_subject_size(clip, unit_setting="data.clip.unit")
    else:
        what = {"zero": r"0 m: its offsets \(bone lengths\) are all zero",
                "small": rf"{h * 1000:.4g} mm with 0\.01 m per file unit"}.get(
                    error, rf"{h:.4g} m with 0\.01 m per file unit")
        with pytest.raises(MotionFormatError, match=rf"^mine\.bvh: the subject's ankle-head "
                                                    rf"chain measures {what}; .*set "
                                                    r"data\.clip\.unit"):
            check_subject_size(clip, unit_setting="data.clip.unit")
