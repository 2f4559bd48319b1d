"""Fitting capsule radii to silhouettes: recovers a known scale, improves the IoU, checkpoints."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.filters.tracking.body_fit import SilhouetteBodyFit, hull_filtered_masks
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parents[2] / "likelihoods"))
from oracle import capsule_masks  # noqa: E402


def test_recovers_thicker_limbs():
    sk = human31()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_shoulder_abd")] = 0.8
    th[sk.dof_index("r_elbow_flex")] = 1.0
    truth = CapsuleBody(sk).float()
    names = truth.bone_names
    scale = torch.tensor([1.5 if ("elbow" in n or "wrist" in n) else 1.0 for n in names])
    truth.radii.mul_(scale)
    masks = capsule_masks(truth, rig, th)
    body = CapsuleBody(sk).float()
    fit = SilhouetteBodyFit(body, rig, iterations=60, stride=2)
    info = fit(th, Frame(index=0, time=0.0, silhouettes=masks))
    assert info["iou_after"] > info["iou_before"] + 0.01
    assert info["iou_after"] > 0.98 and info["kept"]
    assert info["scales"]["elbow"] == pytest.approx(1.5, rel=0.1)  # upper arms
    assert info["scales"]["wrist"] == pytest.approx(1.5, rel=0.1)  # forearms
    assert info["scales"]["knee"] == pytest.approx(1.0, rel=0.1)  # thighs unchanged
    arm = [i for i, n in enumerate(names) if "elbow" in n]
    assert torch.allclose(body.radii[arm], truth.radii[arm], rtol=0.12)  # changed in place
    with pytest.raises(ValueError, match="min_scale"):
        SilhouetteBodyFit(body, rig, min_scale=1.5)
    with pytest.raises(ValueError, match="silhouettes"):
        fit(th, Frame(index=0, time=0.0))


def test_bounds_hold_over_repeated_fits():
    """Limbs twice as thick as the model, bounds at 1.3: one call stops at the bound, and a
    second call (a refit pass) cannot go past it — the bound is on the total scale."""
    sk, rig, th, truth, _, _ = _arm_out_scene()
    arm = [i for i, n in enumerate(truth.bone_names) if "elbow" in n or "wrist" in n]
    truth.radii[arm] *= 2.0
    frame = Frame(index=0, time=0.0, silhouettes=capsule_masks(truth, rig, th))
    body = CapsuleBody(sk).float()
    r_init = body.radii.clone()
    fit = SilhouetteBodyFit(body, rig, iterations=20, stride=2, max_scale=1.3, lr=0.1)
    first = fit(th, frame)
    assert first["scales"]["wrist"] == pytest.approx(1.3, rel=1e-3)
    second = fit(th, frame)
    ratio = body.radii / r_init
    assert float(ratio.max()) <= 1.3 + 1e-4, ratio
    assert second["scales"]["wrist"] == pytest.approx(1.0, abs=1e-4)  # no room left
    assert second["total_scales"]["wrist"] == pytest.approx(1.3, rel=1e-3)


def _disc(mask: torch.Tensor, centre, radius: float) -> None:
    """Paint a filled disc of ``radius`` pixels at ``centre (u, v)`` into ``mask (H, W)``."""
    H, W = mask.shape
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    mask |= (u - float(centre[0])) ** 2 + (v - float(centre[1])) ** 2 <= radius**2


def _arm_out_scene():
    """human31 with the left arm raised and the pelvis turned, seen by a 4-camera ring: the
    skeleton, rig, pose, the capsule body the masks are rendered from, its masks
    ``(C, H, W)`` and the left wrist's pixel in every view ``(C, 2)``."""
    sk = human31()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_shoulder_abd")] = 1.2
    th[sk.dof_index("pelvis_rz")] = 0.4
    truth = CapsuleBody(sk).float()
    pix, _, _ = rig.project(sk(th[None].float()).positions[0, [sk.joint_index("l_wrist")]])
    return sk, rig, th, truth, capsule_masks(truth, rig, th), pix[:, 0]


