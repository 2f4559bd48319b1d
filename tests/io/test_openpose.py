"""OpenPose JSON keypoints: the real BODY_25B files of pose2sim_balancing, formats, bad files."""

from __future__ import annotations

import json

import pytest
import torch

from torchmocap.io.openpose import (
    KEYPOINT_FORMATS,
    KeypointFormatError,
    body25_plausibility,
    check_keypoint_format,
    keypoint_format,
    read_openpose_json,
    write_openpose_json,
)


@pytest.fixture(scope="module")
def pose_dir(shared_data):
    return shared_data / "multiview" / "pose2sim_balancing"


@pytest.fixture(scope="module")
def raw_people(pose_dir) -> list[torch.Tensor]:
    """Every raw detection file of the 4 views (bystander included)."""
    return [read_openpose_json(p, 25) for p in sorted(pose_dir.glob("pose/cam0*_json/*.json"))]


def _to_body25(x: torch.Tensor) -> torch.Tensor:
    """BODY_25B detections rewritten in BODY_25's order (MidHip = the hips' midpoint)."""
    src = KEYPOINT_FORMATS["body_25b"]
    out = torch.zeros_like(x)
    for i, name in enumerate(KEYPOINT_FORMATS["body_25"]):
        if name == "MidHip":
            out[:, i, :2] = 0.5 * (x[:, 11, :2] + x[:, 12, :2])
            out[:, i, 2] = torch.minimum(x[:, 11, 2], x[:, 12, 2])
        else:
            out[:, i] = x[:, src.index(name)]
    return out


def _write(path, people) -> None:
    path.write_text(json.dumps({"version": 1.3, "people": people}))


class TestFormats:
    def test_cardinality(self):
        assert {k: len(v) for k, v in KEYPOINT_FORMATS.items()} == {
            "body_25": 25, "body_25b": 25, "coco_17": 17, "halpe_26": 26, "mediapipe_33": 33}
        for names in KEYPOINT_FORMATS.values():
            assert len(set(names)) == len(names)
        # one vocabulary: COCO's 17 lead BODY_25B and HALPE-26, and BODY_25 has all of them
        coco = KEYPOINT_FORMATS["coco_17"]
        assert KEYPOINT_FORMATS["body_25b"][:17] == coco == KEYPOINT_FORMATS["halpe_26"][:17]
        assert set(coco) < set(KEYPOINT_FORMATS["body_25"])
        assert set(KEYPOINT_FORMATS["body_25"]) == set(KEYPOINT_FORMATS["halpe_26"]) - {"Head"}
        # MediaPipe's 33 share COCO's names but Head/Neck/MidHip; its feet: heels, foot index
        mp = KEYPOINT_FORMATS["mediapipe_33"]
        assert set(coco) < set(mp) and not {"Neck", "Head", "MidHip"} & set(mp)
        assert (mp[0], mp[11], mp[23], mp[29], mp[32]) == ("Nose", "LShoulder", "LHip", "LHeel",
                                                           "RFootIndex")

    def test_feature_known_indices(self):
        b25, b25b = KEYPOINT_FORMATS["body_25"], KEYPOINT_FORMATS["body_25b"]
        assert (b25[1], b25[8], b25[9], b25[12]) == ("Neck", "MidHip", "RHip", "LHip")
        assert (b25b[8], b25b[17], b25b[18], b25b[24]) == ("RElbow", "Neck", "Head", "RHeel")
        h = KEYPOINT_FORMATS["halpe_26"]
        assert (h[17], h[18], h[19], h[25]) == ("Head", "Neck", "MidHip", "RHeel")
        assert keypoint_format("BODY-25B") == b25b
        with pytest.raises(KeypointFormatError, match=r"'mpii' is unknown; expected one of"):
            keypoint_format("mpii")


class TestReadJson:
    def test_feature_real_file(self, pose_dir):
        path = pose_dir / "pose" / "cam01_json" / "cam01.0000.json"
        x = read_openpose_json(path, 25)
        flat = json.loads(path.read_text())["people"]
        assert x.shape == (2, 25, 3) and x.dtype == torch.float64
        for k in range(2):
            assert x[k].flatten().tolist() == flat[k]["pose_keypoints_2d"]
        assoc = read_openpose_json(pose_dir / "pose-associated" / "cam01_json" /
                                   "cam01.0000.json")
        assert assoc.shape == (1, 25, 3) and torch.equal(assoc[0], x[0])

    def test_feature_nobody(self, tmp_path):
        p = tmp_path / "f.json"
        _write(p, [])
        assert read_openpose_json(p, 17).shape == (0, 17, 3)
        _write(p, [{}, {"pose_keypoints_2d": [1.0, 2.0, 0.5] * 17}])  # Pose2Sim's {}: nobody
        assert read_openpose_json(p, 17).shape == (1, 17, 3)

    @pytest.mark.parametrize("text, match", [
        ("", r"f\.json: empty file"),
        ("{\"people\": [", r"f\.json:1: not valid JSON"),
        ("{\"version\": 1.3}", r"f\.json: expected OpenPose JSON with a 'people' list"),
        (json.dumps({"people": [{"pose_keypoints_2d": [0.0] * 75}]}),
         r"f\.json: people\[0\]\.pose_keypoints_2d has 75 values = 25 keypoints, expected 17 "
         r"keypoints \(51 values"),
        (json.dumps({"people": [{"pose_keypoints_2d": ["a", 1, 1] * 17}]}),
         r"f\.json: people\[0\] has non-numeric keypoints"),
        (json.dumps({"people": [{"pose_keypoints_2d": [1, 1, -1] * 17}]}),
         r"f\.json: people\[0\] has non-finite values or negative confidences"),
        (json.dumps({"people": [3]}), r"f\.json: people\[0\] is not a JSON object"),
    ])
    def test_exception(self, tmp_path, text, match):
        p = tmp_path / "f.json"
        p.write_text(text)
        with pytest.raises(KeypointFormatError, match=match):
            read_openpose_json(p, 17)


