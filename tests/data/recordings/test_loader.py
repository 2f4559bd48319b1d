"""``load_recording`` on the real trimmed recordings (pose2sim_balancing: 4 videos, H.264 and
VP9, two of them codec-cropped, BODY_25B keypoints with a bystander; the bodytrack frame), its
Hydra config, and one broken copy of the recording per kind of bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import warnings

import pytest
import torch

from torchmocap.cameras import CameraError, read_toml_calibration, triangulate_dlt
from torchmocap.data import split_heldout
from torchmocap.data.recordings.bodytrack import load_bodytrack
from torchmocap.data.recordings.files import RecordingLayoutError, discover_recording
from torchmocap.data.recordings.loader import load_recording
from torchmocap.io.frames import FrameSourceError, VideoFrames
from torchmocap.io.openpose import KEYPOINT_FORMATS, KeypointFormatError, read_openpose_json

CROP = r"frames are 1080x1920, the calibration \(cam_0[12]\) says 1088x1920: a codec's crop"


@pytest.fixture(scope="module")
def p2s(shared_data):
    return shared_data / "multiview" / "pose2sim_balancing"


@pytest.fixture(scope="module")
def seq(p2s):
    """The whole trimmed recording at the default settings (scale 0.5) but without masks
    (computed masks: TestMasks)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = load_recording(p2s, masks="none")
    s.meta.extra["warnings"] = [str(w.message) for w in caught]
    return s


@pytest.fixture
def copy(tmp_path, p2s):
    """A writable copy of the trimmed recording, for breaking."""
    dst = tmp_path / "rec"
    shutil.copytree(p2s, dst, ignore=shutil.ignore_patterns("background", "pose2sim_output"))
    return dst


def _load(path, **kw):
    """A load without computed masks unless asked (they are tested in TestMasks)."""
    kw.setdefault("masks", "none")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        return load_recording(path, **kw)


def _ffmpeg(*args: str) -> None:
    import imageio_ffmpeg

    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-loglevel", "error",
                    "-y", *args], check=True)


def _associated(p2s, cam: str, t: int) -> torch.Tensor:
    return read_openpose_json(p2s / "pose-associated" / f"{cam}_json" / f"{cam}.{t:04d}.json",
                              25)[0]