def test_a_fit_that_lowers_the_hard_iou_is_undone():
    """From the true radii, with two clutter blobs beside the left forearm in two views, the
    soft-IoU optimum at stride 2 lowers the hard IoU: the fit is undone, the body untouched."""
    sk, rig, th, _, masks, wrist = _arm_out_scene()
    for c in (0, 1):
        _disc(masks[c], wrist[c] + torch.tensor([5.0, 0.0]), 6.0)
    body = CapsuleBody(sk, axis_offsets={"head_top": [0.0, -0.02, 0.0]}).float()
    r0, off0 = body.radii.clone(), body.axis_offsets.clone()
    info = SilhouetteBodyFit(body, rig, iterations=60, stride=2, offsets=["head_top"])(
        th, Frame(index=0, time=0.0, silhouettes=masks))
    assert not info["kept"]
    assert info["iou_after"] == pytest.approx(info["iou_before"], abs=1e-9)
    assert torch.equal(body.radii, r0) and torch.equal(body.axis_offsets, off0)
    assert set(info["scales"].values()) == {1.0}
    assert info["energy_after"] == info["energy_before"]
    from torchmocap.evaluation import summarize_diagnostics
    from torchmocap.filters import FrameInfo

    assert summarize_diagnostics([FrameInfo(0, body_fit=info)])["body_fit"]["kept"] == [False]


def test_recovers_a_head_in_front_of_the_neck():
    """Masks of a body whose head capsule sits 5 cm in front of its bone: the fit with
    ``offsets=["head_top"]`` moves the model's head there; without it no offset is fitted."""
    sk = human31()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("pelvis_rz")] = 0.5  # not facing a camera square on
    th[sk.dof_index("neck_flex")] = 0.3
    truth = CapsuleBody(sk, axis_offsets={"head_top": [0.0, -0.05, 0.0]}).float()
    frame = Frame(index=0, time=0.0, silhouettes=capsule_masks(truth, rig, th))
    body = CapsuleBody(sk).float()
    info = SilhouetteBodyFit(body, rig, iterations=80, stride=2, offsets=["head_top"],
                             offset_prior=0.0)(th, frame)
    got = body.axis_offsets[body.bone_names.index("head_top")]
    assert float(got[1]) == pytest.approx(-0.05, abs=0.012), got
    assert float(got[[0, 2]].abs().max()) < 0.012, got
    assert info["offsets"]["head_top"] == pytest.approx(got.tolist(), abs=1e-4)
    assert info["iou_after"] > info["iou_before"] + 0.005
    others = [i for i, b in enumerate(body.bone_names) if b != "head_top"]
    assert not bool(body.axis_offsets[others].any())
    plain = CapsuleBody(sk).float()
    info = SilhouetteBodyFit(plain, rig, iterations=20, stride=2)(th, frame)
    assert "offsets" not in info and not plain.has_axis_offsets
    with pytest.raises(ValueError, match="offsets: unknown bones"):
        SilhouetteBodyFit(plain, rig, offsets=["nose"])
    with pytest.raises(ValueError, match="max_offset"):
        SilhouetteBodyFit(plain, rig, offsets=["head_top"], max_offset=0.0)


