"""Calibration files of the ecosystem: Pose2Sim TOML, OpenCV intri/extri, Bouguet folders.

The real ``Calib.toml`` of pose2sim_balancing is checked against known values, and its lens
model against OpenCV (``cv2.projectPoints``, ``cv2.undistortPoints``) — an independent
implementation of the same Brown–Conrady model.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from torchmocap.cameras import (
    CameraError,
    CameraRig,
    bouguet_calibration_files,
    camera_key,
    make_ring_rig,
    read_bouguet_folder,
    read_bouguet_rig,
    read_calibration,
    read_opencv_calibration,
    read_toml_calibration,
    write_rig,
)

cv2 = pytest.importorskip("cv2")

F64 = torch.float64


@pytest.fixture(scope="module")
def calib_toml(shared_data):
    return shared_data / "multiview" / "pose2sim_balancing" / "calibration" / "Calib.toml"


@pytest.fixture(scope="module")
def rig(calib_toml) -> CameraRig:
    return read_toml_calibration(calib_toml)


def _points(n: int = 200, seed: int = 0) -> np.ndarray:
    """World points around the treadmill (the subject's volume, metres, Z up)."""
    g = np.random.default_rng(seed)
    return np.stack([g.uniform(-1, 1, n), g.uniform(-1, 1, n), g.uniform(0, 2, n)], -1)


def _toml_camera(key: str, **over) -> str:
    fields = {"name": f'"{key}"', "size": "[ 640.0, 480.0]",
              "matrix": "[ [ 500.0, 0.0, 320.0], [ 0.0, 500.0, 240.0], [ 0.0, 0.0, 1.0]]",
              "distortions": "[ -0.1, 0.01, 0.0, 0.0]", "rotation": "[ 0.0, 0.0, 0.0]",
              "translation": "[ 0.0, 0.0, 3.0]", "fisheye": "false", **over}
    body = "\n".join(f"{k} = {v}" for k, v in fields.items() if v is not None)
    return f"[{key}]\n{body}\n"


class TestCameraKey:
    def test_feature(self):
        for name in ("cam01", "cam_01", "Camera1", "CAM1", "1", "01", "cam01_json", "FG1"):
            assert camera_key(name) == "1", name
        assert camera_key("cam12") == "12" and camera_key("Left View") == "leftview"


class TestTomlCalibration:
    def test_feature_real_file(self, rig):
        assert rig.names == ["cam_01", "cam_02", "cam_03", "cam_04"]
        assert rig.image_size.tolist() == [[1088, 1920]] * 4
        torch.testing.assert_close(rig.K[0], torch.tensor(
            [[1681.244873046875, 0.0, 532.97369384375], [0.0, 1681.075439453125, 948.137390140625],
             [0, 0, 1]], dtype=F64))
        torch.testing.assert_close(rig.dist[0], torch.tensor(
            [-0.000721609375, 0.002187234375, 9.5e-06, 1.078125e-05, 0.0], dtype=F64))
        torch.testing.assert_close(rig.t[3], torch.tensor(
            [0.5030217200000007, 0.04894934000000107, 4.406564460000002], dtype=F64))
        R01, _ = cv2.Rodrigues(np.array([1.6882754799999993, 1.0483220499999997,
                                         -0.41955852000000016]))
        torch.testing.assert_close(rig.R[0], torch.from_numpy(R01), atol=1e-12, rtol=0)
        # Z-up metres: the cameras stand 1.6-2.2 m high, 2.4-4.4 m around the treadmill,
        # and look slightly down
        c = rig.camera_centers()
        assert bool(((c[:, 2] > 1.6) & (c[:, 2] < 2.2)).all()), c
        assert bool(((c[:, :2].norm(dim=-1) > 2.4) & (c[:, :2].norm(dim=-1) < 4.4)).all()), c
        assert bool((rig.optical_axes()[:, 2] < 0).all())

    @pytest.mark.parametrize("gain", [1.0, 100.0])
    def test_feature_projection_matches_opencv(self, rig, gain):
        """``gain`` = 100 scales the (tiny) real coefficients to a strong lens (k1 ≈ -0.07)."""
        X = _points()
        lens = CameraRig(rig.K, rig.R, rig.t, rig.image_size, rig.dist * gain, rig.names)
        pix = lens.project(torch.from_numpy(X))[0]
        for c in range(4):
            rvec, _ = cv2.Rodrigues(rig.R[c].numpy())
            ref, _ = cv2.projectPoints(X, rvec, rig.t[c].numpy(), rig.K[c].numpy(),
                                       lens.dist[c, :4].numpy())
            np.testing.assert_allclose(pix[c].numpy(), ref[:, 0], atol=1e-6, rtol=0)

    @pytest.mark.parametrize("gain", [1.0, 100.0])
    def test_feature_undistortion_matches_opencv(self, rig, gain):
        lens = CameraRig(rig.K, rig.R, rig.t, rig.image_size, rig.dist * gain, rig.names)
        u, v = np.meshgrid(np.linspace(0, 1087, 9), np.linspace(0, 1919, 13))
        pix = np.stack([u.ravel(), v.ravel()], -1)
        _, d = lens.backproject(torch.from_numpy(pix).expand(4, -1, -1).contiguous())
        dc = torch.einsum("cij,cnj->cni", lens.R, d)
        xy = (dc[..., :2] / dc[..., 2:]).numpy()
        for c in range(4):
            ref = cv2.undistortPoints(pix[:, None], rig.K[c].numpy(), lens.dist[c, :4].numpy(),
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                50, 1e-14))
            # normalised coordinates; 1e-7 is 1.7e-4 px at f = 1680 px
            np.testing.assert_allclose(xy[c], ref[:, 0], atol=1e-7, rtol=0)

    def test_feature_round_trip(self, rig):
        X = torch.from_numpy(_points(50, seed=1))
        pix, depth, _ = rig.project(X)
        o, d = rig.backproject(pix)
        back = o + d * (depth[..., None] / torch.einsum("cj,cnj->cn", rig.R[:, 2], d)[..., None])
        torch.testing.assert_close(back, X.expand(4, -1, -1), atol=1e-9, rtol=0)

    def test_feature_five_coefficients_and_unit(self, tmp_path):
        p = tmp_path / "c.toml"
        p.write_text(_toml_camera("a", distortions="[ -0.1, 0.01, 0.001, 0.002, 0.05]",
                                  translation="[ 0.0, 0.0, 3000.0]", name=None)
                     + "[metadata]\nadjusted = false\n")
        r = read_toml_calibration(p, unit="mm")
        assert r.names == ["a"]  # the table's key without a name field
        torch.testing.assert_close(r.dist[0], torch.tensor([-0.1, 0.01, 0.001, 0.002, 0.05],
                                                           dtype=F64))
        torch.testing.assert_close(r.t[0], torch.tensor([0.0, 0.0, 3.0], dtype=F64))

    @pytest.mark.parametrize("over, match", [
        ({"fisheye": "true"}, r"\[a\]: fisheye = True: the fisheye lens model is not supported"),
        ({"matrix": None}, r"\[a\]: missing camera field\(s\) \['matrix'\]"),
        ({"size": "[ 640.5, 480.0]"}, r"\[a\]: image_size must be positive whole numbers"),
        ({"rotation": "[ 0.0, 0.0]"}, r"\[a\]: rotation must have 3 values \(a Rodrigues "
                                       r"vector\) or 9 \(a 3x3 matrix\), got 2"),
        # a non-rotation matrix: named by the table, not as 'camera(s) [0]'
        ({"rotation": "[ [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]]"},
         r"^\S*bad\.toml \[a\]: R is not a rotation matrix"),
        ({"translation": "[ 0.0, nan, 3.0]"}, r"\[a\]: t contains non-finite"),
    ])
    def test_exception(self, tmp_path, over, match):
        p = tmp_path / "bad.toml"
        p.write_text(_toml_camera("a", **over))
        with pytest.raises(CameraError, match=match):
            read_toml_calibration(p)

    def test_exception_rotation_named_by_camera(self):
        eye, bad = torch.eye(3, dtype=F64), torch.diag(torch.tensor([1.0, 2.0, 1.0], dtype=F64))
        K = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], dtype=F64)
        with pytest.raises(CameraError, match=r"^R of camera\(s\) \['b'\] is not a rotation"):
            CameraRig(K.expand(2, 3, 3), torch.stack([eye, bad]), torch.zeros(2, 3, dtype=F64),
                      [(640, 480)] * 2, names=["a", "b"])

    def test_exception_file(self, tmp_path):
        p = tmp_path / "bad.toml"
        p.write_text("[cam_01\nname = 1")
        with pytest.raises(CameraError, match=r"bad\.toml: not a valid TOML file"):
            read_toml_calibration(p)
        p.write_text("[metadata]\nerror = 0.0\n")
        with pytest.raises(CameraError, match=r"bad\.toml: no camera tables"):
            read_toml_calibration(p)
        with pytest.raises(CameraError, match=r"missing\.toml: cannot read"):
            read_toml_calibration(tmp_path / "missing.toml")