class TestPose2Sim:
    def test_smoke(self, seq):
        assert seq.scenario == "recorded" and seq.fps == 60.0 and seq.num_frames == 10
        assert seq.images.shape == (10, 4, 960, 544, 3) and seq.images.dtype == torch.uint8
        assert seq.silhouettes is None and seq.meta.mask_source is None
        assert torch.equal(seq.view_dropped, torch.zeros(10, 4, dtype=torch.bool))
        assert seq.joints2d.shape == (10, 4, 25, 3) and seq.joints2d.dtype == torch.float32
        assert seq.joint_names == list(KEYPOINT_FORMATS["body_25b"])
        assert seq.rig.names == ["cam01", "cam02", "cam03", "cam04"]
        assert seq.rig.K.dtype == torch.float32
        # the codec-cropped views keep their decoded size, with a warning each
        assert seq.rig.image_size.tolist() == [[540, 960], [540, 960], [544, 960], [544, 960]]
        crops = [w for w in seq.meta.extra["warnings"] if "codec's crop" in w]
        assert len(crops) == 2 and "cam01.mp4" in crops[0] and "cam02.mp4" in crops[1]
        m = seq.meta
        assert m.source == "recording" and m.cameras == ["cam01", "cam02", "cam03",
                                                               "cam04"]
        assert m.calibration_names == ["cam_01", "cam_02", "cam_03", "cam_04"]
        assert m.frame_indices == list(range(10)) and m.fps == 60.0 and m.scale == 0.5
        assert m.keypoint_format == "body_25b" and m.keypoint_source == "openpose"
        assert m.keypoint_report["folder"] == "associated"
        assert m.image_sizes["cam01"] == [1080, 1920] and m.image_sizes["cam04"] == \
            [1088, 1920]
        assert m.calibrated_image_sizes["cam01"] == [1088, 1920]
        assert [p.split("/")[-1] for p in m.background["cam02"]] == ["cam02_ext.jpg"]
        assert m.images_bytes == 10 * 4 * 960 * 544 * 3
        assert m.heldout_camera is None
        # the subject fitted to the keypoints: skeleton, one first pose, the scaled map
        assert len(m.initial_poses) == 1 and m.keypoint_map["format"] == "body_25b"
        assert 1.6 < m.subject_fit["stature_m"] < 1.9

    def test_feature_images_are_the_videos_frames(self, seq, p2s):
        for c, cam in ((1, "cam02"), (3, "cam04")):
            frames = list(VideoFrames(p2s / "videos" / f"{cam}.mp4").frames(scale=0.5))
            w = 540 if c < 2 else 544
            for t in (0, 7):
                assert torch.equal(seq.images[t, c, :, :w], torch.from_numpy(frames[t].copy()))
        assert int(seq.images[:, :2, :, 540:].max()) == 0  # cropped views padded black
        assert float(seq.images[:, 2:, :, 540:].float().mean()) > 20

    def test_feature_keypoints_scaled(self, seq, p2s):
        """joints2d = the associated detections with ``u' + 0.5 = 0.5 (u + 0.5)``."""
        for c, cam in enumerate(["cam01", "cam02", "cam03", "cam04"]):
            for t in (0, 5, 9):
                a = _associated(p2s, cam, t)
                keep = a[:, 2] >= 0.1
                want = torch.where(keep[:, None], torch.cat([0.5 * (a[:, :2] + 0.5) - 0.5,
                                                             a[:, 2:]], -1), 0.0)
                torch.testing.assert_close(seq.joints2d[t, c], want.float())

    def test_feature_scaled_rig_agrees_with_scaled_keypoints(self, seq, p2s):
        """Triangulating the scaled keypoints in the scaled rig gives the points of the
        full-size keypoints in the file's calibration (the cropped views included)."""
        j = seq.joints2d.double()
        X = triangulate_dlt(j[..., :2], j[..., 2], seq.rig)
        full = torch.stack([torch.stack([_associated(p2s, c, t) for c in
                                         ["cam01", "cam02", "cam03", "cam04"]])
                            for t in range(10)])
        full[..., 2] = torch.where(full[..., 2] >= 0.1, full[..., 2], 0.0)
        rig = read_toml_calibration(p2s / "calibration" / "Calib.toml")
        ref = triangulate_dlt(full[..., :2], full[..., 2], rig)
        ok = torch.isfinite(ref).all(-1)
        assert int(ok.sum()) > 200
        torch.testing.assert_close(X[ok], ref[ok], atol=2e-4, rtol=0)  # float32 keypoints
        # the subject stands on the treadmill: its keypoints are 0-2 m above the floor
        assert 0.0 < float(ref[ok][:, 2].min()) and float(ref[ok][:, 2].max()) < 2.0

    def test_feature_agreement_report(self, seq):
        sel = seq.meta.selection
        assert sel["method"] == "associated"
        for cam, view in sel["views"].items():
            assert view["people"] == [1] * 10
            assert all(5 < a < 25 for a in view["agreement_px"]), (cam, view)

    def test_feature_raw_detections_select_the_subject(self, p2s):
        raw = _load(p2s, cameras=["cam01", "cam03"], stop=4, scale=0.25,
                    keypoints={"source": "openpose", "folder": "raw"})
        assert raw.meta.keypoint_report["folder"] == "raw"
        sel = raw.meta.selection
        assert sel["method"] == "triangulation"
        assert sel["views"]["cam01"]["frames_with_several_people"] == [0, 1, 2, 3]
        for t in range(4):
            for c, cam in enumerate(["cam01", "cam03"]):
                a = _associated(p2s, cam, t)
                a = torch.where((a[:, 2] >= 0.1)[:, None], a, 0.0)
                uv = torch.where(a[:, 2:] > 0, 0.25 * (a[:, :2] + 0.5) - 0.5, 0.0)
                torch.testing.assert_close(raw.joints2d[t, c, :, :2], uv.float())

    def test_feature_range_stride_and_cameras(self, seq, p2s):
        sub = _load(p2s, cameras=["cam_03", 0], start=2, stop=9, stride=3)
        assert sub.meta.frame_indices == [2, 5, 8] and sub.meta.cameras == ["cam03",
                                                                                  "cam01"]
        assert sub.rig.names == ["cam03", "cam01"]
        torch.testing.assert_close(sub.rig.R, seq.rig.R[[2, 0]])
        assert torch.equal(sub.images, seq.images[[2, 5, 8]][:, [2, 0]])
        assert torch.equal(sub.joints2d, seq.joints2d[[2, 5, 8]][:, [2, 0]])
        assert sub.rig.image_size.tolist() == [[544, 960], [540, 960]]
        assert sub.meta.subject_fit["views"] == ["cam03", "cam01"]

    def test_feature_keypoint_settings(self, p2s):
        none = _load(p2s, cameras=[3], stop=2, scale=0.25, keypoints={"source": "none"})
        assert none.joints2d is None and none.joint_names == [] and \
            none.meta.keypoint_format is None
        strict = _load(p2s, cameras=[3], stop=2, scale=0.25,
                       keypoints={"format": "body_25b", "min_confidence": 0.6})
        c = strict.joints2d[..., 2]
        assert bool(((c == 0) | (c >= 0.6)).all()) and bool((c == 0).any())
        # one view: nothing to triangulate, so no subject (and the meta says why)
        assert "one view" in strict.meta.subject_fit["skipped"]
        assert strict.meta.subject_skeleton is None


    def test_feature_save_round_trip(self, p2s, tmp_path):
        seq = _load(p2s, cameras=["cam02"], stop=2, scale=0.25)
        back = type(seq).load(seq.save(tmp_path / "seq"))
        assert torch.equal(back.images, seq.images) and torch.equal(back.joints2d, seq.joints2d)
        assert back.joint_names == seq.joint_names and back.meta == seq.meta
        torch.testing.assert_close(back.rig.K, seq.rig.K.double())


