"""Self-calibration of recordings (``data.calibration``, ``torchmocap-calibrate``): the settings
and their errors, the refined range, the detections resampled onto the subject's clock, the
written calibration read back, the loader on the trimmed real recording (a rig perturbed by
known amounts comes back), and the model objective on a synthesised skeleton scene."""

from __future__ import annotations

import math
import shutil
import warnings

import pytest
import torch

from torchmocap.cameras import (
    apply_rig_parameters,
    make_ring_rig,
    read_calibration,
    refinement_pixels,
    rig_from_dict,
    triangulate_dlt,
)
from torchmocap.data.recordings.loader import calibrate_recording, load_recording
from torchmocap.data.recordings.self_calibration import (
    calibration_settings,
    refine_range,
    refine_rig,
    shift_detections,
    write_refinement,
)


def _quiet(fn, *args, **kw):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        return fn(*args, **kw)


class TestSettings:
    def test_smoke(self):
        s = calibration_settings(None)
        assert s["refine"] is False and s["objective"] == "bundle"
        assert s["groups"] == ["rotation", "translation"]

    def test_feature_groups_canonical(self):
        s = calibration_settings({"groups": ["time_offset", "rotation"]})
        assert s["groups"] == ["rotation", "time_offset"]

    @pytest.mark.parametrize("given, match", [
        ({"refine": "yes"}, r"data\.calibration\.refine"),
        ({"objective": "joint"}, r"data\.calibration\.objective.*bundle"),
        ({"groups": ["rotation", "zoom"]}, r"data\.calibration\.groups.*'zoom'"),
        ({"frames": [10, 5]}, r"data\.calibration\.frames"),
        ({"frames": [0]}, r"data\.calibration\.frames"),
        ({"priors": {"rotation": 1.0}}, r"data\.calibration\.priors"),
        ({"loss": {"scale_px": -1}}, r"data\.calibration\.loss.*scale_px"),
        ({"iterations": 0}, r"data\.calibration\.iterations"),
        ({"file": 3}, r"data\.calibration\.file"),
        ({"rotation": True}, r"data\.calibration: unknown setting"),
    ])
    def test_exception(self, given, match):
        with pytest.raises(ValueError, match=match):
            calibration_settings(given)


class TestRange:
    def test_feature_default_first_half(self):
        s = calibration_settings(None)
        assert refine_range(s, range(20, 100), 100) == range(20, 60)
        assert refine_range(s, range(0, 1000), 1000) == range(0, 300)

    def test_feature_given_outside_loaded(self):
        s = calibration_settings({"frames": [0, 60]})
        assert refine_range(s, range(60, 100), 100) == range(0, 60)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"data\.calibration\.frames.*beyond the "
                                             r"recording's 50 frames"):
            refine_range(calibration_settings({"frames": [0, 60]}), range(0, 50), 50)
        with pytest.raises(ValueError, match="at least 4"):
            refine_range(calibration_settings({"frames": [3, 5]}), range(0, 50), 50)


class TestShift:
    def test_feature_linear_motion_recovered(self):
        T = 12
        u = torch.arange(T, dtype=torch.float64)[:, None, None].expand(T, 2, 3) * 4.0
        det = torch.stack([u, u + 1, torch.ones_like(u)], -1)  # (T, C=2, K=3, 3)
        # camera 1 runs 0.25 frame ahead: its frame t shows the subject at t + 0.25
        ahead = det.clone()
        ahead[:, 1, :, 0] += 0.25 * 4.0
        ahead[:, 1, :, 1] += 0.25 * 4.0
        out = shift_detections(ahead, torch.tensor([0.0, 0.25]))
        assert torch.allclose(out[1:, 1], det[1:, 1], atol=1e-12)
        assert torch.equal(out[:, 0], ahead[:, 0])

    def test_feature_missed_stays_missed(self):
        det = torch.ones(6, 1, 2, 3)
        det[3, 0, 1] = 0.0
        out = shift_detections(det, torch.tensor([0.5]))
        assert out[3, 0, 1, 2] == 0 and out[4, 0, 1, 2] == 0  # both taps of frame 3.5 / 2.5
        assert out[3, 0, 0, 2] == 1

    def test_feature_zero_offset_identity(self):
        det = torch.rand(5, 3, 4, 3)
        assert torch.equal(shift_detections(det, torch.zeros(3)), det)


