"""TRC marker files: the trimmed Pose2Sim file reads (names, times, metres), its Y-up axes turn
into the Z-up world where the triangulated detections are, units and missing markers, and
malformed files are refused naming the file and line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchmocap.io import TRC_Y_UP_TO_Z_UP, MotionFormatError, read_trc, trc_to_z_up

TRC = ("multiview", "pose2sim_balancing", "pose2sim_output", "S00_P00_T01_BalancingTrial_0-100.trc")
HEADER = ("PathFileType\t4\t(X/Y/Z)\tx.trc\n"
          "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\n"
          "{rate}\t{rate}\t{frames}\t2\t{units}\t{rate}\n"
          "Frame#\tTime\tA\t\t\tB\t\t\n"
          "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n")


def _write(tmp_path, rows, units="mm", rate=100, frames=None, blank=True, name="x.trc"):
    text = HEADER.format(rate=rate, frames=len(rows) if frames is None else frames, units=units)
    text += ("\n" if blank else "") + "".join(r + "\n" for r in rows)
    p = tmp_path / name
    p.write_text(text)
    return p


class TestReadTrc:
    def test_smoke(self, shared_data):
        data = read_trc(shared_data.joinpath(*TRC))
        assert data.points.shape == (10, 21, 3) and data.num_frames == 10
        assert data.marker_names[:3] == ["RHip", "RKnee", "RAnkle"] and data.rate == 60.0
        assert data.units == "m" and data.frames.tolist() == list(range(1, 11))
        torch.testing.assert_close(data.times, torch.arange(1, 11, dtype=torch.float64) / 60)
        assert bool(torch.isfinite(data.points).all())

    def test_feature_z_up_world(self, shared_data):
        """(x, y, z)_trc = (y, z, x)_world: in the world the head is ~1.7 m up (z), the ankles
        near the floor, and the markers lie within a few cm of a plain DLT of the same
        associated detections (frame 1 of the TRC is frame 0 of the JSON)."""
        import tomllib

        from torchmocap.cameras import CameraRig, triangulate_dlt
        from torchmocap.cameras.calibration import _rodrigues

        data = read_trc(shared_data.joinpath(*TRC))
        x = data.z_up()
        i = data.marker_index
        assert 1.5 < float(x[0, i("Head"), 2]) < 1.9
        assert float(x[0, i("RAnkle"), 2]) < 0.25
        torch.testing.assert_close(x, (TRC_Y_UP_TO_Z_UP @ data.points[..., None])[..., 0])
        torch.testing.assert_close(trc_to_z_up(torch.tensor([1.0, 2.0, 3.0])),
                                   torch.tensor([3.0, 1.0, 2.0]))
        assert float(torch.linalg.det(TRC_Y_UP_TO_Z_UP)) == pytest.approx(1.0)
        root = shared_data / "multiview" / "pose2sim_balancing"
        calib = tomllib.loads((root / "calibration" / "Calib.toml").read_text())
        cams = [calib[k] for k in sorted(calib) if k.startswith("cam_")]
        f64 = torch.float64
        rig = CameraRig(torch.tensor([c["matrix"] for c in cams], dtype=f64),
                        torch.stack([_rodrigues(torch.tensor(c["rotation"], dtype=f64))
                                     for c in cams]),
                        torch.tensor([c["translation"] for c in cams], dtype=f64),
                        [[1088, 1920]] * 4,
                        torch.tensor([c["distortions"] + [0.0] for c in cams], dtype=f64))
        det = torch.tensor(np.stack([np.asarray(json.loads(
            (root / "pose-associated" / f"cam{c:02d}_json" / f"cam{c:02d}.0000.json")
            .read_text())["people"][0]["pose_keypoints_2d"]).reshape(25, 3)
            for c in range(1, 5)]))
        X = triangulate_dlt(det[..., :2], det[..., 2], rig)
        body25b = {"RHip": 12, "RKnee": 14, "RAnkle": 16, "LHip": 11, "LKnee": 13,
                   "LAnkle": 15, "RShoulder": 6, "RElbow": 8, "RWrist": 10, "LShoulder": 5,
                   "LElbow": 7, "LWrist": 9}
        d = torch.stack([(X[k] - x[0, i(n)]).norm() for n, k in body25b.items()])
        assert float(d.median()) < 0.05  # measured 2.9 cm

    def test_feature_units_and_missing_markers(self, tmp_path):
        p = _write(tmp_path, ["1\t0.00\t1000\t2000\t3000\t\t\t",
                              "2\t0.01\t1100\t2000\t3000\t10\t20\t30"], units="mm")
        data = read_trc(p)
        torch.testing.assert_close(data.points[0, 0], torch.tensor([1.0, 2.0, 3.0],
                                                                   dtype=torch.float64))
        assert bool(torch.isnan(data.points[0, 1]).all())
        torch.testing.assert_close(data.points[1, 1], torch.tensor([0.01, 0.02, 0.03],
                                                                   dtype=torch.float64))
        cm = read_trc(_write(tmp_path, ["1\t0\t100\t0\t0\t0\t0\t0"], units="cm", blank=False))
        assert float(cm.points[0, 0, 0]) == pytest.approx(1.0)
        with pytest.raises(KeyError, match="unknown marker 'C'"):
            data.marker_index("C")

    def test_exception(self, tmp_path):
        row = "1\t0\t1\t2\t3\t4\t5\t6"
        cases = [
            (dict(rows=[row], units="in"), r"1.trc:3: unknown Units 'in'"),
            (dict(rows=[row], frames=2), r"2.trc:3: NumFrames is 2 but the file has 1"),
            (dict(rows=[row, "2\t0.1\t1\t2\t3\t4\t5"]),
             r"3.trc:8: a row has 7 fields, expected 8"),
            (dict(rows=[row, "2\t0.1\t1\t2\tabc\t4\t5\t6"]),
             r"4.trc:8: coordinate: expected a number, got 'abc'"),
            (dict(rows=[row], rate=0), r"5.trc:3: DataRate must be > 0"),
        ]
        for k, (kw, msg) in enumerate(cases, start=1):
            with pytest.raises(MotionFormatError, match=msg):
                read_trc(_write(tmp_path, name=f"{k}.trc", **kw))
        bad = tmp_path / "y.trc"
        bad.write_text("hello\n")
        with pytest.raises(MotionFormatError, match="y.trc:1: not a TRC file"):
            read_trc(bad)
        text = _write(tmp_path, [row]).read_text().replace("\tA\t\t\tB", "\tA\t\t\t")
        bad.write_text(text)
        with pytest.raises(MotionFormatError, match="y.trc:4: NumMarkers is 2 but 1"):
            read_trc(bad)
        with pytest.raises(FileNotFoundError, match="no such TRC file"):
            read_trc(tmp_path / "none.trc")
        with pytest.raises(ValueError, match="points"):
            trc_to_z_up(torch.zeros(4, 2))
