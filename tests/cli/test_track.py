"""torchmocap-track: in-process and console runs, up-to-date skipping, sweeps that survive a
failing job (basic and joblib launchers), errors, and the real frame through the components."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cli.track import run

EXE = str(Path(sys.executable).parent / "torchmocap-track")
SMALL = ["tracker=p", "data.clip.frames=4", "tracker.num_particles=20",
         "tracker.inference.layers=2",
         "+data.scenario_overrides.image_size=[80,60]", "overlays=0", "progress=false"]


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


def _console(args, tmp_path, timeout=600, **env):
    e = dict(os.environ, OMP_NUM_THREADS="1", **env)
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=timeout, env=e,
                          cwd=tmp_path)


def test_defaults():
    cfg = _compose([])
    # the default tracker is LS (local descent; experiments/ponsmoll2010 says why)
    assert cfg.tracker.name == "default" and cfg.tracker.num_particles == 1
    assert cfg.tracker.inference._target_ == "torchmocap.filters.LocalInference"
    assert cfg.tracker.inference.iterations == 40 and cfg.data.scenario == "studio"
    assert cfg.data.clip.path is None and cfg.seed == 0
    assert "file://conf" in cfg.hydra.searchpath if "hydra" in cfg else True


def test_every_clip_setting_is_in_the_default_config():
    """A documented ``data.clip`` key the config lacks cannot be set without ``+``."""
    from torchmocap.data.synthetic.clips import CLIP_KEYS

    assert set(_compose([]).data.clip) == CLIP_KEYS
    assert _compose(["data.clip.in_place=true"]).data.clip.in_place is True


def test_in_process_run_writes_outputs_and_skips_when_up_to_date(tmp_path):
    cfg = _compose(["tracker=p", "data.clip.frames=6", "tracker.num_particles=30",
                    "tracker.inference.layers=3", "progress=false", "overlays=2",
                    "data.scenario=clean"])
    m = run(cfg, tmp_path)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved == json.loads(json.dumps(m))
    for key in ("frames", "seconds_per_frame", "orientation_error_deg", "mpjpe_mm",
                "fingerprint", "ess_final_mean", "energy_mean"):
        assert key in saved
    assert saved["frames"] == 6 and saved["tracker"] == "p" and saved["layers"] == 3
    assert set(saved["orientation_error_deg"]["per_bone"]) == {
        "spine", "l_shoulder", "r_shoulder", "l_hip", "r_hip"}
    assert 0 <= saved["orientation_error_deg"]["mean"] < 45
    assert (tmp_path / "track.npz").is_file() and (tmp_path / "errors.png").is_file()
    assert len(list(tmp_path.glob("overlay_*.png"))) == 2
    assert oct((tmp_path / "metrics.json").stat().st_mode & 0o777) == "0o644"
    from torchmocap.io import load_motion

    assert load_motion(tmp_path / "tracked.bvh").num_frames == 6
    # the same job again: up to date, nothing recomputed
    mtime = (tmp_path / "track.npz").stat().st_mtime_ns
    assert run(cfg, tmp_path) == saved
    assert (tmp_path / "track.npz").stat().st_mtime_ns == mtime
    # a changed setting reruns it (and changes the fingerprint)
    cfg2 = _compose(["tracker=p", "data.clip.frames=6", "tracker.num_particles=31",
                     "tracker.inference.layers=3", "progress=false", "overlays=0",
                     "data.scenario=clean"])
    m2 = run(cfg2, tmp_path)
    assert m2["num_particles"] == 31 and m2["fingerprint"] != saved["fingerprint"]


def test_run_reports_the_do_nothing_baseline_and_beats_it(tmp_path):
    """``hold_first_pose``: the errors of keeping the first frame's pose (every tracker's start),
    recomputed here from the saved truth; the tracker is below it on a moving clip."""
    import numpy as np
    import torch

    from torchmocap.metrics import orientation_error_deg
    from torchmocap.skeleton import human31

    cfg = _compose(["tracker=p", "data.clip.frames=10", "data.clip.fps=8",
                    "tracker.num_particles=40",
                    "tracker.inference.layers=4", "progress=false", "overlays=0",
                    "data.scenario=clean"])
    m = run(cfg, tmp_path)
    held = m["hold_first_pose"]
    z = np.load(tmp_path / "track.npz")
    from torchmocap.assembly import load_sequence

    sk = human31()  # bone rotations do not depend on the subject's bone lengths
    vb = [sk.joint_index(b) for b in m["validation_bones"]]
    gt = load_sequence(cfg, min_frames=2).ground_truth.rotations[1:, vb].float()
    still = sk(torch.as_tensor(z["theta"][:1], dtype=torch.float32)).rotations[:, vb]
    expected = float(orientation_error_deg(still.expand_as(gt), gt).mean())
    assert held["orientation_error_deg"] == pytest.approx(expected, rel=1e-4)
    assert held["mpjpe_mm"] > 40 and held["orientation_error_deg"] > 5  # the walk moves
    assert m["mpjpe_mm"]["mean"] < 0.6 * held["mpjpe_mm"]
    assert m["orientation_error_deg"]["mean"] < held["orientation_error_deg"]
    assert "held_dofs" not in m  # every DoF tracked
    # root-aligned MPJPE, recomputed from the saved estimate and the truth's joint positions
    seq = load_sequence(cfg, min_frames=2)
    sk_fit = seq.ground_truth.build_skeleton()
    pos = sk_fit(torch.as_tensor(z["theta"], dtype=torch.float64)).positions[1:]
    truth = seq.ground_truth.positions[1:].double()
    rel = ((pos - pos[:, :1]) - (truth - truth[:, :1])).norm(dim=-1).mean(-1) * 1000
    r = m["mpjpe_root_relative_mm"]
    assert r["mean"] == pytest.approx(float(rel.mean()), rel=1e-3)
    assert len(r["per_frame"]) == len(m["mpjpe_mm"]["per_frame"]) == 9
    assert held["mpjpe_root_relative_mm"] < held["mpjpe_mm"]  # the walk carries the root away


def test_upper_body_tracker_on_a_walk_warns_that_the_held_torso_moves(tmp_path, capsys):
    """An upper-body preset holds the torso and legs at the first frame: on a walk the truth
    carries the root away, and the run says so instead of reporting the errors silently."""
    import numpy as np

    cfg = _compose(["tracker=hauberg_angular", "data.clip.frames=8", "data.clip.fps=6",
                    "tracker.num_particles=16", "progress=false", "overlays=0",
                    "glb.enabled=false"])
    m = run(cfg, tmp_path)
    z = np.load(tmp_path / "track.npz")
    still = np.isclose(z["theta"], z["theta"][:1], rtol=1e-5, atol=1e-6).all(0)
    gt = z["theta_gt"]
    assert m["held_dofs"]["count"] == int(still.sum()) > 0
    moved = np.linalg.norm(gt[:, :3] - gt[:1, :3], axis=-1).max()
    assert still[:3].all() and m["held_dofs"]["truth_max_translation_m"] == pytest.approx(
        moved, rel=1e-4) and moved > 0.5
    err = capsys.readouterr().err
    assert "warning: the tracker held" in err and "the root moves" in err


def test_smoothed_run_reports_the_filtered_errors_beside(tmp_path):
    import numpy as np
    import torch

    from torchmocap.assembly import load_sequence

    cfg = _compose(["tracker=kjs", "+smoother@tracker.smoother=viterbi", "data.clip.frames=5",
                    "tracker.num_particles=24", "tracker.inference.components=3",
                    "progress=false", "overlays=0", "glb.enabled=false"])
    m = run(cfg, tmp_path)
    assert m["smoother"]["name"] == "viterbi" and 0 <= m["smoother"]["changed_frames"] <= 4
    assert set(m["filtered"]) == {"orientation_error_deg", "mpjpe_mm", "mpjpe_root_relative_mm",
                                  "marker_error_mm"}
    hyp = m["hypotheses"]
    assert all(hyp["mpjpe_root_relative_best_mm"]["mean"] <= hyp[k]["mean"] + 1e-9
               for k in ("mpjpe_root_relative_top_mm",))
    z = np.load(tmp_path / "track.npz")
    assert z["theta_filtered"].shape == z["theta"].shape == (5, 31)
    if m["smoother"]["changed_frames"] == 0:
        assert m["filtered"]["mpjpe_mm"] == pytest.approx(m["mpjpe_mm"]["mean"])
    # every frame's kept modes are saved: the smoothed pose is one of them, the filtered one is
    # the top-weighted one, and the saved modes reproduce the best-hypothesis error reported
    H, w, e = z["hypotheses"], z["hypothesis_weights"], z["hypothesis_energy"]
    K = H.shape[1]
    assert H.shape == (5, K, 31) and w.shape == e.shape == (5, K) and 1 <= K <= 3
    assert np.isnan(H[0]).all() and np.isnan(w[0]).all()
    seq = load_sequence(cfg, min_frames=2)
    sk_fit = seq.ground_truth.build_skeleton()
    best = []
    for t in range(1, 5):
        ok = ~np.isnan(w[t])
        assert ok.sum() == m["hypotheses"]["modes"]["per_frame"][t - 1]
        assert np.isfinite(e[t, ok]).all() and np.isnan(H[t, ~ok]).all()
        assert np.abs(H[t, ok] - z["theta"][t]).max(1).min() < 1e-6
        assert np.abs(H[t, np.nanargmax(w[t])] - z["theta_filtered"][t]).max() < 1e-6
        pos = sk_fit(torch.as_tensor(H[t, ok], dtype=torch.float64)).positions
        best.append(float((pos - seq.ground_truth.positions[t].double()).norm(dim=-1)
                          .mean(-1).min()) * 1000)
    assert np.mean(best) == pytest.approx(hyp["mpjpe_best_mm"]["mean"], rel=1e-3)


def test_chained_smoothers_report_the_errors_after_each_stage(tmp_path):
    """viterbi_kalman: metrics.json's errors are the last stage's, each stage reports its own
    (the Viterbi stage's equal a Viterbi-only run's), no per-frame tensors reach the JSON."""
    common = ["tracker=kjs", "data.clip.frames=5", "tracker.num_particles=24",
              "tracker.inference.components=3", "progress=false", "overlays=0",
              "glb.enabled=false"]
    (tmp_path / "vk").mkdir()
    (tmp_path / "v").mkdir()
    m = run(_compose([*common, "+smoother@tracker.smoother=viterbi_kalman"]), tmp_path / "vk")
    v = run(_compose([*common, "+smoother@tracker.smoother=viterbi"]), tmp_path / "v")
    sm = m["smoother"]
    assert sm["name"] == "viterbi+kalman"
    vit, kal = sm["stages"]
    assert vit["name"] == "viterbi" and kal["name"] == "kalman" and "dofs" in kal
    assert "modes" not in vit and "theta" not in vit and "theta" not in kal
    assert m["filtered"] == v["filtered"]  # the same filter
    for key in ("orientation_error_deg", "mpjpe_mm", "mpjpe_root_relative_mm"):
        assert vit["errors"][key] == pytest.approx(v[key]["mean"], rel=1e-6)
        assert kal["errors"][key] == m[key]["mean"]  # the last stage is the smoothed track
    assert kal["changed_frames"] > 0 and vit["errors"] != kal["errors"]  # the stage acted
    json.dumps(m)  # plain JSON


def test_kalman_smoothed_run_reports_both_and_saves_the_filtered_track(tmp_path, capsys):
    """Any tracker with the Kalman smoother: metrics.json's errors are the smoothed track's
    (recomputed here from track.npz), "filtered" the tracker's own, and the fitted noise."""
    import numpy as np

    cfg = _compose(["tracker=p", "+smoother@tracker.smoother=kalman", "data.clip.frames=6",
                    "tracker.num_particles=24", "tracker.inference.layers=2",
                    "progress=false", "overlays=0", "glb.enabled=false"])
    m = run(cfg, tmp_path)
    z = np.load(tmp_path / "track.npz")
    assert z["theta_filtered"].shape == z["theta"].shape == (6, 31)
    from torchmocap.cli.outputs import print_summary
    print_summary(m)
    out = capsys.readouterr().out
    f = m["filtered"]
    import re
    assert re.search(rf"filtered \(before kalman\) +{f['orientation_error_deg']:.2f} deg, "
                     rf"{f['mpjpe_mm']:.1f} mm", out), out
    assert np.array_equal(z["theta"][0], z["theta_filtered"][0])
    assert not np.array_equal(z["theta"], z["theta_filtered"])
    assert np.mean(z["mpjpe_mm"]) == pytest.approx(m["mpjpe_mm"]["mean"], rel=1e-5)
    sm = m["smoother"]
    assert sm["name"] == "kalman" and sm["changed_frames"] == 5
    assert sm["measurement_std_deg_median"] > 0 and len(sm["dofs"]) == 31
    # the same errors of the tracker's own estimates, the skin-marker error (eq. 16) included
    assert set(m["filtered"]) == {"orientation_error_deg", "mpjpe_mm", "mpjpe_root_relative_mm",
                                  "marker_error_mm"}
    assert m["filtered"]["mpjpe_mm"] != m["mpjpe_mm"]["mean"]
    assert m["filtered"]["marker_error_mm"] != m["marker_error_mm"]["mean"]