def _write_opencv(folder, rig: CameraRig, names, sizes=True, rot=True, rvec=True,
                  rvec_rig: CameraRig | None = None):
    """intri.yml / extri.yml written by OpenCV's own FileStorage (``R_<n>`` from ``rvec_rig``
    when given)."""
    fi = cv2.FileStorage(str(folder / "intri.yml"), cv2.FILE_STORAGE_WRITE)
    fe = cv2.FileStorage(str(folder / "extri.yml"), cv2.FILE_STORAGE_WRITE)
    for fs in (fi, fe):
        fs.startWriteStruct("names", cv2.FileNode_SEQ)
        for n in names:
            fs.write("", n)
        fs.endWriteStruct()
    for c, n in enumerate(names):
        fi.write(f"K_{n}", rig.K[c].numpy())
        fi.write(f"dist_{n}", rig.dist[c].numpy()[None])
        if sizes:
            fi.write(f"H_{n}", int(rig.image_size[c, 1]))
            fi.write(f"W_{n}", int(rig.image_size[c, 0]))
        if rvec:
            fe.write(f"R_{n}", cv2.Rodrigues((rvec_rig or rig).R[c].numpy())[0])
        if rot:
            fe.write(f"Rot_{n}", rig.R[c].numpy())
        fe.write(f"T_{n}", rig.t[c].numpy()[:, None])
    fi.release()
    fe.release()