class TestBodytrack:
    def test_feature(self, shared_data):
        root = shared_data / "multiview" / "bodytrack_sequenceB_1"
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # one frame: no frame-rate warning
            seq = load_recording(root, scale=0.5)
        rig, grey, masks = load_bodytrack(root, 0.5)
        assert seq.images.shape == (1, 4, 240, 320, 3) and seq.silhouettes.shape == \
            (1, 4, 240, 320)
        for k in range(3):  # grey -> RGB, the same pixels as the bodytrack loader's
            assert torch.equal(seq.images[0, ..., k], grey)
        assert torch.equal(seq.silhouettes[0], masks)
        torch.testing.assert_close(seq.rig.t, rig.t.float())  # millimetres -> metres
        torch.testing.assert_close(seq.rig.K, rig.K.float())
        assert seq.rig.names == ["CAM1", "CAM2", "CAM3", "CAM4"]
        assert seq.joints2d is None and seq.meta.fps_source == "default"
        assert seq.meta.calibration_names == ["Camera1", "Camera2", "Camera3", "Camera4"]
        assert seq.meta.masks["CAM1"].endswith("FG1") and seq.meta.mask_source == "files"
        # no keypoints: the visual-hull start of the bodytrack loader
        assert len(seq.meta.initial_poses) == 12 and seq.meta.subject_fit is None
        assert 1.5 < seq.meta.hull_top_m < 2.0