def test_hull_filter_keeps_the_foreground_all_views_agree_on():
    """Clutter blobs in two of four views — one far from the body, one beside the left forearm
    (not consistent in 3D): ``hull_filter`` removes the far ones completely and most of the
    near ones, never adds foreground, and the fit reports what it saw."""
    sk, rig, th, truth, clean, wrist = _arm_out_scene()
    masks = clean.clone()
    far = torch.zeros_like(masks)
    for c in (0, 1):
        _disc(masks[c], wrist[c] + torch.tensor([10.0, 0.0]), 11.0)
        _disc(far[c], torch.tensor([20.0 + 30 * c, 200.0]), 15.0)  # a corner of the image
    assert not bool((far & clean).any())
    masks |= far
    frame = Frame(index=0, time=0.0, silhouettes=masks)

    def iou(a, b):
        return float((a & b).sum() / (a | b).sum())

    body = CapsuleBody(sk).float()
    fit = SilhouetteBodyFit(body, rig, iterations=20, stride=2, hull_filter=True)
    ends = truth.endpoints(sk(th[None].float()))
    filtered, hull = fit._hull_filtered(masks, None, ends, truth.radii)
    assert hull["applied"] and hull["views"] == 4
    assert not bool((filtered & ~masks).any())  # only removes foreground
    assert not bool((filtered & far).any())  # the far blobs are gone
    assert iou(filtered, clean) > 0.93 > 0.86 > iou(masks, clean)
    assert iou(filtered[2:], clean[2:]) > 0.97  # the views without clutter barely touched
    info = fit(th, frame)
    h = info["hull"]
    assert h["applied"]
    assert h["foreground_kept"] == pytest.approx(float(filtered.sum() / masks.sum()), abs=1e-3)
    assert h["iou_before"] > info["iou_before"]  # the filtered masks fit the body better
    import json

    from torchmocap.evaluation import summarize_diagnostics
    from torchmocap.filters import FrameInfo

    m = json.loads(json.dumps(summarize_diagnostics([FrameInfo(0, body_fit=info)])))["body_fit"]
    assert m["hull"] == pytest.approx(h)  # metrics.json reports what the fit saw
    assert "hull_filter=True" in repr(fit)
    plain = SilhouetteBodyFit(CapsuleBody(sk).float(), rig, iterations=5, stride=2)
    assert "hull" not in plain(th, frame)
    # fewer than two valid views: the masks are used as given, and the info says so
    valid = torch.tensor([True, False, False, False])
    same, h1 = fit._hull_filtered(masks, valid, ends, truth.radii)
    assert not h1["applied"] and "1 valid view" in h1["reason"] and same is masks
    with pytest.raises(ValueError, match="hull_voxel"):
        SilhouetteBodyFit(body, rig, hull_filter=True, hull_voxel=0.0)
    with pytest.raises(ValueError, match="hull_margin"):
        SilhouetteBodyFit(body, rig, hull_filter=True, hull_margin=-0.1)
    with pytest.raises(ValueError, match="hull_filter"):
        SilhouetteBodyFit(body, rig, hull_filter="yes")


def test_tracker_refit_passes_alternate_pose_and_body():
    """Coarse to fine on the first frame (``refit_passes``): pose refined with the fitted body,
    kept only when its energy is lower, body refitted; a real_frame_hull preset in small."""
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.filters import Tracker

    sk = human31().float()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_shoulder_abd")] = 1.4
    truth = CapsuleBody(sk).float()
    truth.radii.mul_(1.3)
    frame = Frame(index=0, time=0.0, silhouettes=capsule_masks(truth, rig, th))
    rt = Runtime(skeleton=sk, body=CapsuleBody(sk).float(), rig=rig)
    cfg = tracker_config("real_frame_hull", [
        "tracker.num_particles=40", "tracker.inference.layers=4", "tracker.inference.rounds=1",
        "tracker.body_fit.iterations=10", "tracker.body_fit.stride=4"])
    tr = build_tracker(cfg, rt, seed=0)
    assert tr.body_fit is not None and tr.body_fit.refit_passes == 1
    start = th.clone()
    start[sk.dof_index("l_shoulder_abd")] = 0.0  # the arm down
    state = tr.init(start[None], frame)
    info = state.infos[0]
    (p,) = info.refit
    assert p["energy_after"] < p["energy_before"] or not p["kept"]
    assert p["body_fit"]["iou_after"] >= info.body_fit["iou_after"] - 0.01
    # the body was fitted in place: each pass scales the radii the previous one left, within
    # the bounds on the total scale
    ratio = rt.body.radii / CapsuleBody(sk).float().radii
    fit = tr.body_fit
    s1, s2 = info.body_fit["scales"], p["body_fit"]["scales"]
    expected = torch.tensor([s1[fit.segments[i]] * s2[fit.segments[i]]
                             for i in fit.segment_index.tolist()])
    assert ratio == pytest.approx(expected, rel=2e-3)
    total = p["body_fit"]["total_scales"]
    assert ratio == pytest.approx(torch.tensor([total[fit.segments[i]]
                                                for i in fit.segment_index.tolist()]), rel=2e-3)
    assert fit.min_scale - 1e-4 <= float(ratio.min()) <= float(ratio.max()) <= fit.max_scale + 1e-4
    assert not torch.allclose(ratio, torch.ones_like(ratio))
    # the preset frees the head capsule from the neck's axis: the offset is in the body
    off = p["body_fit"]["offsets"]["head_top"]
    assert rt.body.axis_offsets[rt.body.bone_names.index("head_top")].tolist() == pytest.approx(
        off, abs=1e-4)
    # metrics.json reports the fit: IoU before the first fit, after the last pass, JSON-clean
    import json

    from torchmocap.evaluation import summarize_diagnostics

    m = json.loads(json.dumps(summarize_diagnostics(state.infos)))["body_fit"]
    assert m["passes"] == 2
    # timings: the fits' own seconds add up to the reported total, and the first frame's
    # seconds cover the refinement, the fits and the refit's inference
    fit_s = info.body_fit["seconds"] + p["body_fit"]["seconds"]
    assert m["seconds"] == pytest.approx(fit_s)
    assert info.seconds > fit_s + p["seconds"] - p["body_fit"]["seconds"] > 0
    assert m["iou_before"] == pytest.approx(info.body_fit["iou_before"])
    assert m["iou_after"] == pytest.approx(p["body_fit"]["iou_after"])
    assert m["iou_after"] > m["iou_before"]
    assert m["scales"] == pytest.approx(p["body_fit"]["scales"])
    assert m["total_scales"] == pytest.approx(total)
    with pytest.raises(ValueError, match="refit_passes"):
        SilhouetteBodyFit(CapsuleBody(sk), rig, refit_passes=-1)
    with pytest.raises(ValueError, match="refit_scale"):
        SilhouetteBodyFit(CapsuleBody(sk), rig, refit_scale=0.0)
    with pytest.raises(TypeError, match="body_fit: expected a torchmocap.filters.tracking."
                                        "body_fit.BodyFit"):
        Tracker(sk, tr.predictor, tr.proposal, tr.likelihood, tr.inference, tr.estimator,
                body_fit=lambda theta, frame: {})


