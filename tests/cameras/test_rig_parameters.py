"""The rig parametrisation of a refinement: zero values give the calibration back, every group
changes what it names (a rotation turns the camera about its own centre, focal / principal
point / k1 k2 change only the intrinsics), pixels are differentiable in every group's values
(gradcheck in float64), groups are checked by name, and the refined rig is a valid CameraRig."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.cameras import (
    RIG_GROUPS,
    CameraRig,
    RefinementError,
    RigParametrization,
    apply_rig_parameters,
    make_ring_rig,
    project_points,
    refinement_pixels,
)
from torchmocap.cameras.rig_parameters import NUM_VALUES, check_groups


def _rig(dist: bool = True) -> CameraRig:
    base = make_ring_rig(3, image_size=(640, 480)).double()
    d = torch.tensor([[-0.1, 0.02, 1e-3, -5e-4, 0.0]] * 3, dtype=torch.float64) if dist \
        else None
    K = base.K.clone()
    K[:, 0, 2] += torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64)
    return CameraRig(K, base.R, base.t, base.image_size, d, base.names)


def _points(n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(2, n, 3, generator=g, dtype=torch.float64) - 0.5) + torch.tensor(
        [0.0, 0.0, 1.0], dtype=torch.float64)


class TestApplyRigParameters:
    def test_smoke(self):
        rig = _rig()
        out = apply_rig_parameters(torch.zeros(3, NUM_VALUES, dtype=torch.float64), rig.K,
                                   rig.R, rig.t, rig.dist)
        for a, b in zip(out, (rig.K, rig.R, rig.t, rig.dist)):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=0)

    def test_feature_groups_change_what_they_name(self):
        rig = _rig()
        g = torch.Generator().manual_seed(1)
        v = torch.zeros(3, NUM_VALUES, dtype=torch.float64)
        v[:, 0:3] = 0.03 * torch.randn(3, 3, generator=g, dtype=torch.float64)
        K, R, t, d = apply_rig_parameters(v, rig.K, rig.R, rig.t, rig.dist)
        # a rotation turns the camera about its own centre: the centre stays
        c0 = -(rig.R.transpose(1, 2) @ rig.t[..., None])[..., 0]
        c1 = -(R.transpose(1, 2) @ t[..., None])[..., 0]
        torch.testing.assert_close(c1, c0, atol=1e-12, rtol=0)
        torch.testing.assert_close(K, rig.K)
        torch.testing.assert_close(d, rig.dist)
        # the rotation is applied in world axes: R' = R exp(w)
        from torchmocap.geometry import so3_exp
        torch.testing.assert_close(R, rig.R @ so3_exp(v[:, 0:3]))
        # the centre moves by the update, the rotation stays
        v = torch.zeros(3, NUM_VALUES, dtype=torch.float64)
        v[:, 3:6] = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
        _, R, t, _ = apply_rig_parameters(v, rig.K, rig.R, rig.t, rig.dist)
        torch.testing.assert_close(R, rig.R)
        torch.testing.assert_close(-(R.transpose(1, 2) @ t[..., None])[..., 0], c0 + v[:, 3:6])
        # focal (log-scale, the skew with fx), principal point, k1 k2
        v = torch.zeros(3, NUM_VALUES, dtype=torch.float64)
        v[:, 6], v[:, 7] = math.log(1.1), math.log(0.95)
        v[:, 8], v[:, 9] = 4.0, -3.0
        v[:, 10], v[:, 11] = 0.01, -0.02
        v[:, 12] = 0.7  # a time offset does not change a camera
        K, R, t, d = apply_rig_parameters(v, rig.K, rig.R, rig.t, rig.dist)
        torch.testing.assert_close(K[:, 0, 0], rig.K[:, 0, 0] * 1.1)
        torch.testing.assert_close(K[:, 1, 1], rig.K[:, 1, 1] * 0.95)
        torch.testing.assert_close(K[:, 0, 2], rig.K[:, 0, 2] + 4.0)
        torch.testing.assert_close(K[:, 1, 2], rig.K[:, 1, 2] - 3.0)
        torch.testing.assert_close(d[:, :2], rig.dist[:, :2] + torch.tensor([0.01, -0.02],
                                                                             dtype=d.dtype))
        torch.testing.assert_close(d[:, 2:], rig.dist[:, 2:])
        torch.testing.assert_close(R, rig.R)
        torch.testing.assert_close(t, rig.t)

    def test_exception(self):
        rig = _rig()
        with pytest.raises(RefinementError, match="values: expected shape"):
            apply_rig_parameters(torch.zeros(2, NUM_VALUES), rig.K, rig.R, rig.t, rig.dist)

    @pytest.mark.parametrize("group", [g for g in RIG_GROUPS if g != "time_offset"])
    def test_gradcheck(self, group):
        """Pixels are differentiable in each group's values, at zero (k1, k2 included: the
        projection runs through the lens polynomial) and away from it."""
        rig = _rig(dist=(group != "distortion"))
        par = RigParametrization(rig, (group,), gauge="none")
        X = _points()
        for scale in (0.0, 1.0):
            g = torch.Generator().manual_seed(3)
            y = (scale * torch.randn(par.num_parameters, generator=g, dtype=torch.float64)
                 ).requires_grad_()

            def pixels(y):
                K, R, t, d = par.camera_tensors(par.values(y))
                return refinement_pixels(X, K, R, t, d)

            assert torch.autograd.gradcheck(pixels, (y,), eps=1e-6, atol=1e-6)

    def test_feature_matches_project_points(self):
        """The refinement's projection is project_points' model (with distortion)."""
        rig = _rig()
        X = _points(20)
        pix = refinement_pixels(X, rig.K, rig.R, rig.t, rig.dist)
        ref = project_points(X, rig.K, rig.R, rig.t, rig.dist)[0]
        torch.testing.assert_close(pix, ref, atol=1e-9, rtol=0)
        per = refinement_pixels(X.expand(3, *X.shape), rig.K, rig.R, rig.t, rig.dist,
                                per_camera=True)
        torch.testing.assert_close(per, pix)


class TestRigParametrization:
    def test_smoke(self):
        par = RigParametrization(make_ring_rig(4).float())
        assert par.groups == ("rotation", "translation", "focal")
        assert (par.num_free, par.num_parameters) == (28, 21)  # 7 per camera, less 7
        assert par.free_names[:7] == ["ring0.rot_x", "ring0.rot_y", "ring0.rot_z",
                                      "ring0.centre_x", "ring0.centre_y", "ring0.centre_z",
                                      "ring0.log_f"]
        v = par.values(torch.zeros(par.num_parameters, dtype=torch.float64))
        assert v.shape == (4, 13) and bool((v == 0).all())
        rig = par.refined_rig(v)
        assert isinstance(rig, CameraRig) and rig.K.dtype == torch.float32  # the given dtype
        torch.testing.assert_close(rig.K, make_ring_rig(4).float().K)

    def test_cardinality(self):
        rig = make_ring_rig(3)
        counts = {"rotation": 3, "translation": 3, "focal": 1, "focal_xy": 2,
                  "principal_point": 2, "distortion": 2, "time_offset": 1}
        for g, n in counts.items():
            assert RigParametrization(rig, (g,), gauge="none",
                                      time_gauge="none").num_free == 3 * n
        par = RigParametrization(rig, tuple(g for g in RIG_GROUPS if g != "focal"))
        assert par.num_free == 3 * 13 and par.num_parameters == 3 * 13 - 8

    def test_feature_focal_is_shared(self):
        par = RigParametrization(make_ring_rig(2), ("focal",), gauge="none")
        v = par.values(torch.tensor([0.1, -0.2], dtype=torch.float64))
        assert torch.equal(v[:, 6], v[:, 7])
        par = RigParametrization(make_ring_rig(2), ("focal_xy",), gauge="none")
        v = par.values(torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64))
        assert not torch.equal(v[:, 6], v[:, 7])
        torch.testing.assert_close(par.free_values(v), par.basis @ torch.tensor(
            [1.0, 2.0, 3.0, 4.0], dtype=torch.float64))

    def test_exception(self):
        rig = make_ring_rig(2)
        with pytest.raises(RefinementError, match="unknown parameter group 'skew'"):
            RigParametrization(rig, ("rotation", "skew"))
        with pytest.raises(RefinementError, match="exclude each other"):
            check_groups(("focal", "focal_xy"))
        with pytest.raises(RefinementError, match="named twice"):
            check_groups(("rotation", "rotation"))
        with pytest.raises(RefinementError, match="at least one group"):
            check_groups(())
        with pytest.raises(RefinementError, match="groups: expected a sequence"):
            check_groups(3)
        with pytest.raises(RefinementError, match="rig: expected a CameraRig"):
            RigParametrization("rig.toml")
        with pytest.raises(RefinementError, match="gauge: expected 'mean', 'none' or"):
            RigParametrization(rig, gauge=5)
        with pytest.raises(RefinementError, match="time_gauge"):
            RigParametrization(rig, ("time_offset",), time_gauge="first")
        par = RigParametrization(rig)
        with pytest.raises(RefinementError, match="y: expected shape"):
            par.values(torch.zeros(3, dtype=torch.float64))

    def test_feature_single_group_name(self):
        assert RigParametrization(make_ring_rig(2), "rotation", gauge="none").num_free == 6
