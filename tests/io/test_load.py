"""``load_motion``: extension dispatch and argument checks."""

from __future__ import annotations

import pytest

from torchmocap.io import bundled_clip_path, load_motion


@pytest.mark.parametrize("fps", [0, 0.0, -120.0, float("nan"), float("inf"), True])
def test_exception_fps(fps, tmp_path):
    """``fps=0`` used to become the default 120 (``fps or 120``): now it is an error."""
    with pytest.raises(ValueError, match=r"^fps: expected a positive finite frame rate"):
        load_motion(tmp_path / "walk.amc", asf=tmp_path / "walk.asf", fps=fps)
    with pytest.raises(ValueError, match=r"^fps: "):
        load_motion(bundled_clip_path(), fps=fps)


def test_feature_fps_default_and_ignored_for_bvh():
    clip = load_motion(bundled_clip_path(), fps=30.0)  # BVH states its rate: 120
    assert clip.fps == 120.0


def test_find_asf_by_name(tmp_path):
    from torchmocap.io import MotionFormatError, find_asf

    amc = tmp_path / "HDM_bk_hop_017_120.amc"
    amc.write_text("")
    with pytest.raises(MotionFormatError, match="no .asf file beside this AMC"):
        find_asf(amc)
    (tmp_path / "other.asf").write_text("")
    assert find_asf(amc) == tmp_path / "other.asf"  # the only one
    for name in ("HDM_bd.asf", "HDM_bk.asf", "HDM.asf", "HDM_bk_hop.ASF"):
        (tmp_path / name).write_text("")
    assert find_asf(amc) == tmp_path / "HDM_bk_hop.ASF"  # longest name prefix, any case
    (tmp_path / "HDM_bk_hop.ASF").unlink()
    assert find_asf(amc) == tmp_path / "HDM_bk.asf"
    assert find_asf(tmp_path / "HDM_bd.amc") == tmp_path / "HDM_bd.asf"  # same name
    with pytest.raises(MotionFormatError, match="none named after it"):
        find_asf(tmp_path / "HDMX_bk_1.amc")  # a prefix without the underscore: no match