def test_checkpoint_keeps_the_fitted_body(tmp_path):
    """Radii and axis offsets fitted at the start are in the checkpoint: a resumed run tracks
    with the same body."""
    from torchmocap.assembly import Runtime, build_tracker, tracker_config
    from torchmocap.filters import TrackState

    sk = human31().float()
    rig = make_ring_rig(4).float()
    rt = Runtime(skeleton=sk, body=CapsuleBody(sk).float(), rig=rig)
    cfg = tracker_config("g", ["+body_fit@tracker.body_fit=silhouette",
                               "tracker.body_fit.offsets=[head_top]"])
    tr = build_tracker(cfg, rt, seed=0)
    assert tr.body_fit.offset_bones == ["head_top"]
    fitted_r = rt.body.radii * 1.2
    fitted_o = torch.zeros_like(rt.body.axis_offsets)
    fitted_o[rt.body.bone_names.index("head_top")] = torch.tensor([0.0, -0.04, -0.01])
    rt.body.radii.copy_(fitted_r)
    rt.body.axis_offsets.copy_(fitted_o)
    state = TrackState(history=sk.zero_pose()[None], frame=0,
                       generator_state=torch.Generator().get_state())
    path = str(tmp_path / "ckpt.pt")
    tr.save_checkpoint(state, path)
    rt.body.radii.div_(1.2)
    rt.body.axis_offsets.zero_()
    tr.load_checkpoint(path)
    torch.testing.assert_close(rt.body.radii, fitted_r)
    torch.testing.assert_close(rt.body.axis_offsets, fitted_o)


@pytest.mark.parametrize("case", ["inverted", "all"])
def test_implausible_masks_give_a_warning(case):
    """Inverted or all-foreground masks were fitted to an IoU of 0.03-0.3 without a word; a
    plausible fit (the same body's masks) gives none."""
    import warnings

    sk, rig, th, truth, masks, _ = _arm_out_scene()
    bad = ~masks if case == "inverted" else torch.ones_like(masks)
    fit = SilhouetteBodyFit(CapsuleBody(sk).float(), rig, iterations=5, stride=2)
    with pytest.warns(UserWarning, match=r"body_fit: the silhouette IoU of the fitted body is "
                                         r"0\.\d\d, far below"):
        info = fit(th, Frame(index=0, time=0.0, silhouettes=bad))
    assert info["iou_after"] < 0.3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ok = SilhouetteBodyFit(CapsuleBody(sk).float(), rig, iterations=5, stride=2)
        assert ok(th, Frame(index=0, time=0.0, silhouettes=masks))["iou_after"] > 0.9


