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