def _perturbed_copy(root, tmp_path, values):
    """A copy of the trimmed recording whose calibration is moved by ``values (C, 13)``."""
    from torchmocap.cameras import write_toml_calibration

    dst = tmp_path / "rec"
    shutil.copytree(root, dst, ignore=shutil.ignore_patterns("background", "pose2sim_output"))
    rig = read_calibration(dst / "calibration" / "Calib.toml").double()
    K, R, t, d = apply_rig_parameters(values, rig.K, rig.R, rig.t, rig.dist)
    from torchmocap.cameras import CameraRig

    bad = CameraRig(K, R, t, rig.image_size, d, rig.names)
    write_toml_calibration(bad, dst / "calibration" / "Calib.toml")
    return dst, rig, bad


def _heldout_dlt_px(det, rig):
    """Mean over cameras of the median distance of each camera's detections from the DLT of
    the other three."""
    meds = []
    for c in range(rig.num_cameras):
        others = [i for i in range(rig.num_cameras) if i != c]
        w = det[..., 2] * (det[..., 2] > 0.3)
        X = triangulate_dlt(det[:, others, :, :2], w[:, others], rig.subset(others))
        uv = rig.subset([c]).project(X.nan_to_num())[0][:, 0]
        ok = torch.isfinite(X).all(-1) & (w[:, c] > 0)
        meds.append(float((uv - det[:, c, :, :2]).norm(dim=-1)[ok].median()))
    return sum(meds) / len(meds)