def _assert_same(a: CameraRig, b: CameraRig, atol=1e-9):
    for f in ("K", "dist", "R", "t"):
        torch.testing.assert_close(getattr(a, f), getattr(b, f), atol=atol, rtol=0)
    assert a.image_size.tolist() == b.image_size.tolist()


class TestOpenCVCalibration:
    NAMES = ["01", "02", "03", "04"]

    @pytest.mark.parametrize("rot, rvec", [(True, True), (True, False), (False, True)])
    def test_feature_round_trip_through_opencv(self, tmp_path, rig, rot, rvec):
        _write_opencv(tmp_path, rig, self.NAMES, rot=rot, rvec=rvec)
        back = read_opencv_calibration(tmp_path / "intri.yml", tmp_path / "extri.yml")
        assert back.names == self.NAMES
        _assert_same(back, rig)

    def test_feature_sizes_from_the_caller(self, tmp_path, rig):
        _write_opencv(tmp_path, rig, self.NAMES, sizes=False)
        with pytest.raises(CameraError, match=r"intri\.yml: the file does not store the image "
                                              r"size .* pass image_sizes"):
            read_opencv_calibration(tmp_path / "intri.yml")
        by_name = {f"cam{i + 1:02d}": (1080 + i, 1920) for i in range(4)}
        back = read_opencv_calibration(tmp_path / "intri.yml", image_sizes=by_name)
        assert back.image_size[:, 0].tolist() == [1080, 1081, 1082, 1083]
        same = read_opencv_calibration(tmp_path / "intri.yml", image_sizes=(1088, 1920))
        _assert_same(same, rig)
        with pytest.raises(CameraError, match=r"image_sizes has no entry for camera\(s\) "
                                              r"\['04'\]"):
            read_opencv_calibration(tmp_path / "intri.yml",
                                    image_sizes={k: v for k, v in list(by_name.items())[:3]})

    def test_exception(self, tmp_path, rig):
        R = rig.R.clone()
        R[1] = rig.R[2]
        _write_opencv(tmp_path, CameraRig(rig.K, R, rig.t, rig.image_size, rig.dist),
                      self.NAMES, rvec_rig=rig)
        with pytest.raises(CameraError, match=r"extri\.yml: R_02 and Rot_02 disagree"):
            read_opencv_calibration(tmp_path / "intri.yml")
        _write_opencv(tmp_path, rig, self.NAMES)
        text = (tmp_path / "extri.yml").read_text()
        start = text.index("T_03:")
        (tmp_path / "extri.yml").write_text(text[:start] + text[start:].replace("T_03", "X_03"))
        with pytest.raises(CameraError, match=r"extri\.yml: missing T_03 \(camera '03'"):
            read_opencv_calibration(tmp_path / "intri.yml")
        (tmp_path / "intri.yml").write_text("%YAML:1.0\n---\nK_01: [1, 2\n")
        with pytest.raises(CameraError, match=r"intri\.yml:\d+: cannot parse"):
            read_opencv_calibration(tmp_path / "intri.yml")


