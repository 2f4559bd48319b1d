"""The gauge of a refinement from the subject: a similarity of the whole scene changes no pixel
and no loss; the refinement's constraints remove exactly those 7 directions (and the common
time shift); without them the reduced normal matrix is singular along 7 directions; a refined
rig does not drift (mean rotation update zero, mean centre and mean distance kept, or a
reference camera unmoved) and the refinement of a transformed scene is the transformed
refinement."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.cameras import (
    CameraRig,
    RigParametrization,
    RobustLoss,
    bundle_adjust,
    gauge_constraints,
    make_ring_rig,
    reprojection_loss,
)
from torchmocap.cameras.bundle_adjustment import _Problem, _reduced_system
from torchmocap.cameras.rig_gauge import similarity_tangents
from torchmocap.cameras.rig_priors import RigPriors
from torchmocap.geometry import random_rotation_matrix

from .calibration_scenes import make_scene


def _similarity(seed=0):
    g = torch.Generator().manual_seed(seed)
    Q = random_rotation_matrix(1, generator=g, dtype=torch.float64)[0]
    s = 0.5 + float(torch.rand(1, generator=g))
    d = torch.randn(3, generator=g, dtype=torch.float64)
    return s, Q, d


def _moved(rig: CameraRig, s, Q, d) -> CameraRig:
    """The rig after the world moved by ``x -> s Q x + d``."""
    R = rig.R.double() @ Q.T
    c = s * rig.camera_centers().double() @ Q.T + d
    t = -(R @ c[..., None])[..., 0]
    return CameraRig(rig.K.double(), R, t, rig.image_size, rig.dist.double(), rig.names)


class TestGaugeConstraints:
    def test_cardinality(self):
        rig = make_ring_rig(4)
        cases = {("rotation", "translation"): 7, ("translation",): 4, ("rotation",): 0,
                 ("rotation", "focal"): 0, ("rotation", "translation", "time_offset"): 8,
                 ("focal", "time_offset"): 1}
        for groups, rows in cases.items():
            par = RigParametrization(rig, groups)
            assert par.constraints.shape == (rows, par.num_free), groups
            assert par.num_parameters == par.num_free - rows
        par = RigParametrization(rig, ("rotation", "translation", "time_offset"), gauge="none",
                                 time_gauge="none")
        assert par.constraints.shape[0] == 0 and par.num_parameters == par.num_free
        G = gauge_constraints(par, 2, 1)
        assert G.shape == (8, par.num_free)

    @pytest.mark.parametrize("gauge", ["mean", 0, 3])
    def test_feature_constraints_are_transverse_to_the_similarity(self, gauge):
        """Each of the 7 similarity directions is removed: the constraints see all of them
        (``G T`` has rank 7) and no combination of them is left in the solver's space."""
        par = RigParametrization(make_ring_rig(4), ("rotation", "translation", "focal"), gauge)
        tangents = similarity_tangents(par)  # (7, n_z)
        assert int(torch.linalg.matrix_rank(par.constraints @ tangents.T)) == 7
        both = torch.cat([par.basis, tangents.T], 1)
        assert int(torch.linalg.matrix_rank(both)) == par.num_free
        # the solver's space is orthogonal to the constraints (in the scaled parameters)
        assert float((par.constraints @ par.basis).abs().max()) < 1e-12

    def test_feature_reference_camera_does_not_move(self):
        par = RigParametrization(make_ring_rig(3), ("rotation", "translation", "focal"), gauge=1)
        g = torch.Generator().manual_seed(0)
        v = par.values(torch.randn(par.num_parameters, generator=g, dtype=torch.float64))
        assert float(v[1, :6].abs().max()) < 1e-12 and float(v[1, 6].abs()) > 0


