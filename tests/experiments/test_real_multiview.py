"""experiments/real_multiview: the triangulation peers on the trimmed pose2sim recording (with
and without aniposelib), Pose2Sim's view dropping on closed cases, and the report on a fake
torchmocap run directory."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch

REC = ("multiview", "pose2sim_balancing")
# reading a video's frame rate runs ffprobe; once aniposelib's tests have started jax's threads
# in this process, Python warns about the fork (the child execs at once)
pytestmark = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")


@pytest.fixture(scope="module")
def peers(load_script):
    return load_script("real_multiview/peers.py")


@pytest.fixture(scope="module")
def report(load_script):
    return load_script("real_multiview/report.py")


@pytest.fixture(scope="module")
def recording(shared_data):
    return shared_data.joinpath(*REC)


@pytest.fixture(scope="module")
def det(peers, recording):
    return peers.load_detections(recording)


@pytest.fixture(scope="module")
def no_anipose_result(peers, recording):
    """``run_all`` on the trimmed recording with aniposelib's import failing."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(sys.modules, "aniposelib", None)
        mp.setitem(sys.modules, "aniposelib.cameras", None)
        messages = []
        result = peers.run_all(recording, log=messages.append)
    return result, messages


def test_detections_and_rig_of_the_recording(det):
    assert det.points.shape == (10, 4, 25, 3) and det.points.dtype == torch.float64
    assert det.cameras == ["cam01", "cam02", "cam03", "cam04"]
    assert det.rig.names == ["cam_01", "cam_02", "cam_03", "cam_04"] and det.fps == 60.0
    assert det.camera_index("cam_03") == 2 and det.camera_index(1) == 1
    with pytest.raises(ValueError, match="unknown camera 'cam07'"):
        det.camera_index("cam07")


def test_peers_without_aniposelib_skip_its_rows_and_score_the_others(no_anipose_result):
    result, messages = no_anipose_result
    skipped = {"anipose_dlt", "anipose_ransac", "anipose_optim"}
    assert set(result["skipped"]) == skipped
    assert all("aniposelib is not installed" in v for v in result["skipped"].values())
    assert sum("aniposelib is not installed" in m for m in messages) == 3
    assert set(result["methods"]) == {"dlt", "dlt_drop", "pose2sim_raw"}
    json.dumps(result, allow_nan=False)  # what peers.json holds
    for key in ("dlt", "dlt_drop"):
        m = result["methods"][key]
        assert not m["saw_heldout"] and list(m["rows"]) == result["cameras"]
        for row in m["rows"].values():
            # the real rig and detections: tens of pixels on 1920-pixel-high images (a wrong
            # camera, axis or frame gives hundreds), nearly every keypoint within 10 % of the
            # subject's height
            assert row["median_px"] < 40 and row["pck_10"] > 0.9
            assert row["seconds_per_frame"] > 0 and len(row["frame_median_px"]) == 10
            assert 0 < row["bone_cv_mean"] < 15 and 0 < row["jitter"]


def test_pose2sim_output_saw_the_heldout_view_and_is_marked_so(no_anipose_result, peers,
                                                               recording, det):
    result, _ = no_anipose_result
    trc, dlt = result["methods"]["pose2sim_raw"], result["methods"]["dlt"]
    assert trc["saw_heldout"] and "saw the held-out" in trc["label"]
    # triangulated with the held-out view, it agrees with that view better than C-1 views do
    for cam in result["cameras"]:
        assert trc["rows"][cam]["median_px"] < dlt["rows"][cam]["median_px"]
    # TRC frame 1 is the detections' frame 0: the keypoints of the 4-view DLT lie within a
    # few cm of Pose2Sim's, on the same frames
    from torchmocap.cameras import triangulate_dlt

    X = peers.trc_keypoints(peers.trc_files(recording)[0], det)
    Y = triangulate_dlt(det.points[..., :2], peers._used(det.points[..., 2]), det.rig)
    d = (X - Y).norm(dim=-1)
    assert float(d.nanmedian()) < 0.05
    assert bool(torch.isnan(X[:, [1, 2, 3, 4]]).all())  # no eyes and ears in the TRC


def _ring(n=4):
    from torchmocap.cameras import make_ring_rig

    return make_ring_rig(n).double()


