"""Frame sources: the real pose2sim videos (H.264 and VP9, codec-cropped sizes), image folders,
frame ranges, strides and the scaling convention."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
from PIL import Image

from torchmocap.io.frames import (
    FrameSourceError,
    ImageFolderFrames,
    VideoFrames,
    check_frame_range,
    frame_number,
    numbered_files,
    open_frames,
    resize_image,
    scaled_size,
)

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")


@pytest.fixture(scope="module")
def videos(shared_data):
    return shared_data / "multiview" / "pose2sim_balancing" / "videos"


@pytest.fixture(scope="module")
def decoded(videos):
    """``decoded(cam)``: every frame, decoded straight by imageio-ffmpeg (no range, no filter)."""
    cache: dict[str, list[np.ndarray]] = {}

    def get(cam: str) -> list[np.ndarray]:
        if cam not in cache:
            gen = imageio_ffmpeg.read_frames(str(videos / f"{cam}.mp4"))
            w, h = next(gen)["size"]
            cache[cam] = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
        return cache[cam]

    return get


class TestVideoFrames:
    def test_smoke(self, videos):
        cams = {c: open_frames(videos / f"{c}.mp4") for c in ("cam01", "cam02", "cam03")}
        assert all(isinstance(s, VideoFrames) for s in cams.values())
        # cam01/cam02 are coded at 1088 columns and cropped to 1080 by the codec
        assert cams["cam01"].size == (1080, 1920) and cams["cam03"].size == (1088, 1920)
        assert [cams[c].codec for c in cams] == ["h264", "vp9", "h264"]
        assert all(s.fps == 60.0 and s.num_frames == 10 for s in cams.values())
        frames = cams["cam01"].frames()
        assert isinstance(frames, types.GeneratorType)  # streamed, one frame at a time
        first = next(frames)
        frames.close()
        assert first.shape == (1920, 1080, 3) and first.dtype == np.uint8

    @pytest.mark.parametrize("cam, start, stop, stride", [
        ("cam02", 1, 9, 3), ("cam02", 9, 10, 1), ("cam03", 0, None, 1), ("cam03", 2, 10, 4)])
    def test_feature_exact_frames(self, videos, decoded, cam, start, stop, stride):
        """A range with a stride returns exactly the frames of those indices of a full decode
        (VP9 and H.264)."""
        src = VideoFrames(videos / f"{cam}.mp4")
        got = list(src.frames(start, stop, stride))
        want = list(range(start, stop or 10, stride))
        assert len(got) == len(want)
        for g, i in zip(got, want):
            np.testing.assert_array_equal(g, decoded(cam)[i])

    def test_feature_scaled(self, videos, decoded):
        src = VideoFrames(videos / "cam01.mp4")
        ref = decoded("cam01")[4]
        got = next(src.frames(4, 5, 1, scale=0.5))
        assert got.shape == (960, 540, 3)
        # a 2x reduction: close to the mean of each 2x2 block (antialiased bilinear)
        block = ref.reshape(960, 2, 540, 2, 3).mean((1, 3))
        assert np.abs(got.astype(float) - block).mean() < 2.0

    def test_exception(self, videos, tmp_path):
        with pytest.raises(FrameSourceError, match=r"nothing\.mp4: no such video file"):
            VideoFrames(tmp_path / "nothing.mp4")
        bad = tmp_path / "bad.mp4"
        bad.write_text("not a video")
        with pytest.raises(FrameSourceError, match=r"bad\.mp4: not a readable video"):
            VideoFrames(bad)
        src = VideoFrames(videos / "cam03.mp4")
        with pytest.raises(ValueError, match=r"stop: expected an integer in \(0, 10\]"):
            next(src.frames(0, 11))
        with pytest.raises(FrameSourceError, match=r"no such video file or image folder"):
            open_frames(tmp_path / "missing")


class TestImageFolderFrames:
    def _folder(self, tmp_path, names, size=(8, 6), mode="L"):
        d = tmp_path / "cam"
        d.mkdir()
        for i, n in enumerate(names):
            Image.new(mode, size, color=10 * i if mode == "L" else (10 * i, 0, 0)).save(d / n)
        return d

    def test_feature_natural_order_and_grey_to_rgb(self, tmp_path):
        d = self._folder(tmp_path, ["img9.png", "img10.png", "img8.bmp", "IMG11.JPG"])
        (d / "notes.txt").write_text("not an image")
        src = open_frames(d)
        assert isinstance(src, ImageFolderFrames) and src.fps is None
        assert [p.name for p in src.files] == ["img8.bmp", "img9.png", "img10.png", "IMG11.JPG"]
        assert src.first_number == 8 and src.missing() == []
        frames = list(src.frames())
        assert frames[0].shape == (6, 8, 3)
        # written in the order img9 (0), img10 (10), img8 (20), IMG11 (30, JPEG: near)
        assert [int(f[0, 0, 0]) for f in frames[:2]] == [20, 0]
        assert int(frames[2][0, 0, 1]) == 10 and abs(int(frames[3][0, 0, 0]) - 30) <= 2
        assert (frames[1][..., 0] == frames[1][..., 2]).all()
        # names without numbers: natural order
        plain = tmp_path / "plain"
        plain.mkdir()
        for n in ("b.png", "a.png"):
            Image.new("L", (8, 6)).save(plain / n)
        assert [p.name for p in ImageFolderFrames(plain).files] == ["a.png", "b.png"]

    def test_exception(self, tmp_path):
        d = self._folder(tmp_path, ["a0.png", "a1.png"])
        Image.new("L", (9, 6)).save(d / "a2.png")
        with pytest.raises(FrameSourceError, match=r"a2\.png: image size \(9, 6\) differs from "
                                                   r"the folder's first image a0\.png \(8, 6\)"):
            list(ImageFolderFrames(d).frames())
        (d / "a3.png").write_text("broken")
        with pytest.raises(FrameSourceError, match=r"a3\.png: cannot read image"):
            list(ImageFolderFrames(d).frames(3))
        empty = tmp_path / "empty"
        empty.mkdir()
        with pytest.raises(FrameSourceError, match=r"empty: no images"):
            ImageFolderFrames(empty)


class TestScaling:
    @pytest.mark.parametrize("scale", [0.5, 0.3, 0.25, 0.7])
    def test_feature_pixel_centres(self, scale):
        """Resizing a linear ramp returns the ramp at ``(u' + 0.5) / scale - 0.5``: the
        convention of CameraRig.scaled_images, whatever the (symmetric) filter. The tolerance
        (0.05 of a ramp rising 0.7 and 1.3 per pixel: < 0.07 px) is the filter's sampling at
        fractional scales; the convention ``u'/scale`` would be off by 0.5/scale - 0.5 px."""
        W, H = 203, 157
        u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
        ramp = Image.fromarray(0.7 * u + 1.3 * v + 5.0, mode="F")
        out = np.asarray(resize_image(ramp, scale))
        w, h = scaled_size((W, H), scale)
        assert out.shape == (h, w)
        uu, vv = np.meshgrid((np.arange(w) + 0.5) / scale - 0.5,
                             (np.arange(h) + 0.5) / scale - 0.5)
        inner = (slice(3, -3), slice(3, -3))  # away from the borders, where filters clip
        np.testing.assert_allclose(out[inner], (0.7 * uu + 1.3 * vv + 5.0)[inner], atol=0.05,
                                   rtol=0)

    def test_exception(self):
        for kw, match in [({"start": -1}, r"start: expected an integer frame index in \[0, 10\)"),
                          ({"start": 10}, r"start: .*got 10"),
                          ({"start": 1.0}, r"start: .*got 1\.0"),
                          ({"start": 5, "stop": 5}, r"stop: expected an integer in \(5, 10\]"),
                          ({"stop": 11}, r"stop: .*got 11"),
                          ({"stride": 0}, r"stride: expected an integer >= 1"),
                          ({"stride": True}, r"stride: .*got True"),
                          ({"scale": 0}, r"scale: expected an image scale in \(0, 1\]"),
                          ({"scale": 1.5}, r"scale: .*got 1\.5"),
                          ({"scale": math.nan}, r"scale: .*got nan")]:
            with pytest.raises(ValueError, match=match):
                check_frame_range(10, **kw)
        assert check_frame_range(10, 2, None, 3) == range(2, 10, 3)


class TestNumberedFiles:
    def test_feature(self, tmp_path):
        assert frame_number("cam01.0012.json") == 12
        assert frame_number("run_000000000007_keypoints.json") == 7
        assert frame_number("image0003.png") == 3
        for name in ("cam01.0000.json", "cam01.0001.json", "cam01.0010.json", "x.txt"):
            (tmp_path / name).write_text("{}")
        files = numbered_files(tmp_path, (".json",))
        assert sorted(files) == [0, 1, 10] and files[10].name == "cam01.0010.json"

    def test_exception(self, tmp_path):
        (tmp_path / "a_000001_keypoints.json").write_text("{}")
        (tmp_path / "b.0001.json").write_text("{}")
        with pytest.raises(FrameSourceError, match=r"a_000001_keypoints\.json and b\.0001\.json "
                                                   r"are both frame 1"):
            numbered_files(tmp_path, (".json",))
        with pytest.raises(FrameSourceError, match=r"keypoints\.json: no frame number"):
            frame_number("keypoints.json")
        with pytest.raises(FrameSourceError, match=r"no \.png files"):
            numbered_files(tmp_path, (".png",))
        with pytest.raises(FrameSourceError, match=r"nope: no such folder"):
            numbered_files(tmp_path / "nope", (".png",))


@pytest.mark.parametrize("levels, fg", [
    ((0, 255), 255), ((0, 1), 1), ((0, 2), 2), ((0, 100), 100), ((0,), None), ((7,), 7),
])
def test_read_mask_binary_levels(tmp_path, levels, fg):
    """A mask of at most two grey levels, one of them 0, is binary whatever its foreground."""
    from torchmocap.io.frames import read_mask

    a = np.full((6, 8), levels[0], np.uint8)
    a[2:4, 3:6] = levels[-1]
    Image.fromarray(a).save(tmp_path / "m.png")
    got = read_mask(tmp_path / "m.png", (8, 6))
    assert got.dtype == bool and np.array_equal(got, a == fg if fg is not None else a > 0)


def test_read_mask_grey_levels_and_size(tmp_path):
    """More levels (antialiased edges): foreground above 127; another size is refused."""
    from torchmocap.io.frames import read_mask

    a = np.array([[0, 3, 127, 128, 200, 255]], np.uint8)
    Image.fromarray(a).save(tmp_path / "m.png")
    assert read_mask(tmp_path / "m.png").tolist() == [[False] * 3 + [True] * 3]
    with pytest.raises(FrameSourceError, match=r"m\.png: mask is 6x1, the camera's frames are "
                                               r"6x2"):
        read_mask(tmp_path / "m.png", (6, 2))