class TestSimilarityInvariance:
    def test_feature_no_pixel_and_no_loss_changes(self):
        """Moving the world and every camera by a similarity leaves the loss (and so every
        pixel) as it was, at zero and at non-zero refinement values (transformed with it)."""
        sc = make_scene(0, T=5, K=6)
        s, Q, d = _similarity(1)
        moved = _moved(sc.perturbed, s, Q, d)
        X = sc.trajectory(torch.arange(5.0))
        Xm = s * X @ Q.T + d
        loss = RobustLoss(scale_px=5.0)
        par, parm = RigParametrization(sc.perturbed), RigParametrization(moved)
        v = torch.zeros(4, 13, dtype=torch.float64)
        v[:, 0:3] = 0.02 * torch.randn(4, 3, dtype=torch.float64)
        v[:, 3:6] = 0.03 * torch.randn(4, 3, dtype=torch.float64)
        v[:, 6:8] = 0.01
        vm = v.clone()
        vm[:, 0:3] = v[:, 0:3] @ Q.T  # world-axis rotation vectors turn with the world
        vm[:, 3:6] = s * v[:, 3:6] @ Q.T
        for a, b in ((torch.zeros_like(v), torch.zeros_like(v)), (v, vm)):
            la = reprojection_loss(X, sc.detections, *par.camera_tensors(a), loss=loss)
            lb = reprojection_loss(Xm, sc.detections, *parm.camera_tensors(b), loss=loss)
            torch.testing.assert_close(la, lb, rtol=1e-9, atol=0)

    def test_feature_refinement_commutes_with_the_similarity(self):
        """Refining the moved scene gives the moved refinement: the same refined pixels and
        time offsets, the refined centres moved by the similarity (priors in metres scaled)."""
        sc = make_scene(2, T=16, K=12, offsets=(0.0, 0.5, -0.3, 0.2))
        s, Q, d = _similarity(3)
        groups = ("rotation", "translation", "focal", "time_offset")
        # converged tightly (a squared loss: Gauss–Newton converges fast), so that what is
        # compared is the solution, not where two paths stopped
        kw = dict(loss=dict(kind="squared"), tolerance=1e-14, trajectory_acceleration=None,
                  noise_px=2.0)
        a = bundle_adjust(sc.detections, sc.perturbed, groups, **kw)
        b = bundle_adjust(sc.detections, _moved(sc.perturbed, s, Q, d), groups,
                          priors=RigPriors(translation_m=0.25 * s), **kw)
        assert a.converged and b.converged
        pa = a.rig.double().project(a.points)[0]
        pb = b.rig.double().project(b.points)[0]
        assert float((pa - pb).abs().max()) < 1e-4
        torch.testing.assert_close(b.time_offsets, a.time_offsets, atol=1e-6, rtol=0)
        torch.testing.assert_close(b.rig.camera_centers().double(),
                                   s * a.rig.camera_centers().double() @ Q.T + d, atol=1e-6,
                                   rtol=0)
        torch.testing.assert_close(b.rig.K.double(), a.rig.K.double(), atol=1e-5, rtol=0)
        torch.testing.assert_close(b.std[:, 6:], a.std[:, 6:], atol=1e-6, rtol=1e-4,
                                   equal_nan=True)


class TestGaugeFixing:
    def test_feature_without_gauge_seven_directions_are_free(self):
        """With free points and no priors, the reduced camera matrix has a 7-dimensional null
        space (the similarity) unless the gauge is held."""
        sc = make_scene(1, T=8, K=12)
        X = sc.trajectory(torch.arange(8.0))
        for gauge, nulls in (("none", 7), ("mean", 0), (2, 0)):
            par = RigParametrization(sc.rig, ("rotation", "translation", "focal"), gauge)
            loss = RobustLoss(kind="squared", min_confidence=0.0)
            w = loss.detection_weights(sc.detections[..., 2])
            widths = RigPriors(rotation_deg=None, translation_m=None,
                               focal_percent=None).widths(par)
            prob = _Problem(par, sc.detections[..., :2], w, loss, widths, False)
            y = torch.zeros(par.num_parameters, dtype=torch.float64)
            r, J_y, J_X, taps = prob.linearise(y, X)
            system = prob.normal_equations(y, X, r, J_y, J_X, taps, 2.0)
            S = _reduced_system(*system, 0.0)[0]
            # Jacobi-scaled, so the eigenvalues compare across parameter kinds
            dsc = S.diagonal().rsqrt()
            ev = torch.linalg.eigvalsh(dsc[:, None] * S * dsc[None, :])
            assert int((ev < 1e-7 * ev.max()).sum()) == nulls, (gauge, ev[:9])

    @pytest.mark.parametrize("gauge", ["mean", 1])
    def test_feature_no_drift(self, gauge):
        sc = make_scene(4, T=20, K=15)
        res = bundle_adjust(sc.detections, sc.perturbed, gauge=gauge,
                            priors=RigPriors(rotation_deg=None, translation_m=None))
        c0 = sc.perturbed.camera_centers().double()
        c1 = res.rig.camera_centers().double()
        if gauge == "mean":
            assert float(res.values[:, 0:3].sum(0).abs().max()) < 1e-10
            torch.testing.assert_close(c1.mean(0), c0.mean(0), atol=1e-9, rtol=0)
            # the RMS distance from the mean centre is kept to first order: its square grows
            # by exactly the mean squared centre update (second order)
            ms0 = ((c0 - c0.mean(0)) ** 2).sum(-1).mean()
            ms1 = ((c1 - c1.mean(0)) ** 2).sum(-1).mean()
            dc = ((c1 - c0) ** 2).sum(-1).mean()
            torch.testing.assert_close(ms1 - ms0, dc, atol=1e-10, rtol=0)
        else:
            torch.testing.assert_close(res.rig.R[1].double(), sc.perturbed.R[1].double(),
                                       atol=1e-12, rtol=0)
            torch.testing.assert_close(c1[1], c0[1], atol=1e-12, rtol=0)
        # the refinement moved the cameras all the same (it is not frozen)
        assert float((c1 - c0).norm(dim=-1).max()) > 5e-3
        assert math.isfinite(res.cost_final) and res.converged