def test_view_dropping_removes_an_outlier_view_and_refuses_hopeless_points(peers):
    rig = _ring()
    X = torch.tensor([[[0.1, -0.2, 1.0], [0.0, 0.3, 1.5], [0.2, 0.1, 0.8]]],
                     dtype=torch.float64)  # (T=1, K=3, 3)
    pix = rig.project(X)[0]  # (1, 4, 3, 2)
    conf = torch.full((1, 4, 3), 0.9, dtype=torch.float64)
    pix[0, 2, 1] += torch.tensor([120.0, -80.0])  # keypoint 1: one view far off
    # keypoint 2: seen by two views only, 60 px up in one and down in the other (across the
    # epipolar lines of cameras at one height: no point reprojects near both)
    conf[0, 2:, 2] = 0.0
    pix[0, 0, 2, 1] += 60.0
    pix[0, 1, 2, 1] -= 60.0
    plain = peers.dlt(pix, conf, rig)
    pair = rig.subset([0, 1]).project(plain[0, 2:])[0][:, 0]  # (2, 2)
    assert float((pair - pix[0, :2, 2]).norm(dim=-1).mean()) > 30
    drop = peers.dlt_view_dropping(pix, conf, rig)
    assert float((plain[0, 1] - X[0, 1]).norm()) > 0.02  # the outlier pulls the plain DLT
    torch.testing.assert_close(drop[0, :2], X[0, :2], atol=1e-6, rtol=0)  # dropped: exact
    torch.testing.assert_close(drop[0, 0], plain[0, 0])  # nothing to drop: the plain DLT
    assert bool(torch.isnan(drop[0, 2]).all())  # the only pair > 15 px: left out
    # a view under the input confidence is not used at all
    low = conf.clone()
    low[0, 2, 1] = 0.2
    torch.testing.assert_close(peers.dlt(pix, low, rig)[0, 1], X[0, 1], atol=1e-6, rtol=0)


def test_anipose_camera_group_matches_the_rig_conventions(peers, det):
    pytest.importorskip("aniposelib")
    g = peers.camera_group(det.rig)
    X = torch.tensor([[0.3, 0.2, 1.1], [-0.4, 0.5, 0.2], [0.0, 0.0, 1.8]], dtype=torch.float64)
    ours = det.rig.project(X)[0].numpy()  # (C, N, 2), distortion included
    np.testing.assert_allclose(g.project(X.numpy()), ours, atol=1e-6)
    assert [c.get_size() for c in g.cameras] == det.rig.image_size.tolist()


def _three_views(det, frames=slice(None)):
    views = [0, 1, 3]
    sub = det.points[frames, views]
    return sub[..., :2], sub[..., 2], det.rig.subset(views)


def test_anipose_dlt_is_the_unweighted_dlt_of_the_same_rays(peers, det):
    pytest.importorskip("aniposelib")
    from torchmocap.cameras import triangulate_dlt

    pix, conf, rig = _three_views(det)
    a = peers.anipose_dlt(pix, conf, rig)
    ones = (peers._used(conf) > 0).double()
    assert bool(torch.isfinite(a).any())
    torch.testing.assert_close(a, triangulate_dlt(pix, ones, rig), atol=1e-6, rtol=0,
                               equal_nan=True)


@pytest.mark.slow  # aniposelib compiles its jax and numba functions on first use (~10 s)
def test_anipose_ransac_and_optim_on_the_recording(peers, det):
    """RANSAC reconstructs what two views see; the optimiser's limb-length constraints make
    the bones more constant than the DLT's, and it still lands on the held-out detections."""
    pytest.importorskip("aniposelib")
    from torchmocap.evaluation import bone_length_cv

    pix, conf, rig = _three_views(det, slice(0, 4))
    a = peers.anipose_dlt(pix, conf, rig)
    r = peers.anipose_ransac(pix, conf, rig)
    assert bool((torch.isfinite(r).all(-1) == torch.isfinite(a).all(-1)).all())
    o = peers.anipose_optim(pix, conf, rig)
    cv = [bone_length_cv(x, peers.CV_BONES, peers.KEYPOINTS).mean_percent for x in (o, a)]
    assert cv[0] < 0.5 * cv[1]
    four = peers.Detections(det.points[:4], det.rig, det.cameras, det.frames[:4], det.fps,
                            det.path)
    assert peers.heldout_scores(o, four, 2).median_px < 40