class TestImageFolders:
    def _recording(self, tmp_path, shared_data, frames=3):
        """bodytrack's calibration with images/<cam>/ folders of ``frames`` frames and
        masks/<cam>/ numbered by frame."""
        src = shared_data / "multiview" / "bodytrack_sequenceB_1"
        root = tmp_path / "rec"
        shutil.copytree(src / "CALIB", root / "calibration")
        from PIL import Image

        for i in range(1, 5):
            img = Image.open(src / f"CAM{i}" / "image0000.png")
            fg = Image.open(src / f"FG{i}" / "image0000.png")
            (root / "images" / f"cam{i}").mkdir(parents=True)
            (root / "masks" / f"cam{i}").mkdir(parents=True)
            for t in range(frames):
                img.rotate(0 if t == 0 else 180).save(root / "images" / f"cam{i}" /
                                                      f"{t:06d}.jpg", quality=95)
                fg.rotate(0 if t == 0 else 180).save(root / "masks" / f"cam{i}" /
                                                     f"mask_{t:04d}.png")
        return root

    def test_feature(self, tmp_path, shared_data):
        root = self._recording(tmp_path, shared_data)
        # frames 1-2 are turned by 180 degrees: their masks fit no camera of the calibration,
        # which the views' check says (refused by default)
        with pytest.raises(ValueError, match=r"no three views' masks agree"):
            load_recording(root, scale=1.0, start=1)
        with pytest.warns(UserWarning, match=r"image folders carry no frame rate; using 25 fps"), \
                pytest.warns(UserWarning, match=r"no three views' masks agree"):
            seq = load_recording(root, scale=1.0, start=1, checks="warn")
        assert seq.fps == 25.0 and seq.meta.frame_indices == [1, 2]
        assert seq.silhouettes.shape == (2, 4, 480, 640)
        ref = load_bodytrack(shared_data / "multiview" / "bodytrack_sequenceB_1")[2]
        assert torch.equal(seq.silhouettes[0], ref.flip(-1).flip(-2))
        fast = load_recording(root, fps=30, masks="none", stop=1)
        assert fast.fps == 30.0 and fast.silhouettes is None and fast.meta.masks is None

    def test_feature_zero_one_masks(self, tmp_path, shared_data):
        """Masks written as 0/1 (numpy booleans) were read as empty (foreground above 127)."""
        import numpy as np
        from PIL import Image

        root = self._recording(tmp_path, shared_data, frames=1)
        want = load_recording(root, fps=30, scale=0.5).silhouettes
        for p in root.glob("masks/*/*.png"):
            Image.fromarray((np.asarray(Image.open(p)) > 127).astype(np.uint8)).save(p)
        got = load_recording(root, fps=30, scale=0.5).silhouettes
        assert torch.equal(got, want) and 0.03 < float(got.float().mean()) < 0.1

    def test_exception_masks(self, tmp_path, shared_data):
        root = self._recording(tmp_path, shared_data, frames=2)
        (root / "masks" / "cam2" / "mask_0001.png").unlink()
        with pytest.raises(FrameSourceError, match=r"masks/cam2: no mask file for frame 1"):
            load_recording(root, fps=30)
        shutil.rmtree(root / "masks" / "cam3")
        assert load_recording(root, fps=30).silhouettes is None  # auto: not every camera
        with pytest.raises(RecordingLayoutError, match=r"no mask folder .* \['cam3'\]"):
            load_recording(root, fps=30, masks="files")


