"""Animations: the frame count and the frames read back (GIF with Pillow, MP4 decoded by
ffmpeg), the GIF fallback without ffmpeg and its message, decimation, typed errors, and no
half-written file when the frames fail midway."""

from __future__ import annotations

import logging
import subprocess

import numpy as np
import pytest
from PIL import Image, ImageSequence

from torchmocap.viz import video
from torchmocap.viz.video import decimation, ffmpeg_executable, write_gif, write_mp4, write_video

H, W = 30, 41  # odd width: the MP4 pads to even sizes


def _frames(n=7):
    out = []
    for k in range(n):
        f = np.zeros((H, W, 3), np.uint8)
        f[..., 0] = 20 * k + 10          # frame k is recognisable by its red level
        f[:, : 4 + 4 * k, 1] = 255        # and by the width of a green band
        out.append(f)
    return out


def _decode_mp4(path):
    exe = ffmpeg_executable()
    raw = subprocess.run([exe, "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt",
                          "rgb24", "-"], capture_output=True, check=True).stdout
    return raw


@pytest.fixture
def ffmpeg():
    exe = ffmpeg_executable()
    if exe is None:  # the dev extra installs imageio-ffmpeg, which bundles one
        pytest.skip("no ffmpeg executable (pip install imageio-ffmpeg)")
    return exe


class TestDecimation:
    def test_feature(self):
        assert decimation(25, None) == 1 and decimation(25, 25) == 1
        assert decimation(50, 25) == 2 and decimation(60, 25) == 3 and decimation(10, 25) == 1
        for fps, mx in [(25, 25), (60, 25), (120, 7.5), (30, 12.5)]:
            k = decimation(fps, mx)
            assert fps / k <= mx + 1e-9 and (k == 1 or fps / (k - 1) > mx)

    def test_exception(self):
        with pytest.raises(ValueError, match="fps"):
            decimation(0, 25)
        with pytest.raises(ValueError, match="max_fps"):
            decimation(25, -1)


class TestGif:
    def test_cardinality_and_frames(self, tmp_path):
        frames = _frames()
        path = write_gif(tmp_path / "a.gif", frames, fps=10)
        im = Image.open(path)
        assert im.n_frames == 7 and im.size == (W, H)
        for k, f in enumerate(ImageSequence.Iterator(im)):
            a = np.asarray(f.convert("RGB")).astype(int)
            np.testing.assert_allclose(a, frames[k], atol=12)
            assert f.info["duration"] == 100
        assert [p.name for p in tmp_path.iterdir()] == ["a.gif"]

    def test_exception(self, tmp_path):
        with pytest.raises(ValueError, match="frames"):
            write_gif(tmp_path / "a.gif", [], fps=10)
        with pytest.raises(ValueError, match="frames"):
            write_gif(tmp_path / "a.gif", [np.zeros((4, 4, 3), np.uint8),
                                           np.zeros((5, 4, 3), np.uint8)], fps=10)
        with pytest.raises(ValueError, match="frames"):
            write_gif(tmp_path / "a.gif", [np.zeros((4, 4, 3))], fps=10)
        with pytest.raises(ValueError, match="fps"):
            write_gif(tmp_path / "a.gif", _frames(2), fps=0)
        assert list(tmp_path.iterdir()) == []


class TestMp4:
    def test_cardinality_and_frames(self, tmp_path, ffmpeg):
        frames = _frames()
        path = write_mp4(tmp_path / "a.mp4", frames, fps=10)
        raw = _decode_mp4(path)
        size = H * (W + 1) * 3  # padded to an even width
        assert len(raw) == 7 * size
        decoded = np.frombuffer(raw, np.uint8).reshape(7, H, W + 1, 3)
        for k in range(7):  # lossy: compare the red level and the green band's width
            assert abs(decoded[k, H // 2, -6, 0].astype(int) - (20 * k + 10)) <= 12
            assert (decoded[k, H // 2, : 4 * k + 2, 1] > 180).all()
            assert (decoded[k, H // 2, 4 * k + 7:W - 1, 1] < 80).all()
        assert [p.name for p in tmp_path.iterdir()] == ["a.mp4"]

    def test_exception(self, tmp_path, monkeypatch):
        monkeypatch.setattr(video, "ffmpeg_executable", lambda: None)
        with pytest.raises(FileNotFoundError, match="ffmpeg"):
            write_mp4(tmp_path / "a.mp4", _frames(2), fps=10)


class TestWriteVideo:
    def test_mp4(self, tmp_path, ffmpeg):
        path = write_video(tmp_path / "overlays", _frames(5), fps=25, format="mp4")
        assert path.name == "overlays.mp4" and len(_decode_mp4(path)) == 5 * H * (W + 1) * 3

    def test_gif_fallback_says_so(self, tmp_path, monkeypatch, caplog):
        monkeypatch.setattr(video, "ffmpeg_executable", lambda: None)
        with caplog.at_level(logging.WARNING, logger="torchmocap.viz.video"):
            path = write_video(tmp_path / "overlays.mp4", _frames(5), fps=25, format="mp4")
        assert path.name == "overlays.gif" and Image.open(path).n_frames == 5
        assert "GIF instead of an MP4" in caplog.text and "imageio-ffmpeg" in caplog.text

    def test_exception(self, tmp_path):
        with pytest.raises(ValueError, match="format"):
            write_video(tmp_path / "v", _frames(2), fps=25, format="avi")

    @pytest.mark.parametrize("fmt", ["gif", "mp4"])
    def test_atomic_when_the_frames_fail(self, tmp_path, fmt):
        if fmt == "mp4" and ffmpeg_executable() is None:
            pytest.skip("no ffmpeg executable")
        (tmp_path / f"v.{fmt}").write_bytes(b"old")

        def broken():
            yield from _frames(3)
            raise RuntimeError("renderer failed")

        with pytest.raises(RuntimeError, match="renderer failed"):
            write_video(tmp_path / "v", broken(), fps=25, format=fmt)
        assert [p.name for p in tmp_path.iterdir()] == [f"v.{fmt}"]
        assert (tmp_path / f"v.{fmt}").read_bytes() == b"old"
