"""Calibration writers: a rig written as Pose2Sim/anipose TOML or OpenCV intri/extri YAML reads
back as the same rig through the project's readers and through OpenCV's FileStorage; the real
recording's Calib.toml survives a round trip; writes are atomic; names that cannot be keys and
other bad inputs are clear errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.cameras import (
    CameraError,
    CameraRig,
    make_ring_rig,
    read_calibration,
    read_opencv_calibration,
    read_toml_calibration,
    write_calibration,
    write_opencv_calibration,
    write_toml_calibration,
)
from torchmocap.cameras.formats import tomllib


def _rig(names=None) -> CameraRig:
    base = make_ring_rig(3, image_size=(1088, 1920)).double()
    K = base.K.clone()
    K[:, 0, 0] *= torch.tensor([1.0, 1.01, 0.99], dtype=torch.float64)
    K[:, 0, 1] = torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64)  # a skew
    K[:, 0, 2] += torch.tensor([3.25, -1e-5, 7.0], dtype=torch.float64)
    dist = torch.tensor([[-0.1, 0.02, 1e-5, -3e-6, 0.0], [0.05, -1e-7, 0.0, 0.0, 1e-3],
                         [0.0, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    # a rotation near pi: the Rodrigues conversion's hard case
    flip = torch.tensor([[-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]], dtype=torch.float64)
    R = base.R.clone()
    R[2] = flip @ R[2]
    t = base.t.clone()
    t[2] = flip @ t[2]
    return CameraRig(K, R, t, base.image_size, dist, names or ["cam_01", "cam_02", "cam-3"])


def _same(a: CameraRig, b: CameraRig, atol=1e-12):
    assert a.names == b.names
    assert torch.equal(a.image_size, b.image_size)
    for x, y in ((a.K, b.K), (a.R, b.R), (a.t, b.t), (a.dist, b.dist)):
        torch.testing.assert_close(x.double(), y.double(), atol=atol, rtol=0)


class TestWriteToml:
    def test_smoke(self, tmp_path):
        rig = _rig()
        path = write_toml_calibration(rig, tmp_path / "sub" / "Calib.toml")
        assert path.is_file()
        _same(read_toml_calibration(path), rig)

    def test_feature_schema(self, tmp_path):
        rig = _rig(["cam 1", "cam_02", "c3"])  # a name that needs a quoted table key
        path = write_toml_calibration(rig, tmp_path / "c.toml", metadata={"adjusted": False,
                                                                          "error": 0.5})
        data = tomllib.loads(path.read_text())
        assert list(data) == ["cam 1", "cam_02", "c3", "metadata"]
        cam = data["cam_02"]
        assert set(cam) == {"name", "size", "matrix", "distortions", "rotation",
                            "translation", "fisheye"}
        assert cam["fisheye"] is False and cam["size"] == [1088.0, 1920.0]
        assert len(cam["distortions"]) == 5  # k3 != 0 is written
        assert len(data["c3"]["distortions"]) == 4  # Pose2Sim's four when k3 = 0
        assert data["metadata"] == {"adjusted": False, "error": 0.5}
        _same(read_toml_calibration(path), rig)

    def test_feature_units(self, tmp_path):
        rig = _rig()
        path = write_toml_calibration(rig, tmp_path / "mm.toml", unit="mm")
        data = tomllib.loads(path.read_text())
        assert data["cam_01"]["translation"][2] == pytest.approx(1000 * float(rig.t[0, 2]))
        _same(read_toml_calibration(path, unit="mm"), rig, atol=1e-12)

    def test_feature_real_calibration_round_trip(self, tmp_path, pose2sim_root):
        rig = read_toml_calibration(pose2sim_root / "calibration" / "Calib.toml")
        back = read_toml_calibration(write_toml_calibration(rig, tmp_path / "Calib.toml"))
        _same(back, rig, atol=1e-12)

    def test_feature_atomic(self, tmp_path, monkeypatch):
        """A write that fails leaves the old file as it was, and no temporary file."""
        path = write_toml_calibration(_rig(), tmp_path / "Calib.toml")
        before = path.read_text()
        import pathlib

        def boom(self, *a, **k):
            raise OSError("disk full")

        monkeypatch.setattr(pathlib.Path, "write_text", boom)
        with pytest.raises(OSError, match="disk full"):
            write_toml_calibration(make_ring_rig(2), path)
        monkeypatch.undo()
        assert path.read_text() == before
        assert [p.name for p in tmp_path.iterdir()] == ["Calib.toml"]

    def test_exception(self, tmp_path):
        with pytest.raises(CameraError, match="rig: expected a CameraRig"):
            write_toml_calibration("rig", tmp_path / "x.toml")
        rig = make_ring_rig(2)
        rig.names = ["a", "a"]
        with pytest.raises(CameraError, match="unique"):
            write_toml_calibration(rig, tmp_path / "x.toml")
        with pytest.raises(CameraError, match="unknown unit"):
            write_toml_calibration(make_ring_rig(2), tmp_path / "x.toml", unit="furlong")
        with pytest.raises(CameraError, match="metadata"):
            write_toml_calibration(make_ring_rig(2), tmp_path / "x.toml",
                                   metadata={"when": [1, 2]})


class TestWriteOpenCV:
    def test_smoke(self, tmp_path):
        rig = _rig()
        intri, extri = write_opencv_calibration(rig, tmp_path / "calib")
        assert intri.name == "intri.yml" and extri.name == "extri.yml"
        _same(read_opencv_calibration(intri, extri), rig)
        _same(read_calibration(tmp_path / "calib"), rig)

    def test_feature_opencv_filestorage(self, tmp_path):
        """OpenCV's own reader sees the same matrices (intri: K, dist, H, W; extri: the
        Rodrigues vector, the matrix and T)."""
        cv2 = pytest.importorskip("cv2")
        rig = _rig()
        intri, extri = write_opencv_calibration(rig, tmp_path)
        fi = cv2.FileStorage(str(intri), cv2.FILE_STORAGE_READ)
        fe = cv2.FileStorage(str(extri), cv2.FILE_STORAGE_READ)
        names = fi.getNode("names")
        assert [names.at(i).string() for i in range(names.size())] == rig.names
        for c, n in enumerate(rig.names):
            K = torch.from_numpy(fi.getNode(f"K_{n}").mat())
            torch.testing.assert_close(K, rig.K[c], atol=1e-12, rtol=0)
            d = torch.from_numpy(fi.getNode(f"dist_{n}").mat()).reshape(-1)
            torch.testing.assert_close(d, rig.dist[c], atol=1e-15, rtol=0)
            assert int(fi.getNode(f"H_{n}").real()) == 1920
            assert int(fi.getNode(f"W_{n}").real()) == 1088
            rvec = fe.getNode(f"R_{n}").mat()
            R, _ = cv2.Rodrigues(rvec)
            torch.testing.assert_close(torch.from_numpy(R), rig.R[c], atol=1e-12, rtol=0)
            torch.testing.assert_close(torch.from_numpy(fe.getNode(f"Rot_{n}").mat()),
                                       rig.R[c], atol=1e-15, rtol=0)
            torch.testing.assert_close(torch.from_numpy(fe.getNode(f"T_{n}").mat()).reshape(-1),
                                       rig.t[c], atol=1e-15, rtol=0)
        fi.release()
        fe.release()

    def test_feature_small_numbers_stay_numbers(self, tmp_path):
        """1e-05 would be a string to YAML 1.1: the writer gives every float a mantissa dot."""
        rig = _rig()
        intri, _ = write_opencv_calibration(rig, tmp_path)
        text = intri.read_text()
        assert "1e-05" not in text and "1.0e-05" in text
        torch.testing.assert_close(read_opencv_calibration(intri).dist, rig.dist, atol=0,
                                   rtol=0)

    def test_exception(self, tmp_path):
        with pytest.raises(CameraError, match=r"camera name\(s\) \['cam 1'\]"):
            write_opencv_calibration(_rig(["cam 1", "b", "c"]), tmp_path)
        with pytest.raises(CameraError, match="suffix"):
            write_opencv_calibration(_rig(), tmp_path, suffix=".json")


class TestWriteCalibration:
    def test_feature_dispatch(self, tmp_path):
        rig = _rig()
        (p,) = write_calibration(rig, tmp_path / "a.toml")
        _same(read_calibration(p), rig)
        paths = write_calibration(rig, tmp_path / "b" / "intri.yaml")
        assert [q.name for q in paths] == ["intri.yaml", "extri.yaml"]
        _same(read_calibration(paths[0]), rig)
        paths = write_calibration(rig, tmp_path / "folder")
        _same(read_calibration(tmp_path / "folder"), rig)
        (p,) = write_calibration(rig, tmp_path / "rig.json")
        _same(read_calibration(p), rig)

    def test_exception(self, tmp_path):
        with pytest.raises(CameraError, match="unknown calibration format '.txt'"):
            write_calibration(_rig(), tmp_path / "rig.txt")
        with pytest.raises(CameraError, match="unit"):
            write_calibration(_rig(), tmp_path / "rig.json", unit="mm")


def test_writers_keep_every_digit(tmp_path):
    """Shortest round-trip floats: a value with every bit set comes back bit-exact."""
    rig = _rig()
    K = rig.K.clone()
    K[0, 0, 0] = math.pi * 1000
    rig = CameraRig(K, rig.R, rig.t, rig.image_size, rig.dist, rig.names)
    back = read_toml_calibration(write_toml_calibration(rig, tmp_path / "x.toml"))
    assert float(back.K[0, 0, 0]) == math.pi * 1000
