"""The recording checks (``torchmocap.data.recordings.checks``) on the trimmed pose2sim_balancing
recording, intact and corrupted the way real recordings are (``broken``, conftest.py): the
intact one passes without a word; every corruption is refused or reported, naming the view or
setting."""

from __future__ import annotations

import time
import warnings

import pytest
import torch

from torchmocap.cameras import CameraError, read_toml_calibration
from torchmocap.data.recordings.checks import (
    MAX_VIEW_RESIDUAL,
    STATURE_RANGE_M,
    RecordingCheckError,
    check_camera_choice,
    view_consistency,
)
from torchmocap.data.recordings.loader import load_recording
from torchmocap.io.frames import FrameSourceError, ImageFolderFrames

pytestmark = pytest.mark.filterwarnings("ignore:.*codec's crop")
KW = {"masks": "none", "scale": 0.25, "stop": 4}
CAMS = ["cam01", "cam02", "cam03", "cam04"]


@pytest.fixture
def p2s_calibration(shared_data):
    return read_toml_calibration(shared_data / "multiview" / "pose2sim_balancing" /
                                 "calibration" / "Calib.toml")


def _load(path, **kw):
    """The recording's sequence and its warnings (the codec crops left out)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = load_recording(path, **{**KW, **kw})
    return seq, [str(w.message) for w in caught if "codec's crop" not in str(w.message)]


class TestIntact:
    def test_feature_silent_and_consistent(self, broken):
        seq, said = _load(broken("intact"), stop=10, heldout_camera="cam01")
        assert said == []
        r = seq.meta.view_consistency
        assert r["consistent_views"] == CAMS and r["heldout_camera"] == "cam01"
        assert 1.5 < r["stature_m"] < 1.9 and r["frames"] == list(range(10))
        for name in CAMS:
            v = r["views"][name]
            assert v["status"] == "consistent" and v["points"] >= 100
            # within half the limit: the margin the limit keeps on intact data
            assert 0 < v["relative"] < MAX_VIEW_RESIDUAL / 2
            assert 5 < v["residual_px"] < 60 and 600 < v["subject_px"] < 1000
            # the cameras stand 3-4.5 m from the subject, as their images show
            assert 2.5 < v["distance_m"] < 4.5
            assert 0.7 < v["distance_m"] / v["apparent_distance_m"] < 1.4
            assert set(v["against"]) == set(CAMS) - {name}

    def test_feature_residual_is_a_reprojection(self, broken):
        """A view's figure is the median distance of its detections from the others'
        triangulation: its own detections moved by 40 px move it by about that."""
        seq, _ = _load(broken("intact"))
        j = seq.joints2d.clone()
        rig = seq.rig
        base = view_consistency(j, rig, CAMS, 0.25)["views"]["cam03"]["residual_px"]
        j[:, 2, :, 0] += torch.where(j[:, 2, :, 2] > 0, 10.0, 0.0)  # 40 full-size px
        moved = view_consistency(j, rig, CAMS, 0.25)["views"]["cam03"]["residual_px"]
        assert abs(moved - base) > 15 and moved < base + 45

    def test_exception_camera_choice_first(self, broken):
        """Too few tracked views are refused before anything is read: a recording whose
        videos are unreadable gets this error, not the video's."""
        root = broken("intact")
        for v in (root / "videos").glob("*.mp4"):
            v.write_bytes(b"not a video")
        t0 = time.perf_counter()
        with pytest.raises(ValueError, match=r"data\.cameras: the tracker sees 1 view "
                                             r"\(cam02\).*at least 2 views"):
            load_recording(root, cameras=["cam02"], min_views=2)
        with pytest.raises(ValueError, match=r"data\.cameras: the tracker sees 1 view "
                                             r"\(cam03; cam01 is held out "
                                             r"\(evaluation\.heldout_camera\)\)"):
            load_recording(root, cameras=["cam01", "cam03"], heldout_camera="cam01",
                           min_views=2)
        assert time.perf_counter() - t0 < 2.0
        check_camera_choice(["cam01"], None, 0)  # a library load of one view is fine


    def test_feature_a_subject_too_small_in_the_images(self, broken):
        _, said = _load(broken("intact"), stop=2, scale=0.02)
        assert len(said) == 1 and said[0].startswith("data.scale=0.02: the subject is at most "
                                                     "18 px tall in the scaled images")