class TestLoader:
    def test_feature_perturbed_rig_comes_back(self, pose2sim_root, tmp_path):
        """The real recording's calibration moved by 2-3 degrees per camera: refined on its
        own detections the views agree again (held-out DLT error less than half the perturbed
        rig's, back near the given calibration's)."""
        g = torch.Generator().manual_seed(0)
        v = torch.zeros(4, 13, dtype=torch.float64)
        for c in range(4):
            a = torch.randn(3, generator=g, dtype=torch.float64)
            v[c, :3] = a / a.norm() * math.radians(2.0 + c / 3)
        root, given, bad = _perturbed_copy(pose2sim_root, tmp_path, v)
        seq_bad = _quiet(load_recording, root, masks="none", scale=0.25, checks="warn")
        seq = _quiet(load_recording, root, masks="none", scale=0.25,
                     calibration={"refine": True, "frames": [0, 10]})
        det = seq.joints2d.double()
        err_bad = _heldout_dlt_px(det, seq_bad.rig.double())
        err_ref = _heldout_dlt_px(det, seq.rig.double())
        assert err_ref < 0.5 * err_bad, (err_bad, err_ref)
        rec = seq.meta.calibration_refinement
        assert rec["objective"] == "bundle" and rec["frames"] == [0, 10]
        assert len(rec["report"]["cameras"]) == 4
        for cam in rec["report"]["cameras"]:
            assert cam["residual_median_px_after"] < cam["residual_median_px_before"]
        # as consistent as the given calibration (which the perturbation started from)
        err_given = _heldout_dlt_px(det, given.scaled_images(0.25))
        assert err_ref < 1.5 * err_given + 1.0, (err_given, err_ref)

    def test_feature_written_calibration_reads_back(self, pose2sim_root, tmp_path):
        rig, rec = _quiet(calibrate_recording, pose2sim_root, stop=10)
        files = write_refinement(tmp_path / "run", rig_from_dict(rec["rig"]), rec,
                                 rec["calibration"], rec["unit"])
        names = [p.name for p in files]
        assert names == ["Calib_refined.toml", "refinement.md", "refinement.json"]
        back = read_calibration(files[0]).double()
        ref = rig_from_dict(rec["rig"]).double()
        assert torch.allclose(back.R, ref.R, atol=1e-12)
        assert torch.allclose(back.t, ref.t, atol=1e-12)
        assert back.image_size.tolist() == [[1088, 1920]] * 4  # the calibrated sizes
        text = files[1].read_text()
        assert "rotation" in text and "cam01" in text
        # and used by the loader in place of the recording's own calibration
        seq = _quiet(load_recording, pose2sim_root, stop=3, masks="none", scale=0.25,
                     calibration={"file": str(files[0])})
        assert torch.allclose(seq.rig.R.double(), rig.R.double(), atol=1e-6)
        assert torch.allclose(seq.rig.t.double(), rig.t.double(), atol=1e-6)
        # intri/extri in, intri/extri out
        ocv = tmp_path / "ocv"
        from torchmocap.cameras import write_opencv_calibration

        write_opencv_calibration(back, ocv)
        out = write_refinement(tmp_path / "run2", back, rec, ocv / "intri.yml")
        assert [p.name for p in out][:2] == ["intri.yml", "extri.yml"]
        assert torch.allclose(read_calibration(out[0]).R.double(), back.R, atol=1e-12)

    def test_feature_time_offsets_refined(self, pose2sim_root):
        _, rec = _quiet(calibrate_recording, pose2sim_root, stop=10,
                        calibration={"groups": ["rotation", "translation", "time_offset"],
                                     "max_time_offset": 2.0})
        offsets = rec["time_offsets"]
        assert len(offsets) == 4 and all(abs(v) <= 2.0 + 1e-9 for v in offsets)
        assert all(c["time_offset_std_frames"] is not None for c in rec["report"]["cameras"])

    def test_exception_refine_range(self, pose2sim_root):
        with pytest.raises(ValueError, match=r"data\.calibration\.frames.*beyond"):
            _quiet(load_recording, pose2sim_root, masks="none",
                   calibration={"refine": True, "frames": [0, 40]})

    def test_exception_one_camera(self, pose2sim_root):
        with pytest.raises(ValueError, match=r"data\.calibration\.refine.*two cameras"):
            _quiet(load_recording, pose2sim_root, masks="none", cameras=["cam01"],
                   calibration={"refine": True})

    def test_exception_too_few_detections(self, pose2sim_root):
        with pytest.raises(ValueError, match=r"data\.calibration:.*usable detections"):
            _quiet(calibrate_recording, pose2sim_root, stop=10,
                   calibration={"frames": [0, 4], "loss": {"min_confidence": 0.99}})

    def test_exception_time_offset_bound(self, pose2sim_root):
        with pytest.raises(ValueError, match=r"data\.calibration:.*max_time_offset"):
            _quiet(calibrate_recording, pose2sim_root, stop=10,
                   calibration={"frames": [0, 6], "groups": ["rotation", "time_offset"],
                                "max_time_offset": 8.0})

    def test_exception_missing_file(self, pose2sim_root, tmp_path):
        with pytest.raises(ValueError, match=r"data\.calibration\.file.*does not exist"):
            _quiet(load_recording, pose2sim_root, masks="none",
                   calibration={"file": str(tmp_path / "nope.toml")})

    def test_feature_overlap_with_heldout_warned(self, pose2sim_root):
        with pytest.warns(UserWarning, match="held-out camera 'cam02'.*optimistic"):
            load_recording(pose2sim_root, masks="none", stop=8, scale=0.25,
                           heldout_camera="cam02",
                           calibration={"refine": True})


