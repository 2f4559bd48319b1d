"""torchmocap-track's outputs people look at: the overlay grids (every view, estimate and truth,
legend), the video of the whole track (frame count read back, decimated to video.max_fps),
the animated GLB of the skinned body following the estimate; all written atomically; bad output
settings fail before the track."""

from __future__ import annotations

import math
import subprocess

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from PIL import Image

from torchmocap.cli.outputs import validate_outputs
from torchmocap.cli.track import run
from torchmocap.viz.overlays import ESTIMATE_COLOR, TITLE_HEIGHT, TRUTH_COLOR
from torchmocap.viz.video import ffmpeg_executable

W, H = 80, 60


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


def _has(a, color):
    return bool((a.reshape(-1, 3) == np.array(color)).all(-1).any())


def test_defaults_keep_the_run_cheap():
    cfg = _compose([])
    assert cfg.overlays == 3 and cfg.video.enabled is False and cfg.glb.enabled is True
    assert cfg.video.format == "mp4" and cfg.glb.body == "auto" and cfg.glb.up == "y"


@pytest.mark.parametrize("fmt", ["mp4", "gif"])
def test_overlays_video_and_glb(tmp_path, fmt):
    if fmt == "mp4" and ffmpeg_executable() is None:
        pytest.skip("no ffmpeg executable (pip install imageio-ffmpeg)")
    T = 5
    cfg = _compose([f"data.clip.frames={T}", "tracker=gs", f"sequence_cache={tmp_path / 'c'}",
                    "tracker.num_particles=20", "tracker.inference.layers=2",
                    f"+data.scenario_overrides.image_size=[{W},{H}]",
                    "progress=false", "overlays=2", "video.enabled=true",
                    f"video.format={fmt}", "video.max_fps=12.5", "video.scale=1.0",
                    "glb.enabled=true"])
    m = run(cfg, tmp_path)
    assert m["frames"] == T
    # overlay grids: the 2x2 grid of the four studio views, both skeletons, the legend
    grids = sorted(tmp_path.glob("overlay_*.png"))
    assert [p.name for p in grids] == ["overlay_0001.png", "overlay_0004.png"]
    widths = set()
    for p in grids:
        a = np.asarray(Image.open(p).convert("RGB"))
        # 2 x 2 panels (wider when the title and the legend need it, black on the right)
        assert a.shape[0] == TITLE_HEIGHT + 2 * H and a.shape[1] >= 2 * W
        widths.add(a.shape[1])
        assert _has(a[:TITLE_HEIGHT], ESTIMATE_COLOR) and _has(a[:TITLE_HEIGHT], TRUTH_COLOR)
        for r in range(2):
            for c in range(2):  # every panel shows the estimate
                panel = a[TITLE_HEIGHT + r * H:TITLE_HEIGHT + (r + 1) * H, c * W:(c + 1) * W]
                assert _has(panel, ESTIMATE_COLOR), (p.name, r, c)
    assert len(widths) == 1
    # the video: every second frame (25 fps -> at most 12.5 fps): frames 0, 2, 4
    n = math.ceil(T / 2)
    video = tmp_path / f"overlays.{fmt}"
    if fmt == "gif":
        im = Image.open(video)
        assert im.n_frames == n and im.size[1] == TITLE_HEIGHT + 2 * H
        assert im.info["duration"] == 80  # 12.5 fps
    else:
        md5 = subprocess.run([ffmpeg_executable(), "-v", "error", "-i", str(video), "-f",
                              "framemd5", "-"], capture_output=True, text=True,
                             check=True).stdout
        assert len([ln for ln in md5.splitlines() if ln and not ln.startswith("#")]) == n
    # the GLB: the skinned body, keyframes at the frame times, the root at the estimate's
    import torch

    from torchmocap.assembly import Runtime, load_sequence
    from torchmocap.export import read_accessor, read_glb

    doc, blob = read_glb(tmp_path / "track.glb")
    assert doc["meshes"][0]["name"] == "body"
    anim = doc["animations"][0]
    times = read_accessor(doc, blob, anim["samplers"][0]["input"])
    np.testing.assert_allclose(times, np.arange(T) / 25.0, rtol=1e-6)
    (ch,) = [c for c in anim["channels"] if c["target"]["path"] == "translation"]
    root = read_accessor(doc, blob, anim["samplers"][ch["sampler"]]["output"])
    sk = Runtime.from_sequence(load_sequence(cfg)).skeleton  # the subject (from the cache)
    assert doc["nodes"][ch["target"]["node"]]["name"] == sk.joint_names[sk.parents.index(-1)]
    theta = torch.as_tensor(np.load(tmp_path / "track.npz")["theta"], dtype=torch.float64)
    with torch.no_grad():
        expect = sk.double()(theta).positions[:, sk.parents.index(-1)].numpy()
    np.testing.assert_allclose(root, expect, atol=1e-5)
    # nothing half-written is left: no temporary files
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("override,key", [
    ("video.format=avi", "video.format"), ("video.max_fps=0", "video.max_fps"),
    ("video.scale=-1", "video.scale"), ("glb.body=robot", "glb.body"), ("glb.up=x", "glb.up"),
    ("overlays=-1", "overlays"), ("overlay_scale=0", "overlay_scale")])
def test_bad_output_settings_fail_before_the_track(tmp_path, override, key):
    cfg = _compose([override])
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        validate_outputs(cfg)
    # run(): before any data is read (the clip does not even exist)
    cfg = _compose([override, "data.clip.path=/nonexistent.bvh", "progress=false"])
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        run(cfg, tmp_path)
    assert not (tmp_path / "metrics.json").exists()