class TestBouguetFolder:
    def _folder(self, tmp_path, bodytrack_calibs, numbers):
        d = tmp_path / "CALIB"
        d.mkdir()
        for src, i in zip(bodytrack_calibs, numbers):
            shutil.copy(src, d / f"Camera{i}.cal")
        return d

    def test_feature_paired_by_number(self, tmp_path, bodytrack_calibs):
        # lexical order would put Camera10 before Camera9
        d = self._folder(tmp_path, bodytrack_calibs, [8, 9, 10, 11])
        files = bouguet_calibration_files(d)
        assert [i for i, _ in files] == [8, 9, 10, 11]
        rig = read_bouguet_folder(d)
        ref = read_bouguet_rig(bodytrack_calibs)
        assert rig.names == ["Camera8", "Camera9", "Camera10", "Camera11"]
        _assert_same(rig, ref, atol=0)

    def test_exception_gap(self, tmp_path, bodytrack_calibs):
        d = self._folder(tmp_path, bodytrack_calibs, [1, 2, 3, 4])
        (d / "Camera2.cal").unlink()
        with pytest.raises(CameraError, match=r"CALIB: missing Camera2\.cal"):
            read_bouguet_folder(d)
        shutil.copy(bodytrack_calibs[0], d / "Camera02.cal")
        shutil.copy(bodytrack_calibs[0], d / "camera2.cal")
        with pytest.raises(CameraError, match=r"are both camera 2"):
            bouguet_calibration_files(d)
        with pytest.raises(CameraError, match=r"no Bouguet calibration files"):
            bouguet_calibration_files(tmp_path)


class TestReadCalibration:
    def test_feature_dispatch(self, tmp_path, calib_toml, rig, bodytrack_calibs):
        _assert_same(read_calibration(calib_toml), rig, atol=0)
        _assert_same(read_calibration(calib_toml.parent), rig, atol=0)
        _write_opencv(tmp_path, rig, ["1", "2", "3", "4"])
        _assert_same(read_calibration(tmp_path), rig)
        _assert_same(read_calibration(tmp_path / "extri.yml"), rig)
        cal = tmp_path / "CALIB"
        cal.mkdir()
        for src in bodytrack_calibs:
            shutil.copy(src, cal)
        _assert_same(read_calibration(cal, image_sizes=(640, 480)),
                     read_bouguet_rig(bodytrack_calibs), atol=0)
        _assert_same(read_calibration(cal / "Camera3.cal", image_sizes=(640, 480)),
                     read_bouguet_rig(bodytrack_calibs[2:3]), atol=0)
        ring = make_ring_rig(3)
        _assert_same(read_calibration(write_rig(ring, tmp_path / "ring.json")), ring, atol=0)

    def test_exception(self, tmp_path, calib_toml, bodytrack_calibs):
        with pytest.raises(CameraError, match=r"no calibration found"):
            read_calibration(tmp_path)
        with pytest.raises(CameraError, match=r"no such calibration file or folder"):
            read_calibration(tmp_path / "nothing")
        shutil.copy(calib_toml, tmp_path)
        shutil.copy(bodytrack_calibs[0], tmp_path)
        with pytest.raises(CameraError, match=r"several calibrations \(toml: \['Calib\.toml'\]; "
                                              r"bouguet: \['Camera1\.cal'\]\)"):
            read_calibration(tmp_path)
        with pytest.raises(CameraError, match=r"Camera1\.cal: the file does not store the image "
                                              "size"):
            read_calibration(tmp_path / "Camera1.cal")
        (tmp_path / "Calib.txt").write_text("x")
        with pytest.raises(CameraError, match=r"Calib\.txt: unknown calibration format '\.txt'"):
            read_calibration(tmp_path / "Calib.txt")
        with pytest.raises(CameraError, match="unknown unit"):
            read_calibration(calib_toml, unit="furlong")
