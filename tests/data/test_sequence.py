"""Sequence: frame access, required modalities, camera subsets and the held-out split, atomic
save/load round trip."""

from __future__ import annotations

import json

import pytest
import torch

from torchmocap.data import MissingModalityError, Sequence, SequenceFormatError
from torchmocap.data.subjects.mocap import fit_subject
from torchmocap.data.synthetic import load_scenario, synthesize
from torchmocap.io import bundled_clip_path, load_motion


@pytest.fixture(scope="module")
def seq():
    subject = fit_subject(load_motion(bundled_clip_path()).resample(25).slice(0, 3))
    sc = load_scenario("outdoor", image_size=[80, 60], silhouettes={"drop_view": 0.2})
    return synthesize(subject, sc, seed=11)


class TestSequence:
    def test_frame(self, seq):
        assert len(seq) == seq.num_frames == 3 and seq.num_cameras == 4
        f = seq.frame(1)
        assert f.index == 1 and f.time == pytest.approx(1 / 25)
        assert f.silhouettes.shape == (4, 60, 80) and f.images.shape == (4, 60, 80, 3)
        assert f.imu.shape == (10, 4) and f.imu_valid.shape == (10,)
        assert f.depth.shape == (int(seq.depth.counts[1]), 3)
        assert f.joints2d.shape == (4, 21, 3) and f.view_dropped.shape == (4,)
        assert f.theta.shape == (31,) and f.rotations.shape == (21, 3, 3)
        assert torch.equal(seq.frame(-1).positions, seq.ground_truth.positions[2])
        assert [fr.index for fr in seq] == [0, 1, 2]
        with pytest.raises(IndexError, match="t"):
            seq.frame(3)

    def test_require(self, seq):
        assert seq.require("silhouettes", "imu", "depth") is seq
        partial = Sequence(fps=25.0, scenario="partial", silhouettes=seq.silhouettes)
        assert partial.modalities == ["silhouettes"] and partial.num_frames == 3
        with pytest.raises(MissingModalityError, match="'imu'") as e:
            partial.require("silhouettes", "imu")
        assert e.value.modality == "imu" and "partial" in str(e.value)
        with pytest.raises(ValueError, match="unknown modality"):
            seq.require("smell")

    def test_select_cameras(self, seq):
        """A camera subset: the rig's cameras and those views of every per-view array, in the
        order asked; the rest shared, ``meta`` copied with the selected camera names."""
        import dataclasses

        from torchmocap.cameras import CameraRig

        sub = seq.select_cameras([2, 0])
        assert sub.num_cameras == 2 and sub.num_frames == 3
        torch.testing.assert_close(sub.rig.K, seq.rig.K[[2, 0]])
        for name in ("silhouettes", "images", "joints2d", "view_dropped"):
            assert torch.equal(getattr(sub, name), getattr(seq, name)[:, [2, 0]]), name
        assert sub.imu is seq.imu and sub.ground_truth is seq.ground_truth
        named = dataclasses.replace(seq, meta={"cameras": ["a", "b", "c", "d"], "x": [1]})
        other = named.select_cameras([3])
        assert other.meta.to_dict() == {"cameras": ["d"], "x": [1]} and named.meta.cameras[0] == "a"
        # views smaller than the array: cropped to the largest selected one
        rig = seq.rig
        small = CameraRig(rig.K, rig.R, rig.t, [[80, 60], [70, 50], [80, 60], [70, 50]],
                          rig.dist)
        cropped = dataclasses.replace(seq, rig=small).select_cameras([1, 3])
        assert cropped.images.shape[2:4] == (50, 70) and cropped.silhouettes.shape[2:] == (50, 70)
        for bad in ([], [0, 0], [4], [-1]):
            with pytest.raises(ValueError, match="indices"):
                seq.select_cameras(bad)
        with pytest.raises(ValueError, match="no cameras"):
            Sequence(fps=25.0).select_cameras([0])

    def test_split_heldout(self, seq):
        """The held-out camera named in ``meta`` is split off; a tracker refuses the sequence
        that still holds it."""
        import dataclasses

        from torchmocap.assembly import Runtime, build_tracker, tracker_config
        from torchmocap.data import split_heldout

        names = list(seq.rig.names)
        assert split_heldout(seq) == (seq, None)
        held = dataclasses.replace(seq, meta={**seq.meta.to_dict(), "heldout_camera": names[1]})
        tracked, view = split_heldout(held)
        assert tracked.rig.names == [names[0], *names[2:]] and view.rig.names == [names[1]]
        assert torch.equal(view.images, seq.images[:, 1:2])
        assert split_heldout(tracked) == (tracked, None)  # the camera is gone
        tracker = build_tracker(tracker_config("g"), Runtime.from_sequence(seq))
        with pytest.raises(ValueError, match=f"still holds its held-out camera '{names[1]}'"):
            tracker.check_sequence(held)
        tracker.check_sequence(tracked)

    def test_save_load_round_trip(self, seq, tmp_path):
        out = seq.save(tmp_path / "sequence")
        assert (out / "manifest.json").is_file()
        assert (out / "masks" / "cam3" / "00002.png").is_file()
        man = json.loads((out / "manifest.json").read_text())
        assert man["format"] == "torchmocap-sequence" and man["num_frames"] == 3
        assert man["imu"]["names"][0] == "back" and man["scenario"] == "outdoor"
        back = Sequence.load(out)
        assert back.modalities == seq.modalities and back.fps == seq.fps
        assert torch.equal(back.silhouettes, seq.silhouettes)
        assert torch.equal(back.images, seq.images)
        assert torch.equal(back.view_dropped, seq.view_dropped)
        for k in ("quaternions", "valid", "clean", "offsets", "misalignment", "drift_rates",
                  "tracking"):
            assert torch.equal(getattr(back.imu, k), getattr(seq.imu, k)), k
        assert back.imu.names == seq.imu.names and back.imu.bones == seq.imu.bones
        assert torch.equal(back.depth.points, seq.depth.points)
        assert torch.equal(back.depth.counts, seq.depth.counts)
        assert torch.allclose(back.depth.camera.K, seq.depth.camera.K.double())
        assert torch.equal(back.joints2d, seq.joints2d) and back.joint_names == seq.joint_names
        assert torch.allclose(back.rig.R, seq.rig.R.double()) and back.rig.names == seq.rig.names
        g, h = back.ground_truth, seq.ground_truth
        assert torch.equal(g.theta, h.theta) and torch.equal(g.rotations, h.rotations)
        assert torch.equal(g.positions, h.positions) and g.joint_names == h.joint_names
        sk = g.build_skeleton()
        assert torch.allclose(sk.offsets, h.build_skeleton().offsets)
        assert torch.equal(sk.lower, h.build_skeleton().lower)  # ±inf limits survive JSON
        assert back.meta.seed == 11 and back.meta.scenario["name"] == "outdoor"
        # loading through the manifest path works too
        assert Sequence.load(out / "manifest.json").num_frames == 3

    def test_save_is_atomic(self, seq, tmp_path, monkeypatch):
        target = tmp_path / "sequence"
        seq.save(target)
        with pytest.raises(FileExistsError, match="overwrite"):
            seq.save(target)
        first = json.loads((target / "manifest.json").read_text())
        # a failure while writing leaves the previous sequence intact and no temp dirs
        import torchmocap.data.sequence as mod

        def boom(*a, **k):
            raise OSError("disk full")

        monkeypatch.setattr(mod.np, "savez_compressed", boom)
        with pytest.raises(OSError, match="disk full"):
            seq.save(target, overwrite=True)
        assert json.loads((target / "manifest.json").read_text()) == first
        assert sorted(p.name for p in tmp_path.iterdir()) == ["sequence"]
        monkeypatch.undo()
        seq.save(target, overwrite=True)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["sequence"]
        assert Sequence.load(target).num_frames == 3

    def test_partial_sequence_round_trip(self, seq, tmp_path):
        part = Sequence(fps=25.0, scenario="imu-only", imu=seq.imu)
        back = Sequence.load(part.save(tmp_path / "s"))
        assert back.modalities == ["imu"] and torch.equal(back.imu.quaternions,
                                                          seq.imu.quaternions)

    def test_exception(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="manifest"):
            Sequence.load(tmp_path)
        (tmp_path / "manifest.json").write_text('{"format": "other"}')
        with pytest.raises(SequenceFormatError, match="format"):
            Sequence.load(tmp_path)
        (tmp_path / "manifest.json").write_text("{not json")
        with pytest.raises(SequenceFormatError, match="JSON"):
            Sequence.load(tmp_path)

    def test_missing_png_is_reported(self, seq, tmp_path):
        out = seq.save(tmp_path / "s")
        (out / "masks" / "cam1" / "00001.png").unlink()
        with pytest.raises(SequenceFormatError, match="00001.png"):
            Sequence.load(out)