class TestMasks:
    def test_feature_computed_and_cached(self, p2s, tmp_path):
        """``masks: compute`` at the working scale: subject-sized masks lined up with the
        images, cached (a second load reads the entry: equal masks, ``hit``) with a preview
        PNG beside the entry; ``mask_settings`` reach the computation (another key)."""
        from PIL import Image

        kw = dict(stop=3, scale=0.25, masks="compute", mask_cache=tmp_path)
        first = _load(p2s, **kw)
        rep = first.meta.mask_report
        assert first.silhouettes.shape == (3, 4, 480, 272) and not rep["cache"]["hit"]
        frac = first.silhouettes.flatten(2).double().mean(-1)
        assert bool((frac > 0.02).all()) and bool((frac < 0.2).all()), frac
        with Image.open(rep["preview"]) as im:
            assert im.size[1] == 480
        assert rep["preview"] == rep["cache"]["path"] + ".png"
        again = _load(p2s, **kw)
        assert again.meta.mask_report["cache"]["hit"]
        assert torch.equal(again.silhouettes, first.silhouettes)
        other = _load(p2s, mask_settings={"threshold": 8.0}, **kw)
        assert not other.meta.mask_report["cache"]["hit"]
        assert other.meta.mask_report["settings"]["threshold"] == 8.0
        assert int(other.silhouettes.sum()) < int(first.silhouettes.sum())

    def test_feature_auto(self, copy):
        """auto: computed with keypoints or plates (not cached without a cache folder; the
        cropped views' padding is never foreground); none without either."""
        auto = _load(copy, stop=2, scale=0.25, masks="auto")
        assert auto.meta.mask_source == "computed" and auto.meta.masks is None
        assert "cache" not in auto.meta.mask_report and auto.silhouettes.shape[1] == 4
        assert not bool(auto.silhouettes[:, :2, :, 270:].any())
        bare = _load(copy, stop=2, scale=0.25, masks="auto", keypoints={"source": "none"})
        assert bare.silhouettes is None and bare.meta.mask_source is None

    def test_exception(self, copy, p2s):
        with pytest.raises(ValueError, match=r"data\.masks: compute needs the subject's keypoints "
                                             r"or background plates"):
            _load(copy, stop=2, scale=0.25, masks="compute", keypoints={"source": "none"})
        with pytest.raises(ValueError, match=r"data\.masks: expected one of"):
            _load(p2s, masks="computed")
        with pytest.raises(ValueError, match=r"data\.mask_settings\.scale: the masks are "
                                             r"computed at the images' working scale"):
            _load(p2s, masks="compute", mask_settings={"scale": 0.5})
        with pytest.raises(ValueError, match=r"data\.mask_settings: unknown setting\(s\) "
                                             r"\['treshold'\]"):
            _load(p2s, masks="compute", mask_settings={"treshold": 3.0})
        with pytest.raises(ValueError, match=r"data\.mask_settings\.threshold"):
            _load(p2s, masks="compute", mask_settings={"threshold": -1.0})


class TestHeldOut:
    def test_feature_the_tracked_views_never_use_the_held_out_one(self, p2s):
        """With cam02 held out, the other views' detections and the subject fit are those of
        a recording loaded without cam02; the held-out view keeps its own detections."""
        held = _load(p2s, stop=3, scale=0.25, heldout_camera="cam02")
        ref = _load(p2s, stop=3, scale=0.25, cameras=["cam01", "cam03", "cam04"])
        assert held.meta.heldout_camera == "cam02" and held.num_cameras == 4
        tracked, view = split_heldout(held)
        assert tracked.rig.names == ["cam01", "cam03", "cam04"] and view.rig.names == ["cam02"]
        assert tracked.meta.cameras == ["cam01", "cam03", "cam04"]
        assert torch.equal(tracked.joints2d, ref.joints2d)
        assert torch.equal(tracked.images, ref.images)
        assert held.meta.initial_poses == ref.meta.initial_poses
        assert held.meta.subject_skeleton == ref.meta.subject_skeleton
        assert held.meta.subject_fit["views"] == ["cam01", "cam03", "cam04"]
        full = _load(p2s, stop=3, scale=0.25)
        assert torch.equal(view.joints2d, full.joints2d[:, 1:2])
        assert held.meta.initial_poses != full.meta.initial_poses

    @pytest.mark.slow
    def test_feature_masks_of_the_tracked_views_never_use_it(self, p2s, tmp_path):
        """The tracked views' computed masks are those of a recording without cam02 (the
        multi-view check carves with the tracked views only); the held-out view's come from
        every view, as a recording's masks without a held-out camera."""
        kw = dict(stop=2, scale=0.25, masks="compute", mask_cache=tmp_path)
        held = _load(p2s, heldout_camera="cam02", **kw)
        ref = _load(p2s, cameras=["cam01", "cam03", "cam04"], **kw)
        full = _load(p2s, **kw)
        assert full.meta.mask_report["cache"]["hit"]  # computed for the held-out view
        tracked, view = split_heldout(held)
        assert torch.equal(tracked.silhouettes, ref.silhouettes)
        assert torch.equal(view.silhouettes[:, 0, :, :270], full.silhouettes[:, 1, :, :270])
        assert not torch.equal(full.silhouettes[:, [0, 2, 3]], tracked.silhouettes)

    def test_feature_raw_detections_selected_without_it(self, p2s):
        held = _load(p2s, stop=2, scale=0.25, cameras=["cam01", "cam02", "cam03"],
                     keypoints={"source": "openpose", "folder": "raw"}, heldout_camera=1)
        ref = _load(p2s, stop=2, scale=0.25, cameras=["cam01", "cam03"],
                    keypoints={"source": "openpose", "folder": "raw"})
        tracked, _ = split_heldout(held)
        assert held.meta.heldout_camera == "cam02"
        assert torch.equal(tracked.joints2d, ref.joints2d)
        assert held.meta.selection == ref.meta.selection

    def test_exception(self, p2s):
        where = r"evaluation\.heldout_camera: "
        with pytest.raises(ValueError, match=where + r"unknown camera 'cam09'"):
            _load(p2s, stop=2, heldout_camera="cam09")
        with pytest.raises(ValueError, match=where + r"camera 'cam02' is not among the loaded "
                                                     r"cameras \(data\.cameras: \['cam01', "
                                                     r"'cam03'\]\)"):
            _load(p2s, stop=2, cameras=["cam01", "cam03"], heldout_camera="cam02")
        with pytest.raises(ValueError, match=where + r"index 4 out of range"):
            _load(p2s, stop=2, heldout_camera=4)
        with pytest.raises(ValueError, match=where + r"holding out 'cam01' leaves no camera"):
            _load(p2s, stop=2, cameras=["cam01"], heldout_camera="cam01")
        with pytest.raises(ValueError, match=where + r"expected a camera name or index"):
            _load(p2s, stop=2, heldout_camera=1.5)


