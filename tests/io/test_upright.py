"""Up axis of motion files: Z-up (and other) files are turned upright from their rest pose."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from torchmocap.io import Y_UP_TO_Z_UP, load_motion, write_bvh
from torchmocap.io.skeleton_maps import human31_positions
from torchmocap.io.upright import rest_up_direction, upright

from .synthetic_bvh import unseen_family_clip


def _load(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clip = load_motion(path, **kw)
    return clip, [str(w.message) for w in caught]


def _rx(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]],
                        dtype=torch.float64)


@pytest.fixture(scope="module")
def kick(cmu):
    return load_motion(cmu / "cmu21_kick.bvh")


@pytest.mark.parametrize("G, written", [
    (Y_UP_TO_Z_UP, "a Z-up file"),            # our +z -> -y: the file's up is +z
    (Y_UP_TO_Z_UP.T, "a -Z-up file"),
    (torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)), "an upside-down file"),
    (torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=torch.float64), "an X-up file"),
])
def test_feature_turned_upright(tmp_path, kick, G, written):
    """A real clip written with other up axes reads back standing along +z, every joint where
    it was (the facing direction within the ground plane may differ only by a rotation about z,
    which the positions below rule out for these axes)."""
    path = write_bvh(tmp_path / "clip.bvh", kick.change_basis(G), unit=0.01)
    clip, msgs = _load(path)
    assert any("the clip was turned to stand along +z" in m for m in msgs), (written, msgs)
    torch.testing.assert_close(human31_positions(clip), human31_positions(kick),
                               atol=1e-6, rtol=0)
    up = rest_up_direction(clip)
    assert float(up[2]) > math.cos(math.radians(10))


def test_feature_explicit_up(tmp_path, kick):
    path = write_bvh(tmp_path / "zup.bvh", kick.change_basis(Y_UP_TO_Z_UP), unit=0.01)
    z, msgs = _load(path, up="z")  # said: no detection, no warning, upright
    assert not msgs
    torch.testing.assert_close(human31_positions(z), human31_positions(kick), atol=1e-6, rtol=0)
    y, msgs = _load(path, up="y")  # kept as read: lying along -y
    assert not msgs
    assert float(rest_up_direction(y)[1]) < -0.99
    with pytest.raises(ValueError, match=r"^up: expected one of"):
        load_motion(path, up="Z")


def test_feature_upright_files_untouched(cmu, hdm05):
    """Every bundled family reads as before: no clip is turned, nothing is warned."""
    for path in (cmu / "131_01.bvh", cmu / "01_01.bvh", cmu / "60_12_scaled.bvh",
                 cmu / "cmu21_kick.bvh", hdm05 / "HDM_bd_throwBasketball_001_120.amc"):
        clip, msgs = _load(path)
        assert not any("up" in m and "turned" in m for m in msgs), (path, msgs)
        ref = load_motion(path, up="y")
        assert torch.equal(clip.offsets, ref.offsets) and torch.equal(clip.rotations,
                                                                       ref.rotations)


def test_feature_tilted_rest_pose_is_left_alone(kick):
    """A rest pose 60 deg from +z and 30 deg from -y: no axis to snap to; unchanged, warned."""
    tilted = kick.change_basis(_rx(60.0))
    out, note = upright(tilted)
    assert out is tilted and "cannot be told" in note
    out, note = upright(kick.change_basis(_rx(30.0)))  # within 45 deg of +z: standing
    assert note is None


def test_feature_unmappable_skeleton_is_left_alone():
    clip = unseen_family_clip("mixamo", rename={"l_knee": "Gelenk7"}).change_basis(Y_UP_TO_Z_UP)
    out, note = upright(clip)
    assert out is clip and note is None and rest_up_direction(clip) is None


class TestChangeBasis:
    def test_positions_rotate_and_round_trip(self, kick):
        G = _rx(90.0) @ torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
        turned = kick.change_basis(G)
        torch.testing.assert_close(turned.global_positions(), kick.global_positions() @ G.T,
                                   atol=1e-12, rtol=0)
        back = turned.change_basis(G.T)
        torch.testing.assert_close(back.rotations, kick.rotations, atol=1e-12, rtol=0)
        torch.testing.assert_close(back.offsets, kick.offsets, atol=1e-12, rtol=0)

    @pytest.mark.parametrize("G", [torch.eye(3).double() * 2, torch.diag(torch.tensor(
        [1.0, 1.0, -1.0], dtype=torch.float64)), torch.eye(2).double()])
    def test_exception_not_a_rotation(self, kick, G):
        with pytest.raises(ValueError, match=r"^G: expected"):
            kick.change_basis(G)
