"""Leading reference-pose frames (``skip_frames="auto"``): found on real files, never on motion."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchmocap.io import load_motion
from torchmocap.io.trim import leading_reference_frames


def _load(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clip = load_motion(path, **kw)
    return clip, [str(w.message) for w in caught]


def _with_leading_rest(clip, n):
    """``clip`` with ``n`` frames of its rest pose (identity rotations, first root position)
    put in front, as exporters write a T-pose frame 0."""
    rest = torch.eye(3, dtype=clip.rotations.dtype).expand(n, clip.num_joints, 3, 3)
    return type(clip)(
        joint_names=clip.joint_names, parents=clip.parents, offsets=clip.offsets,
        rotations=torch.cat([rest, clip.rotations]),
        root_translation=torch.cat([clip.root_translation[:1].expand(n, 3),
                                    clip.root_translation]),
        fps=clip.fps, axes=clip.axes, skeleton_family=clip.skeleton_family)


def test_feature_cgspeed_t_pose_frame_dropped(cmu):
    """The cgspeed MotionBuilder BVH of CMU 01_01 starts with a synthetic T-pose: auto drops
    exactly that frame (70 cm from frame 1 against at most 2.8 cm per frame later)."""
    auto, msgs = _load(cmu / "01_01.bvh", skip_frames="auto")
    one = load_motion(cmu / "01_01.bvh", skip_frames=1)
    assert auto.num_frames == one.num_frames
    assert torch.equal(auto.rotations, one.rotations)
    assert any("skipped the first 1 frame(s)" in m and "71 cm" in m for m in msgs), msgs


@pytest.mark.parametrize("name", ["131_01.bvh", "cmu21_kick.bvh", "cmu21_jump-across.bvh",
                                  "cmu21_box-1.bvh", "01_01.amc"])
def test_feature_motion_is_kept(cmu, name):
    """Takes that start in motion — fast kicks, jumps and punches among them — lose nothing."""
    auto, msgs = _load(cmu / name, skip_frames="auto")
    assert auto.num_frames == load_motion(cmu / name).num_frames
    assert not any("skipped" in m for m in msgs)


@pytest.mark.parametrize("n", [1, 3])
def test_feature_prepended_rest_frames(cmu, n):
    kick = load_motion(cmu / "cmu21_kick.bvh")
    lead = leading_reference_frames(_with_leading_rest(kick, n))
    assert lead.count == n and lead.jump > 0.15


def test_short_clip_is_never_trimmed(cmu):
    kick = load_motion(cmu / "cmu21_kick.bvh").slice(0, 15)
    assert leading_reference_frames(_with_leading_rest(kick, 1)).count == 0


@pytest.mark.parametrize("bad", [-1, 1.5, "1", True, None])
def test_exception_skip_frames(cmu, bad):
    with pytest.raises(ValueError, match=r"skip_frames"):
        load_motion(cmu / "cmu21_kick.bvh", skip_frames=bad)


@pytest.mark.parametrize("kw", [{"max_frames": 0}, {"max_frames": 2.5}, {"min_jump": -0.1},
                                {"factor": float("nan")}, {"factor": True}])
def test_exception_settings(cmu, kw):
    with pytest.raises(ValueError, match=rf"^{next(iter(kw))}: expected"):
        leading_reference_frames(load_motion(cmu / "cmu21_kick.bvh"), **kw)