@pytest.mark.slow
def test_peers_with_aniposelib_write_every_row(peers, recording, tmp_path):
    pytest.importorskip("aniposelib")
    out = tmp_path / "peers.json"
    assert peers.main(["--recording", str(recording), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert not result["skipped"]
    assert {"anipose_dlt", "anipose_ransac", "anipose_optim"} <= set(result["methods"])
    assert result["load_before"]["aniposelib"]


# ----------------------------------------------------------------------------- report
@pytest.fixture(scope="module")
def fitted(det):
    """The subject fitted to the 4-view DLT of the detections: a track whose keypoints land
    on the detections."""
    from torchmocap.cameras import triangulate_dlt
    from torchmocap.ik import fit_keypoint_subject

    X = triangulate_dlt(det.points[..., :2], det.points[..., 2], det.rig)
    return fit_keypoint_subject(X, None, "body_25b", headings=4)


def _fake_run(run, fit=None, camera="cam02", recording="pose2sim_balancing", heldout=True):
    """A torchmocap run directory as torchmocap-track writes it (the track of ``fit``; without
    it only metrics.json and the config)."""
    import yaml

    from torchmocap.io import MotionClip, write_bvh

    run.mkdir(parents=True)
    if fit is not None:
        np.savez_compressed(run / "track.npz", theta=fit.theta.numpy())
        write_bvh(run / "tracked.bvh", MotionClip.from_skeleton(fit.skeleton, fit.theta,
                                                                fps=60.0))
    metrics = {"tracker": "real_fake", "seed": 0, "seconds_per_frame": 1.25}
    if heldout:
        metrics["heldout"] = {"median_px": 7.0, "mean_px": 9.0, "pck_05": 0.5, "pck_10": 0.8,
                              "pixels": "full-size images"}
        metrics["consistency"] = {"bone_length_cv_percent": {"mean": 0.25},
                                  "jitter_m_s2": {"mean": 3.0}}
    (run / "metrics.json").write_text(json.dumps(metrics))
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({
        "data": {"path": f"/somewhere/{recording}", "start": 0, "stride": 1},
        "evaluation": {"heldout_camera": camera}}))


def test_report_reads_a_torchmocap_run_and_names_what_is_missing(report, no_anipose_result,
                                                                 recording, fitted, tmp_path):
    result, _ = no_anipose_result
    peers_json = tmp_path / "peers.json"
    peers_json.write_text(json.dumps(result))
    runs = tmp_path / "runs"
    _fake_run(runs / "cam02", fitted)
    _fake_run(runs / "other", recording="another_recording")
    (runs / "failed").mkdir()
    (runs / "failed" / "failure.json").write_text("{}")
    out = tmp_path / "out"
    assert report.main(["--peers", str(peers_json), "--runs", str(runs), "--recording",
                        str(recording), "--out", str(out)]) == 0
    md = (out / "table.md").read_text()
    row = next(line for line in md.splitlines()
               if line.startswith("| torchmocap `real_fake` (seed 0) | cam02 |"))
    cells = [c.strip() for c in row.split("|")[3:-1]]
    median, pck_10, cv, spf = float(cells[0]), float(cells[3]), float(cells[5]), cells[7]
    # scored by the protocol from the track, not copied from metrics.json (7 px there): the
    # fitted skeleton's keypoints land on the detections within tens of pixels, and a rigid
    # skeleton's bones barely change length
    assert 5 < median < 40 and pck_10 > 80 and cv < 1.0 and spf == "1.2500"
    assert "missing** held-out camera(s) cam01, cam03, cam04" in md
    assert "tracked /somewhere/another_recording" in md
    assert f"failed run (failure.json): `{runs / 'failed'}`" in md
    assert "| torchmocap `real_fake` (seed 0) | cam02 | full-size images | 7.0 | 9.0 | 50.0 | " \
        "80.0 | 0.25 | 3.0 |" in md
    assert "† context only" in md and "aniposelib is not installed" in md
    for png in ("heldout_error.png", "bone_cv.png"):
        assert (out / png).stat().st_size > 10_000


def test_report_names_a_smoothed_run_apart(report):
    assert report._tracker_label("real_mixture", {}) == "real_mixture"
    cfg = {"tracker": {"smoother": {"_target_": "torchmocap.filters.KalmanSmoother"}}}
    assert report._tracker_label("real_mixture", cfg) == "real_mixture + KalmanSmoother"
    assert report._tracker_label("p", {"tracker": {"smoother": None}}) == "p"


def test_report_without_runs_says_the_torchmocap_rows_are_missing(report, no_anipose_result,
                                                                  tmp_path):
    result, _ = no_anipose_result
    peers_json = tmp_path / "peers.json"
    peers_json.write_text(json.dumps(result))
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "out"
    assert report.main(["--peers", str(peers_json), "--runs", str(empty), "--out",
                        str(out)]) == 0
    md = (out / "table.md").read_text()
    assert "**missing**: no torchmocap runs were given" in md
    assert "| weighted DLT (Pose2Sim's triangulation) | cam04 |" in md
    assert report.main(["--peers", str(tmp_path / "none.json"), "--out", str(out)]) == 2


def test_a_run_without_heldout_scores_or_track_is_refused_by_name(report, det, tmp_path):
    _fake_run(tmp_path / "run", heldout=False)
    with pytest.raises(report.RunError, match=r"metrics.json: expected 'heldout' with"):
        report.read_run(tmp_path / "run", det)
    _fake_run(tmp_path / "untracked")
    with pytest.raises(report.RunError, match=r"untracked: no track.npz"):
        report.read_run(tmp_path / "untracked", det)