class TestUnits:
    def test_exception_millimetres_in_a_metres_file(self, broken):
        root = broken("millimetres")
        with pytest.raises(RecordingCheckError, match=r"data\.unit: the subject triangulated "
                                                      r"from the first frames measures 16\d\d m"
                                                      r".*set data\.unit=mm"):
            load_recording(root, **KW)
        # reported, not refused, when asked; the figures say what is wrong
        seq, said = _load(root, checks="warn")
        assert any("data.unit=mm" in w for w in said)
        assert 1400 < seq.meta.view_consistency["stature_m"] < 1900
        # read in its unit, it is the intact recording
        seq, said = _load(root, unit="mm")
        assert said == [] and STATURE_RANGE_M[0] < seq.meta.view_consistency["stature_m"] < 2

    def test_exception_metres_read_as_millimetres(self, broken):
        with pytest.raises(RecordingCheckError, match=r"measures 0\.00\d+ m.*data\.unit=mm"
                                                      r".*set data\.unit=m\b"):
            load_recording(broken("intact"), unit="mm", **KW)


class TestViews:
    @pytest.mark.parametrize("kind", ["calibrations_exchanged", "detections_exchanged"])
    def test_exception_exchanged(self, broken, kind):
        with pytest.raises(RecordingCheckError) as e:
            load_recording(broken(kind), heldout_camera="cam01", **KW)
        msg = str(e.value)
        assert "\n" not in msg
        assert msg.startswith("data.cameras: cam01, cam02 disagree with the other views")
        assert "cam01 (held out)" in msg and "triangulation of cam03, cam04" in msg
        assert "their calibrations or their detections are exchanged" in msg
        assert "data.cameras=[cam03,cam04]" in msg and "data.checks=warn" in msg

    def test_exception_camera_far_away(self, broken):
        with pytest.raises(RecordingCheckError, match=r"cam02 disagrees with the other views: "
                                                      r"cam02 \d+ px.*triangulation of cam01, "
                                                      r"cam03, cam04.*its calibration: the "
                                                      r"camera is 1\.73\de\+06 m from the "
                                                      r"subject.*about [34]\.\d m away"):
            load_recording(broken("camera_far"), **KW)

    def test_feature_warn_mode_reports_and_goes_on(self, broken):
        seq, said = _load(broken("calibrations_exchanged"), checks="warn")
        assert len(said) == 1 and "cam01, cam02 disagree" in said[0]
        r = seq.meta.view_consistency
        assert r["consistent_views"] == ["cam03", "cam04"]
        for name in ("cam01", "cam02"):
            v = r["views"][name]
            assert v["status"] == "inconsistent" and v["relative"] > MAX_VIEW_RESIDUAL
            assert "exchanged" in v["cause"]

    def test_exception_mode(self, broken):
        with pytest.raises(ValueError, match=r"data\.checks: expected one of \['refuse', "
                                             r"'warn'\], got 'off'"):
            load_recording(broken("intact"), checks="off", **KW)


class TestDetections:
    def test_feature_outside_the_image(self, broken):
        seq, said = _load(broken("outside"))
        assert len(said) == 1 and said[0].startswith("cam02: all of its")
        assert "outside its 1080x1920 pixels; dropped" in said[0]
        assert int(seq.joints2d[:, 1, :, 2].count_nonzero()) == 0  # missing, not wrong
        assert seq.meta.view_consistency["views"]["cam02"]["status"] == "no detections"
        assert seq.meta.view_consistency["consistent_views"] == ["cam01", "cam03", "cam04"]

    def test_feature_half_size_images(self, broken):
        seq, said = _load(broken("half_size"), checks="warn")
        quarter = [w for w in said if "top-left quarter" in w]
        assert len(quarter) == 1 and quarter[0].startswith("cam02: every keypoint")
        assert any(w.startswith("data.cameras: cam02 disagrees") for w in said)

    def test_feature_confidences_above_one(self, broken):
        _, said = _load(broken("confidences"))
        assert len(said) == 1 and said[0].startswith("cam02: keypoint confidences up to 2.")
        assert "above 1" in said[0]

    @pytest.mark.parametrize("heldout,cameras", [("cam01", None), ("cam03", None),
                                                 (None, ["cam02", "cam03", "cam04"])])
    def test_feature_nobody_in_one_view(self, broken, heldout, cameras):
        """A view where nobody was detected (the first loaded one too): loaded, its keypoints
        missing, said by name."""
        seq, said = _load(broken("nobody"), heldout_camera=heldout, cameras=cameras)
        assert len(said) == 1 and said[0].startswith("cam02: nobody detected in any loaded "
                                                     "frame 0..3")
        c = seq.rig.names.index("cam02")
        assert int(seq.joints2d[:, c, :, 2].count_nonzero()) == 0
        assert seq.meta.view_consistency["views"]["cam02"]["status"] == "no detections"
        assert seq.meta.subject_skeleton is not None

    @pytest.mark.parametrize("fmt", ["auto", "body_25b"])
    def test_exception_nobody_anywhere(self, broken, fmt):
        with pytest.raises(ValueError, match=r"nobody (is )?detected in any.*"
                                             r"data\.keypoints\.source=none") as e:
            load_recording(broken("nobody_anywhere"), keypoints={"format": fmt}, **KW)
        assert "start at another frame" not in str(e.value)