class TestCheckFormat:
    def test_feature_real_body25b(self, raw_people):
        assert check_keypoint_format("auto", raw_people) == "body_25b"
        assert check_keypoint_format("body_25b", raw_people) == "body_25b"
        assert body25_plausibility(raw_people) > 0.4

    def test_feature_body25(self, raw_people):
        as_b25 = [_to_body25(x) for x in raw_people]
        assert body25_plausibility(as_b25) < 0.05
        assert check_keypoint_format("auto", as_b25) == "body_25"

    def test_feature_by_count(self, raw_people):
        coco = [x[:, :17] for x in raw_people]
        assert check_keypoint_format("auto", coco) == "coco_17"
        halpe = [torch.cat([x, x[:, :1]], 1) for x in raw_people]
        assert check_keypoint_format("auto", halpe) == "halpe_26"

    def test_exception(self, raw_people):
        with pytest.raises(KeypointFormatError, match=r"pose: declared 'body_25', but the "
                                                      r"detections look like 'body_25b'"):
            check_keypoint_format("body_25", raw_people, "pose")
        with pytest.raises(KeypointFormatError, match=r"declared 'body_25b', but the detections "
                                                      r"look like 'body_25'"):
            check_keypoint_format("body_25b", [_to_body25(x) for x in raw_people])
        with pytest.raises(KeypointFormatError, match=r"17 keypoints per person, but format "
                                                      r"'halpe_26' has 26"):
            check_keypoint_format("halpe_26", [x[:, :17] for x in raw_people])
        with pytest.raises(KeypointFormatError, match=r"18 keypoints per person match no known"):
            check_keypoint_format("auto", [x[:, :18] for x in raw_people])
        hidden = [x.clone() for x in raw_people]
        for x in hidden:
            x[:, [2, 9], 2] = 0  # neither BODY_25 triple (1, 2, 5), (8, 9, 12) complete
        with pytest.raises(KeypointFormatError, match=r"no person shows both hips or both "
                                                      r"shoulders .* set data\.keypoints\.format"):
            check_keypoint_format("auto", hidden)
        with pytest.raises(KeypointFormatError, match=r"different keypoint counts"):
            check_keypoint_format("auto", [raw_people[0], raw_people[1][:, :17]])


class TestWriteJson:
    def test_feature_round_trip(self, tmp_path):
        x = torch.rand(2, 33, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        path = write_openpose_json(tmp_path / "sub" / "cam01.000007.json", x, {"note": [1, 2]})
        assert torch.equal(read_openpose_json(path, 33), x)
        data = json.loads(path.read_text())
        assert data["version"] == 1.3 and data["note"] == [1, 2]
        assert check_keypoint_format("auto", [x]) == "mediapipe_33"
        empty = write_openpose_json(tmp_path / "none.json", torch.zeros(0, 33, 3))
        assert read_openpose_json(empty, 33).shape == (0, 33, 3)
        assert not list(tmp_path.rglob("*.tmp*"))

    def test_exception(self, tmp_path):
        with pytest.raises(KeypointFormatError, match=r"people: expected shape \(P, K, 3\)"):
            write_openpose_json(tmp_path / "a.json", torch.zeros(33, 3))
        with pytest.raises(KeypointFormatError, match=r"finite values and confidences"):
            write_openpose_json(tmp_path / "a.json", torch.full((1, 2, 3), float("nan")))
        with pytest.raises(KeypointFormatError, match=r"must not set 'version'"):
            write_openpose_json(tmp_path / "a.json", torch.zeros(1, 2, 3), {"people": []})
        with pytest.raises(KeypointFormatError, match=r"extra: expected JSON-safe"):
            write_openpose_json(tmp_path / "a.json", torch.zeros(1, 2, 3), {"x": object()})
        assert not (tmp_path / "a.json").exists()