class TestConfig:
    def test_module(self, p2s):
        """``data=recording`` composes and builds through the CLI's sequence loader."""
        from hydra import compose, initialize_config_module
        from hydra.core.global_hydra import GlobalHydra

        from torchmocap.assembly import load_sequence

        GlobalHydra.instance().clear()
        with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
            cfg = compose(config_name="track", overrides=[
                "data=recording", f"data.path={p2s}", "data.cameras=[cam04]", "data.stop=2",
                "data.scale=0.25", "data.keypoints.source=none"])
        assert cfg.data._target_ == "torchmocap.data.recordings.loader.load_recording"
        seq = load_sequence(cfg)
        assert seq.images.shape == (2, 1, 480, 272, 3) and seq.meta.source == "recording"


@pytest.mark.filterwarnings("ignore:.*codec's crop")
class TestBadInput:
    def test_exception_unknown_camera(self, p2s):
        with pytest.raises(ValueError, match=r"data\.cameras: unknown camera 'cam05'; the "
                                             r"recording has \['cam01', 'cam02', 'cam03', "
                                             r"'cam04'\]"):
            load_recording(p2s, cameras=["cam05"])
        with pytest.raises(ValueError, match=r"data\.cameras: index 4 out of range"):
            load_recording(p2s, cameras=[4])

    def test_exception_missing_video(self, copy):
        (copy / "videos" / "cam02.mp4").unlink()
        with pytest.raises(RecordingLayoutError, match=r"pose-associated/cam02_json: keypoints "
                                                       r"of a camera without frames"):
            load_recording(copy)

    def test_exception_missing_keypoints(self, copy):
        shutil.rmtree(copy / "pose-associated" / "cam03_json")
        with pytest.raises(RecordingLayoutError, match=r"keypoints missing for camera\(s\) "
                                                       r"pose-associated/<cam>_json: \['cam03'\]"):
            load_recording(copy, keypoints={"source": "openpose", "folder": "associated"})
        # auto falls back to the raw detections every camera has
        seq = _load(copy, cameras=["cam03", "cam04"], stop=1, scale=0.25)
        assert seq.meta.keypoint_report["folder"] == "raw"

    def test_exception_missing_calibration(self, copy):
        calib = copy / "calibration" / "Calib.toml"
        text = calib.read_text()
        calib.write_text(text[:text.index("[cam_04]")] + text[text.index("[metadata]"):])
        with pytest.raises(CameraError, match=r"no calibration for camera 'cam04' .*cam04\.mp4"):
            load_recording(copy, cameras=["cam04"])
        shutil.rmtree(copy / "calibration")
        with pytest.raises(RecordingLayoutError, match=r"no calibration \(looked in"):
            load_recording(copy)

    def test_exception_ambiguous_calibration(self, copy):
        calib = copy / "calibration" / "Calib.toml"
        text = calib.read_text()
        block = text[text.index("[cam_04]"):text.index("[metadata]")]
        calib.write_text(text + "\n" + block.replace("cam_04", "camera4"))
        with pytest.raises(CameraError, match=r"calibration entries \['cam_04', 'camera4'\] all "
                                              r"match camera 'cam04'"):
            load_recording(copy, cameras=["cam04"])

    def test_exception_calibrated_size(self, copy):
        calib = copy / "calibration" / "Calib.toml"
        text = calib.read_text().split("[cam_03]")
        calib.write_text(text[0] + "[cam_03]" + text[1].replace("1088.0", "1280.0", 1))
        with pytest.raises(CameraError, match=r"cam03\.mp4: frames are 1088x1920 but the "
                                              r"calibration .*cam_03\) says 1280x1920"):
            load_recording(copy, cameras=["cam03"])

    def test_exception_lengths(self, copy):
        video = copy / "videos" / "cam04.mp4"
        _ffmpeg("-i", str(video), "-c", "copy", "-frames:v", "6", str(copy / "short.mp4"))
        shutil.move(copy / "short.mp4", video)
        with pytest.raises(FrameSourceError, match=r"cameras of different lengths: .*cam03\.mp4 "
                                                   r"10 frames.*cam04\.mp4 6 frames; set "
                                                   r"data\.stop <= 6"):
            load_recording(copy, cameras=["cam03", "cam04"])
        assert _load(copy, stop=6, cameras=["cam03", "cam04"], scale=0.25).num_frames == 6

    def test_exception_frame_rates(self, copy):
        video = copy / "videos" / "cam04.mp4"
        _ffmpeg("-itsscale", "2", "-i", str(video), "-c", "copy", str(copy / "slow.mp4"))
        shutil.move(copy / "slow.mp4", video)
        with pytest.raises(FrameSourceError, match=r"videos of different frame rates: .*cam03"
                                                   r"\.mp4 60 fps.*cam04\.mp4 3\d"):
            load_recording(copy, cameras=["cam03", "cam04"])

    def test_feature_sizes(self, copy):
        """A view half the size of the others shares their image tensor (it was refused), in
        its top-left corner, with its own size in the rig (test_checks.py: TestSizes)."""
        video = copy / "videos" / "cam04.mp4"
        _ffmpeg("-i", str(video), "-vf", "scale=544:960", "-c:v", "mpeg4",
                str(copy / "small.mp4"))
        shutil.move(copy / "small.mp4", video)
        calib = copy / "calibration" / "Calib.toml"
        text = calib.read_text().split("[cam_04]")
        calib.write_text(text[0] + "[cam_04]" + text[1].replace("[ 1088.0, 1920.0]",
                                                                "[ 544.0, 960.0]", 1))
        seq = _load(copy, cameras=["cam03", "cam04"], stop=2, scale=0.25,
                    keypoints={"source": "none"})
        assert seq.images.shape == (2, 2, 480, 272, 3)
        assert seq.rig.image_size.tolist() == [[272, 480], [136, 240]]
        assert int(seq.images[:, 1, 240:].max()) == 0 and int(seq.images[:, 1, :, 136:].max()) \
            == 0

    def test_exception_keypoint_format(self, copy):
        p = copy / "pose-associated" / "cam02_json" / "cam02.0003.json"
        x = read_openpose_json(p, 25)[:, :17]
        p.write_text(json.dumps({"people": [{"pose_keypoints_2d": x.flatten().tolist()}]}))
        with pytest.raises(KeypointFormatError, match=r"cam02\.0003\.json: people\[0\]\."
                                                      r"pose_keypoints_2d has 51 values = 17 "
                                                      r"keypoints, expected 25"):
            load_recording(copy, cameras=["cam01", "cam02"])
        with pytest.raises(KeypointFormatError, match=r"cam01\.0000\.json: .* 25 keypoints, "
                                                      r"expected 17"):
            load_recording(copy, cameras=["cam01"], keypoints={"format": "coco_17"})
        with pytest.raises(KeypointFormatError, match=r"declared 'body_25', but the detections "
                                                      r"look like 'body_25b'"):
            load_recording(copy, cameras=["cam01"], stop=3, keypoints={"format": "body_25"})

    def test_exception_bad_json(self, copy):
        folder = copy / "pose-associated" / "cam01_json"
        (folder / "cam01.0002.json").write_text("")
        with pytest.raises(KeypointFormatError, match=r"cam01\.0002\.json: empty file"):
            load_recording(copy, cameras=["cam01"])
        (folder / "cam01.0002.json").write_text('{"people": [{"pose_keypoints_2d": [1, 2,')
        with pytest.raises(KeypointFormatError, match=r"cam01\.0002\.json:1: not valid JSON"):
            load_recording(copy, cameras=["cam01"])
        (folder / "cam01.0002.json").unlink()
        with pytest.raises(FrameSourceError, match=r"cam01_json: no keypoint file for frame 2"):
            load_recording(copy, cameras=["cam01"])

    @pytest.mark.parametrize("kw, match", [
        ({"stride": 0}, r"data\.stride: expected an integer >= 1"),
        ({"scale": 0.0}, r"data\.scale: expected an image scale in \(0, 1\]"),
        ({"scale": 2.0}, r"data\.scale: expected an image scale in \(0, 1\]"),
        ({"start": 10}, r"data\.start: expected an integer frame index in \[0, 10\)"),
        ({"start": 4, "stop": 2}, r"data\.stop: expected an integer in \(4, 10\]"),
        ({"stop": 11}, r"data\.stop: expected an integer in \(0, 10\]"),
        ({"masks": "maybe"}, r"data\.masks: expected one of"),
        ({"fps": 30}, r"data\.fps: 30 differs from the videos' 60 fps"),
        ({"keypoints": {"source": "both"}},
         r"data\.keypoints\.source: unknown source 'both'; expected one of \['auto', 'none', "
         r"'mediapipe', 'openpose'"),
        ({"keypoints": {"source": "openpose", "folder": "both"}},
         r"data\.keypoints\.folder: expected one of \['auto', 'associated', 'raw'\]"),
        ({"keypoints": {"source": "auto", "folder": "raw"}},
         r"data\.keypoints: unknown setting\(s\) \['folder'\]"),
        ({"keypoints": {"min_conf": 0.2}}, r"data\.keypoints: unknown setting\(s\) \['min_conf'"),
        ({"keypoints": {"format": "mpii"}}, r"keypoint format 'mpii' is unknown"),
    ])
    def test_exception_settings(self, p2s, kw, match):
        with pytest.raises(ValueError, match=match):
            load_recording(p2s, cameras=["cam03"], **kw)

    def test_exception_layout(self, tmp_path, p2s):
        with pytest.raises(RecordingLayoutError, match=r"data\.path: no such recording folder"):
            discover_recording(tmp_path / "missing")
        (tmp_path / "calibration").mkdir()
        shutil.copy(p2s / "calibration" / "Calib.toml", tmp_path / "calibration")
        with pytest.raises(RecordingLayoutError, match=r"no camera frames \(expected videos/"):
            discover_recording(tmp_path)
        (tmp_path / "videos").mkdir()
        shutil.copy(p2s / "videos" / "cam01.mp4", tmp_path / "videos" / "cam01.mp4")
        shutil.copy(p2s / "videos" / "cam01.mp4", tmp_path / "videos" / "cam_1.mp4")
        with pytest.raises(RecordingLayoutError, match=r"cam01\.mp4 and .*cam_1\.mp4 are the "
                                                       r"same camera"):
            discover_recording(tmp_path)