def test_energy_vs_truth_diagnostic(tmp_path):
    cfg = _compose([*SMALL, "diagnostics.energy_vs_truth=true", "tracker=g"])
    m = run(cfg, tmp_path)
    assert 0.0 <= m["estimate_energy_below_truth"] <= 1.0


def test_console_unreadable_clip_fails_cleanly(tmp_path):
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")
    r = _console([f"data.clip.path={bad}", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "torchmocap-track: error" in lines[0] and "bad.bvh" in lines[0]
    assert not (tmp_path / "run" / "metrics.json").exists()
    rec = json.loads((tmp_path / "run" / "failure.json").read_text())
    assert "bad.bvh" in rec["error"] and rec["traceback"]


def test_console_missing_imus_fails_cleanly(tmp_path):
    scen = tmp_path / "noimu.yaml"
    scen.write_text("name: noimu\nrig: ring4\nimage_size: [80, 60]\nimu: {enabled: false}\n"
                    "depth: {enabled: false}\njoints2d: {enabled: false}\n")
    r = _console([f"data.scenario={scen}", "data.clip.frames=3",
                  f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert r.returncode == 2, r.stderr
    assert "tracking IMUs" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["basic", "joblib"])
def test_sweep_survives_a_failing_job(tmp_path, launcher):
    """The issue's sweep: good jobs finish and write metrics.json, the bad ones are reported
    (failure.json, one line each) and the command exits with status 2."""
    sweep = tmp_path / "sweep"
    # "++": the sweep's base config (the default tracker, LS) has no annealing layers
    rest = [("++" + s if s.startswith("tracker.") else s) for s in SMALL
            if not s.startswith(("tracker=", "data.clip.frames="))]
    r = _console(["-m", "tracker=p,g", "data.clip.path=/nonexistent,null",
                  "data.clip.frames=3", *rest, f"hydra/launcher={launcher}",
                  "hydra.launcher.n_jobs=2" if launcher == "joblib" else "progress=false",
                  f"hydra.sweep.dir={sweep}"], tmp_path, timeout=900)
    assert r.returncode == 2, r.stderr[-3000:]
    good = sorted(sweep.rglob("metrics.json"))
    bad = sorted(sweep.rglob("failure.json"))
    assert len(good) == 2 and len(bad) == 2
    assert {json.loads(p.read_text())["tracker"] for p in good} == {"p", "g"}
    assert all("nonexistent" in str(p) for p in bad)
    assert "2 job(s) of the sweep failed" in r.stderr and "/nonexistent" in r.stderr


@pytest.mark.slow
def test_sweep_without_failures_exits_zero(tmp_path):
    r = _console(["-m", "tracker=g", "seed=0,1", *SMALL, f"hydra.sweep.dir={tmp_path / 's'}"],
                 tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    seeds = {json.loads(p.read_text())["seed"] for p in (tmp_path / "s").glob("*/metrics.json")}
    assert seeds == {0, 1}


@pytest.mark.slow
def test_real_frame_through_the_assembled_components(tmp_path, shared_data):
    root = shared_data / "multiview" / "bodytrack_sequenceB_1"
    r = _console(["data=bodytrack", f"data.path={root}", "data.scale=0.5",
                  "tracker=real_frame", "tracker.inference.rounds=2",
                  "tracker.num_particles=60", "tracker.inference.layers=5",
                  f"hydra.run.dir={tmp_path / 'run'}", "progress=false"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["tracker"] == "real_frame" and len(m["silhouette_iou"]["per_view"]) == 4
    assert m["silhouette_iou"]["mean"] > 0.3
    grids = list((tmp_path / "run").glob("overlay_*.png"))  # the last frame, every view
    assert len(grids) == 1 and (tmp_path / "run" / "track.glb").is_file()
    # the default tracker needs IMUs: a clear message pointing at the right preset
    r = _console(["data=bodytrack", f"data.path={root}", "data.scale=0.5",
                  f"hydra.run.dir={tmp_path / 'run2'}"], tmp_path)
    assert r.returncode == 2 and "tracker=real_frame" in r.stderr


def test_summary_names_layers_only_for_a_layered_inference(capsys):
    from torchmocap.cli.outputs import _search_row

    assert _search_row({"num_particles": 1, "layers": None}) == ("particles", "1")
    assert _search_row({"num_particles": 200, "layers": 15}) == ("particles x layers",
                                                                 "200 x 15")