def _skeleton_scene(seed: int, T: int = 30):
    """human31 walking in place with body_25b keypoints, seen by a 4-camera ring: the true
    rig, a perturbed one (1-3 degrees, 2-5 cm), noisy detections and the true poses."""
    from torchmocap.skeleton import human31, keypoint_positions, load_keypoint_map

    g = torch.Generator().manual_seed(seed)
    sk = human31().double()
    kmap = load_keypoint_map("body_25b", sk)
    D = sk.num_dofs
    t = torch.arange(T, dtype=torch.float64)[:, None] / 30.0
    amp = 0.3 * torch.rand(D, generator=g, dtype=torch.float64)
    phase = 2 * math.pi * torch.rand(D, generator=g, dtype=torch.float64)
    theta = amp * torch.sin(2 * math.pi * 0.8 * t + phase)
    theta[:, :3] = 0.1 * theta[:, :3]  # the pelvis moves a few centimetres
    kin = sk(theta)
    X = keypoint_positions(kin.positions, kin.rotations, kmap)
    rig = make_ring_rig(4, radius=3.5, image_size=(1280, 960)).double()
    uv = refinement_pixels(X, rig.K, rig.R, rig.t, rig.dist)
    uv = uv + 1.5 * torch.randn(uv.shape, generator=g, dtype=torch.float64)
    det = torch.cat([uv, 0.9 * torch.ones(*uv.shape[:-1], 1, dtype=torch.float64)], -1)
    v = torch.zeros(4, 13, dtype=torch.float64)
    for c in range(4):
        a = torch.randn(3, generator=g, dtype=torch.float64)
        v[c, :3] = a / a.norm() * math.radians(1.0 + 2.0 * float(torch.rand(1, generator=g)))
        d = torch.randn(3, generator=g, dtype=torch.float64)
        v[c, 3:6] = d / d.norm() * (0.02 + 0.03 * float(torch.rand(1, generator=g)))
    from torchmocap.cameras import CameraRig

    K, R, tt, dd = apply_rig_parameters(v, rig.K, rig.R, rig.t, rig.dist)
    bad = CameraRig(K, R, tt, rig.image_size, dd, rig.names)
    return rig, bad, det, kmap


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("objective", ["bundle", "model"])
def test_feature_skeleton_scene_recovered(seed, objective):
    """Both objectives bring a perturbed rig back: the held-out DLT error of noisy skeleton
    keypoints falls to near the true rig's (a do-nothing refinement keeps the perturbed
    rig's)."""
    rig, bad, det, kmap = _skeleton_scene(seed)
    from torchmocap.io.openpose import keypoint_format

    names = list(keypoint_format("body_25b"))
    s = calibration_settings({"objective": objective, "progress": False, "iterations": 100})
    refined, rec = refine_rig(det, bad, names, "body_25b", s, 30.0, range(det.shape[0]))
    e_true = _heldout_dlt_px(det, rig)
    e_bad = _heldout_dlt_px(det, bad)
    e_ref = _heldout_dlt_px(det, refined.double())
    assert e_bad > 3 * e_true
    assert e_ref < e_true + 0.3 * (e_bad - e_true), (e_true, e_bad, e_ref)
    assert rec["objective"] == objective
    if objective == "model":
        assert "bundle_report" in rec


def test_exception_model_objective_shapes():
    from torchmocap.cameras import RefinementError
    from torchmocap.ik import fit_rig_to_skeleton
    from torchmocap.skeleton import human31, load_keypoint_map

    sk = human31().double()
    kmap = load_keypoint_map("body_25b", sk)
    rig = make_ring_rig(2).double()
    det = torch.zeros(5, 2, 25, 3, dtype=torch.float64)
    with pytest.raises(RefinementError, match=r"theta: expected shape \(5, "):
        fit_rig_to_skeleton(det, rig, sk, kmap, torch.zeros(4, sk.num_dofs), ["x"] * 25)
    with pytest.raises(RefinementError, match="keypoint_names"):
        fit_rig_to_skeleton(det, rig, sk, kmap, torch.zeros(5, sk.num_dofs), ["x"] * 3)
    with pytest.raises(RefinementError, match="noise_px"):
        fit_rig_to_skeleton(det, rig, sk, kmap, torch.zeros(5, sk.num_dofs), ["x"] * 25,
                            noise_px=-1.0)
