"""SequenceMeta: the typed record of a sequence's metadata."""

from __future__ import annotations

import json

import pytest
import torch

from torchmocap.data import Sequence, SequenceMeta


class TestSequenceMeta:
    def test_smoke(self):
        m = SequenceMeta(source="recording", cameras=["a", "b"], scale=0.5)
        assert m.to_dict() == {"source": "recording", "cameras": ["a", "b"], "scale": 0.5}
        assert SequenceMeta().to_dict() == {}

    def test_feature_round_trip_keeps_fields_and_extra(self):
        d = {"seed": 3, "clip": {"name": "walk"}, "initial_poses": [[0.0, 1.0]],
             "operator": "x"}
        m = SequenceMeta.from_dict(d)
        assert m.seed == 3 and m.clip == {"name": "walk"} and m.initial_poses == [[0.0, 1.0]]
        assert m.extra == {"operator": "x"}  # not a field: kept, not read
        assert m.to_dict() == d and SequenceMeta.from_dict(m.to_dict()) == m

    def test_feature_update_sets_fields(self):
        m = SequenceMeta().update({"subject_skeleton": {"a": 1}, "skeleton_scale": 1.1})
        assert m.subject_skeleton == {"a": 1} and m.skeleton_scale == 1.1

    def test_exception(self):
        with pytest.raises(KeyError, match=r"'initial_pose' is not a SequenceMeta field "
                                           r"\(did you mean 'initial_poses'\?\)"):
            SequenceMeta().update({"initial_pose": [[0.0]]})
        with pytest.raises(TypeError, match="meta: expected a SequenceMeta or a mapping"):
            SequenceMeta.from_dict([("seed", 1)])

    def test_feature_sequence_takes_a_dict_and_saves_the_record(self, tmp_path):
        seq = Sequence(fps=25.0, joints2d=torch.zeros(2, 1, 3, 3), joint_names=["a", "b", "c"],
                       meta={"heldout_camera": "cam02", "timings": {"total_s": 1.5},
                             "note": [1, 2]})
        assert isinstance(seq.meta, SequenceMeta) and seq.meta.heldout_camera == "cam02"
        back = Sequence.load(seq.save(tmp_path / "s"))
        assert back.meta == seq.meta and back.meta.extra == {"note": [1, 2]}
        # on disk: the plain dict of the fields that are set (what earlier versions wrote)
        man = json.loads((tmp_path / "s" / "manifest.json").read_text())
        assert man["meta"] == {"heldout_camera": "cam02", "timings": {"total_s": 1.5},
                               "note": [1, 2]}