class TestImageFolders:
    def test_exception_gap(self, broken):
        root = broken("image_gap")
        with pytest.raises(FrameSourceError, match=r"images/cam02: no image for frame 2 \(the "
                                                   r"images are numbered 0\.\.4; number\(s\) 2 "
                                                   r"missing\).*data\.stop=2"):
            load_recording(root, **KW)
        seq = load_recording(root, **{**KW, "stop": 2, "fps": 60})  # before the gap
        assert seq.num_frames == 2

    def test_feature_numbered_frames_pair_by_number(self, tmp_path):
        import numpy as np
        from PIL import Image

        folder = tmp_path / "cam"
        folder.mkdir()
        for n in (3, 4, 6):  # frame t is image 3 + t; 5 is missing
            Image.fromarray(np.full((4, 6, 3), 10 * n, np.uint8)).save(folder / f"im{n}.png")
        frames = ImageFolderFrames(folder)
        assert frames.num_frames == 4 and frames.missing() == [2]
        assert [int(f[0, 0, 0]) for f in frames.frames(0, 2)] == [30, 40]
        with pytest.raises(FrameSourceError, match="no image for frame 2"):
            list(frames.frames(0, 4))
        (folder / "im6.png").rename(folder / "im06.png")
        Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(folder / "im6.png")
        with pytest.raises(FrameSourceError, match="im06.png and im6.png are both frame 6"):
            ImageFolderFrames(folder)


class TestSizes:
    def test_feature_a_camera_at_half_resolution(self, broken):
        """cam04 recorded at 544x960 with a calibration of its own size: loaded beside the
        1088x1920 views (its images in the tensor's top-left corner), consistent with them."""
        root = broken("half_resolution_camera")
        seq, said = _load(root, stop=2)
        assert said == []
        assert seq.rig.image_size.tolist()[3] == [136, 240]
        assert seq.images.shape[2:4] == (480, 272)
        assert int(seq.images[:, 3, 240:].max()) == 0 and int(seq.images[:, 3, :, 136:].max()) \
            == 0 and float(seq.images[:, 3, :240, :136].float().mean()) > 20
        assert seq.meta.image_sizes["cam04"] == [544, 960]
        r = seq.meta.view_consistency
        assert r["consistent_views"] == CAMS
        assert 300 < r["views"]["cam04"]["subject_px"] < 500  # its own pixels

    @pytest.mark.slow
    def test_feature_half_resolution_camera_through_a_track(self, broken, tmp_path):
        """Every consumer of the views' sizes on that recording: computed masks, the
        silhouette and keypoint terms, the held-out and tracked scores, the overlays."""
        from hydra import compose, initialize_config_module
        from hydra.core.global_hydra import GlobalHydra
        from PIL import Image

        from torchmocap.cli.track import run

        root = broken("half_resolution_camera")
        GlobalHydra.instance().clear()
        with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
            cfg = compose(config_name="track", overrides=[
                "data=recording", f"data.path={root}", "data.stop=3", "data.scale=0.25",
                "data.mask_cache=null", "tracker=real_keypoints", "tracker.num_particles=30",
                "tracker.inference.layers=3", "evaluation.heldout_camera=cam04",
                "overlays=1", "glb.enabled=false", "progress=false", "threads=1"])
        out = tmp_path / "run"
        out.mkdir()
        m = run(cfg, out)
        h = m["heldout"]
        assert h["camera"] == "cam04" and h["median_px"] < 60 and h["pck_10"] > 0.8
        assert 0.3 < h["silhouette_iou"] < 1.0
        assert all(v["median_px"] < 60 for v in m["tracked_views"].values())
        (grid,) = out.glob("overlay_*.png")
        with Image.open(grid) as im:
            assert im.size == (544, 20 + 960)

    def test_feature_calibration_at_another_resolution(self, broken, p2s_calibration):
        seq, said = _load(broken("calibration_4k"), stop=2, scale=1.0)
        assert len(said) == 1 and "the calibration (cam_03) is of 2176x3840 images, the same " \
            "aspect ratio: its intrinsics are scaled by 0.5" in said[0]
        torch.testing.assert_close(seq.rig.K[2], p2s_calibration.K[2].float(), rtol=1e-6,
                                   atol=1e-3)
        assert seq.meta.view_consistency["consistent_views"] == CAMS

    def test_exception_not_a_codec_crop(self, broken):
        with pytest.raises(CameraError, match=r"frames are 1088x1920 but the calibration .*"
                                              r"says 1100x1920; the calibration is of other "
                                              r"images \(not a codec's crop"):
            load_recording(broken("size_12px"), **KW)

    def test_exception_an_image_named_as_a_video(self, broken):
        with pytest.raises(FrameSourceError, match=r"cam02\.mp4: a single PNG image, not a "
                                                   r"video"):
            load_recording(broken("png_video"), **KW)