def test_hull_tolerance_keeps_one_views_hole_its_own():
    """A hole across the left forearm of view 0 carves the all-views hull, so the filtered masks
    lose that piece of the forearm in the other views too; with ``tolerance=1`` the other views
    keep their foreground, view 0 keeps its hole (the filter never adds foreground), and a blob
    only view 1 sees, far from the body, is still removed."""
    sk, rig, th, truth, clean, wrist = _arm_out_scene()
    elbow = rig.project(sk(th[None].float()).positions[0, [sk.joint_index("l_elbow")]])[0][:, 0]
    masks = clean.clone()
    hole = torch.zeros_like(masks[0])
    _disc(hole, 0.5 * (wrist[0] + elbow[0]), 8.0)
    hole &= clean[0]
    assert int(hole.sum()) > 50
    masks[0] &= ~hole
    far = torch.zeros_like(masks[1])
    _disc(far, torch.tensor([25.0, 210.0]), 14.0)
    assert not bool((far & clean[1]).any())
    masks[1] |= far
    ends = truth.endpoints(sk(th[None].float()))
    strict, hs = hull_filtered_masks(rig, masks, None, ends, truth.radii, 0.3, 0.02)
    loose, hl = hull_filtered_masks(rig, masks, None, ends, truth.radii, 0.3, 0.02,
                                    tolerance=1)
    assert hs["applied"] and hl["applied"] and hl["tolerance"] == 1
    lost = [float((clean[c] & ~strict[c].bool()).sum()) for c in (1, 2, 3)]
    kept = [float((clean[c] & ~loose[c].bool()).sum()) for c in (1, 2, 3)]
    assert max(lost) > 30  # the hole of view 0 carved another view's torso
    assert max(kept) < 0.25 * max(lost)
    assert not bool((loose.bool() & ~masks).any())  # only removes foreground
    assert bool((loose[0].bool() & hole).sum() == 0)  # view 0's hole stays
    assert not bool((loose[1].bool() & far).any())  # the far blob is removed
    with pytest.raises(ValueError, match="tolerance"):
        hull_filtered_masks(rig, masks, None, ends, truth.radii, 0.3, 0.02, tolerance=-1)
    one = torch.tensor([True, True, False, False])
    same, info = hull_filtered_masks(rig, masks, one, ends, truth.radii, 0.3, 0.02, tolerance=1)
    assert not info["applied"] and "needs 3" in info["reason"] and same is masks


def test_hull_reach_drops_what_is_consistent_but_off_the_body():
    """A second body 1.2 m beside the subject is seen by every view — consistent in 3D, so the
    hull keeps it; with ``reach`` only the voxels near the subject's capsules stay: the second
    body is gone and the subject's own foreground is kept."""
    sk, rig, th, truth, clean, _ = _arm_out_scene()
    other = th.clone()
    other[0] += 1.2
    second = capsule_masks(truth, rig, other)
    assert float((second & ~clean).sum()) > 500
    masks = clean | second
    ends = truth.endpoints(sk(th[None].float()))
    kept, info = hull_filtered_masks(rig, masks, None, ends, truth.radii, 1.5, 0.02)
    near, info_r = hull_filtered_masks(rig, masks, None, ends, truth.radii, 1.5, 0.02,
                                       reach=0.08)
    off = second & ~clean
    assert float((kept.bool() & off).sum()) > 0.8 * float(off.sum())  # consistent: kept
    # off the body: gone, but where it borders the subject in a view (within reach)
    assert float((near.bool() & off).sum()) < 0.1 * float(off.sum())
    own = float((near.bool() & clean).sum()) / float(clean.sum())
    assert own > 0.97
    assert info_r["reach"] == 0.08 and info_r["voxels_off_the_body"] > 0.2
    assert "reach" not in info
    with pytest.raises(ValueError, match="reach"):
        hull_filtered_masks(rig, masks, None, ends, truth.radii, 0.3, 0.02, reach=0.0)
