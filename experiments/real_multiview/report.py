"""The table and plots of the experiment: the peers (``results/peers.json``, written by
``peers.py``) and torchmocap's runs, scored by one protocol (``protocol.py``).

torchmocap runs: one ``torchmocap-track data=recording data.path=<recording> tracker=<preset>
evaluation.heldout_camera=<cam>`` run per held-out camera, given with ``--runs`` (a run
directory, or a folder searched for them; default ``runs/`` here). From a run the report reads

* ``metrics.json``: ``tracker``, ``seed``, ``seconds_per_frame``, ``heldout`` (``median_px``,
  ``mean_px``, ``pck_05``, ``pck_10``, optionally ``camera``) and ``consistency`` — shown as the
  run reported them, in a table of their own;
* ``.hydra/config.yaml``: ``data.path`` (must be the peers' recording), ``data.start`` /
  ``data.stride`` (the frames tracked) and ``evaluation.heldout_camera`` (when ``heldout`` does
  not name the camera);
* ``track.npz`` ``theta`` and ``tracked.bvh`` (the same track on the subject's skeleton): the
  BODY_25B keypoints of the track (the keypoint map, :mod:`torchmocap.skeleton.keypoints`,
  ``--keypoint-map``, on the track's skeleton), scored exactly as the peers' reconstructions
  (full-resolution pixels, the same threshold, bones and keypoints) — these are the numbers
  in the main table and the plots.

Writes ``results/table.md``, ``results/heldout_error.png`` (per held-out camera, each method's
median error per frame over time) and ``results/bone_cv.png`` (each bone's length CV per
method, mean over the held-out reconstructions).

Usage (from the repository root)::

    python experiments/real_multiview/report.py                      # peers only, or runs/
    python experiments/real_multiview/report.py --runs outputs/real  # + torchmocap runs
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from protocol import (  # noqa: E402 - this folder is not a package
    CV_BONES,
    KEYPOINTS,
    LIMB_KEYPOINTS,
    Detections,
    bone_name,
    heldout_scores,
    load_detections,
    score_row,
)

RESULTS = HERE / "results"
RUNS = HERE / "runs"
RECORDING = HERE.parents[2] / "shared" / "data" / "multiview" / "pose2sim_balancing"
#: ``heldout`` entries a run's metrics.json must have
HELDOUT_KEYS = ("median_px", "mean_px", "pck_05", "pck_10")


class RunError(ValueError):
    """A torchmocap run directory that cannot be read (names the file and what is wrong)."""


# ----------------------------------------------------------------------------- torchmocap runs
def find_runs(paths: list[Path]) -> tuple[list[Path], list[Path]]:
    """Run directories (with ``metrics.json``) under ``paths``, and failed ones (only
    ``failure.json``)."""
    done, failed = [], []
    for p in paths:
        if not p.is_dir():
            raise RunError(f"--runs {p}: no such directory")
        done += sorted({m.parent for m in p.rglob("metrics.json")})
        failed += sorted({f.parent for f in p.rglob("failure.json")
                          if not (f.parent / "metrics.json").is_file()})
    return done, failed


def _config(run: Path) -> dict:
    """The run's ``.hydra/config.yaml`` (``{}`` without one)."""
    import yaml

    path = run / ".hydra" / "config.yaml"
    if not path.is_file():
        return {}
    try:
        cfg = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise RunError(f"{path}: not valid YAML ({e})") from None
    return cfg if isinstance(cfg, dict) else {}


def _tracker_label(name, cfg: dict) -> str:
    """The preset's name, and its smoother's class when the run smoothed its track."""
    smoother = ((cfg.get("tracker") or {}).get("smoother") or {})
    target = smoother.get("_target_") if isinstance(smoother, dict) else None
    return f"{name} + {str(target).rsplit('.', 1)[-1]}" if target else str(name)


def _heldout_camera(run: Path, metrics: dict, cfg: dict, det: Detections) -> int:
    cam = metrics["heldout"].get("camera")
    if cam is None:
        cam = (cfg.get("evaluation") or {}).get("heldout_camera")
    if cam is None:
        raise RunError(f"{run}: which camera was held out? neither metrics.json heldout.camera "
                       "nor .hydra/config.yaml evaluation.heldout_camera says")
    try:
        return det.camera_index(cam)
    except ValueError as e:
        raise RunError(f"{run}: held-out camera: {e}") from None


def track_keypoints(run: Path, keypoint_map: str = "body_25b") -> torch.Tensor:
    """The BODY_25B keypoints ``(T, K, 3)`` of a run's track (NaN for keypoints the map does
    not place): ``tracked.bvh`` through the keypoint map; its frames must be those of
    ``track.npz``'s ``theta``."""
    from torchmocap.io import read_bvh
    from torchmocap.skeleton import keypoint_positions, load_keypoint_map

    for name in ("track.npz", "tracked.bvh"):
        if not (run / name).is_file():
            raise RunError(f"{run}: no {name} (a finished torchmocap-track run writes it)")
    with np.load(run / "track.npz") as npz:
        if "theta" not in npz:
            raise RunError(f"{run / 'track.npz'}: no 'theta' array (has {list(npz.keys())})")
        frames = int(npz["theta"].shape[0])
    clip = read_bvh(run / "tracked.bvh")
    if clip.num_frames != frames:
        raise RunError(f"{run}: tracked.bvh has {clip.num_frames} frames, track.npz theta "
                       f"{frames}")
    kmap = load_keypoint_map(keypoint_map, clip.to_skeleton()[0])
    if kmap.format_keypoints != KEYPOINTS:
        raise RunError(f"keypoint map {keypoint_map!r} is of format {kmap.format!r}; the "
                       "detections are BODY_25B")
    x = keypoint_positions(clip.global_positions(), clip.global_rotations(), kmap)
    out = torch.full((frames, len(KEYPOINTS), 3), float("nan"), dtype=torch.float64)
    out[:, kmap.columns(KEYPOINTS)] = x.double()
    return out


def read_run(run: Path, det: Detections, keypoint_map: str = "body_25b") -> dict:
    """One torchmocap run: ``tracker``, ``seed``, ``camera`` (name), ``row`` (its track scored
    by the protocol, with the run's seconds per frame; ``None`` entries where the run tracked
    fewer frames than the peers) and ``reported`` (its own ``heldout`` and ``consistency``).

    Raises:
        RunError: a missing or malformed file, another recording, frames outside it.
    """
    path = run / "metrics.json"
    try:
        metrics = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise RunError(f"{path}: cannot read ({e})") from None
    held = metrics.get("heldout")
    if not isinstance(held, dict) or any(k not in held for k in HELDOUT_KEYS):
        raise RunError(f"{path}: expected 'heldout' with {list(HELDOUT_KEYS)} (a run with "
                       f"evaluation.heldout_camera set), got {held!r}")
    cfg = _config(run)
    data = cfg.get("data") or {}
    if data.get("path") is not None and Path(str(data["path"])).name != det.path.name:
        raise RunError(f"{run}: tracked {data['path']}, the peers' recording is {det.path}")
    c = _heldout_camera(run, metrics, cfg, det)
    X = track_keypoints(run, keypoint_map)
    start, stride = int(data.get("start") or 0), int(data.get("stride") or 1)
    frames = [start + stride * i for i in range(X.shape[0])]
    where = {t: i for i, t in enumerate(det.frames)}
    outside = [t for t in frames if t not in where]
    if outside:
        raise RunError(f"{run}: tracked frames {outside[:5]} the peers' frames "
                       f"{det.frames[0]}..{det.frames[-1]} do not have")
    # the track on the peers' frames (NaN where the run has none: counted as missing)
    full = torch.full((len(det.frames), len(KEYPOINTS), 3), float("nan"), dtype=torch.float64)
    full[[where[t] for t in frames]] = X
    row = score_row(heldout_scores(full, det, c), full, det.fps)
    row["seconds_per_frame"] = metrics.get("seconds_per_frame")
    return {"tracker": _tracker_label(metrics.get("tracker", run.name), cfg),
            "seed": metrics.get("seed"),
            "camera": det.cameras[c], "row": row, "run": str(run),
            "reported": {"heldout": {k: held[k] for k in (*HELDOUT_KEYS, "pixels")
                                     if k in held},
                         "consistency": metrics.get("consistency")}}


def torchmocap_methods(runs: list[dict]) -> dict[str, dict]:
    """The runs as methods (``peers.json``'s layout), one per tracker and seed."""
    out: dict[str, dict] = {}
    for r in runs:
        key = f"torchmocap_{r['tracker']}_seed{r['seed']}"
        m = out.setdefault(key, {"label": f"torchmocap `{r['tracker']}` (seed {r['seed']})",
                                 "saw_heldout": False, "rows": {}, "reported": {},
                                 "runs": {}})
        if r["camera"] in m["rows"]:
            raise RunError(f"two runs of {m['label']} hold out {r['camera']}: "
                           f"{m['runs'][r['camera']]} and {r['run']}")
        m["rows"][r["camera"]] = r["row"]
        m["reported"][r["camera"]] = r["reported"]
        m["runs"][r["camera"]] = r["run"]
    return out


# ----------------------------------------------------------------------------- table
def _f(x, fmt: str = ".1f", scale: float = 1.0) -> str:
    return "–" if x is None or (isinstance(x, float) and not math.isfinite(x)) \
        else format(scale * x, fmt)


def _mean(vals: list) -> float | None:
    vals = [v for v in vals if v is not None and math.isfinite(v)]
    return sum(vals) / len(vals) if vals else None


def _missing_pct(row: dict) -> float | None:
    n = row["compared"] + row["missing"]
    return 100.0 * row["missing"] / n if n else None


def _cells(row: dict) -> str:
    return (f"{_f(row['median_px'])} | {_f(row['mean_px'])} | {_f(row['pck_05'], '.1f', 100)} | "
            f"{_f(row['pck_10'], '.1f', 100)} | {_f(_missing_pct(row))} | "
            f"{_f(row['bone_cv_mean'], '.2f')} | {_f(row['jitter'], '.1f')} | "
            f"{_f(row.get('seconds_per_frame'), '.4f')}")


def _name(m: dict) -> str:
    return m["label"] + (" †" if m["saw_heldout"] else "")


def table(peers: dict, tm: dict, notes: list[str]) -> str:
    """``table.md``: the mean over the held-out cameras and the per-camera rows of every
    method, the missing torchmocap rows, and what the runs reported themselves."""
    cams = peers["cameras"]
    methods = {**tm, **peers["methods"]}
    head = ("median px | mean px | PCK@5 % | PCK@10 % | missing % | bone CV % | "
            "jitter m/s² | s/frame")
    lines = [
        f"# {peers['recording']} — leave one camera out: torchmocap and triangulation peers",
        "",
        f"Frames {peers['frames'][0]}–{peers['frames'][1]} at {peers['fps']:g} fps, cameras "
        f"{', '.join(cams)}. Each method reconstructs from the other "
        f"{len(cams) - 1} views; its BODY_25B keypoints are projected into the held-out view "
        f"and compared with that view's detections of confidence > {peers['min_confidence']} "
        "(full-resolution pixels; PCK thresholds 5 % and 10 % of the height of the frame's box "
        "of compared detections; *missing* = compared detections the method did not "
        "reconstruct). Bone CV: mean over "
        f"{len(CV_BONES)} bones ({', '.join(bone_name(b) for b in CV_BONES)}) of the "
        "coefficient of variation of their length over the frames; jitter: mean acceleration "
        f"of the {len(LIMB_KEYPOINTS)} keypoints of those bones. The peers use the detections "
        f"of confidence > {peers['input_confidence']}. s/frame: wall time of the "
        "reconstruction (peers: after an untimed first call; 2 shared CPU cores, one thread, "
        f"load average {peers['load_before']['load_average_1_5_15min'][0]:g} before and "
        f"{peers['load_after'][0]:g} after; torchmocap: the run's own `seconds_per_frame`).",
        "",
        "† context only: Pose2Sim triangulated from all four views, the held-out one included.",
        "",
        "## Mean over the held-out cameras",
        "",
        f"| method | {head} |",
        "|---|" + "---:|" * 8,
    ]
    for m in methods.values():
        rows = [m["rows"][c] for c in cams if c in m["rows"]]
        mean = {k: _mean([r.get(k) for r in rows]) for k in
                ("median_px", "mean_px", "pck_05", "pck_10", "bone_cv_mean", "jitter",
                 "seconds_per_frame")}
        mean["compared"] = sum(r["compared"] for r in rows)
        mean["missing"] = sum(r["missing"] for r in rows)
        some = "" if len(rows) == len(cams) else f" ({len(rows)} of {len(cams)} cameras)"
        lines.append(f"| {_name(m)}{some} | {_cells(mean)} |")
    lines += ["", "## Per held-out camera", "",
              f"| method | held out | {head} |", "|---|---|" + "---:|" * 8]
    for m in methods.values():
        for c in cams:
            if c in m["rows"]:
                lines.append(f"| {_name(m)} | {c} | {_cells(m['rows'][c])} |")
    lines += ["", "## torchmocap rows", ""] + [f"- {n}" for n in notes]
    if peers["skipped"]:
        lines += ["", "## Peers skipped", ""] + [f"- `{k}`: {v}" for k, v in
                                                  peers["skipped"].items()]
    reported = [(m, c, m["reported"][c]) for m in tm.values() for c in cams
                if c in m["reported"]]
    if reported:
        lines += ["", "## As the runs report them (metrics.json `heldout`, `consistency`)", "",
                  "The run's own scores: its pixels (`heldout.pixels`) and its skeleton's "
                  "keypoints; bone CV over the limb segments the keypoint map has, jitter over "
                  "every mapped keypoint.", "",
                  "| method | held out | pixels | median px | mean px | PCK@5 % | PCK@10 % | "
                  "bone CV % | jitter m/s² |", "|---|---|---|---:|---:|---:|---:|---:|---:|"]
        for m, c, rep in reported:
            h = rep["heldout"]
            cv, jit = _reported_consistency(rep["consistency"])
            lines.append(f"| {m['label']} | {c} | {h.get('pixels', '–')} | "
                         f"{_f(h['median_px'])} | {_f(h['mean_px'])} | "
                         f"{_f(h['pck_05'], '.1f', 100)} | {_f(h['pck_10'], '.1f', 100)} | "
                         f"{_f(cv, '.2f')} | {_f(jit)} |")
    return "\n".join(lines) + "\n"


def _reported_consistency(cons) -> tuple[float | None, float | None]:
    """(bone-length CV %, jitter m/s²) of a run's ``consistency`` (None where absent)."""
    if not isinstance(cons, dict):
        return None, None
    cv = (cons.get("bone_length_cv_percent") or {}).get("mean")
    jit = (cons.get("jitter_m_s2") or {}).get("mean")
    return cv, jit


def missing_notes(tm: dict, cams: list[str], failed: list[Path], problems: list[str]
                  ) -> list[str]:
    """What the table lacks of torchmocap: no runs at all, cameras without a run, failed or
    unreadable runs."""
    notes = []
    if not tm:
        notes.append(
            "**missing**: no torchmocap runs were given (`--runs`). Each comes from "
            "`torchmocap-track data=recording data.path=<recording> tracker=<preset> "
            f"evaluation.heldout_camera=<cam>`, one run per held-out camera ({', '.join(cams)}).")
    for m in tm.values():
        lacking = [c for c in cams if c not in m["rows"]]
        if lacking:
            notes.append(f"{m['label']}: **missing** held-out camera(s) {', '.join(lacking)}")
    notes += [f"failed run (failure.json): `{p}`" for p in failed]
    notes += [f"unreadable run: {p}" for p in problems]
    if tm and not notes:
        notes.append("every torchmocap method has a run for every held-out camera")
    return notes


# ----------------------------------------------------------------------------- plots
def _methods_in_order(peers: dict, tm: dict) -> list[dict]:
    return list(tm.values()) + list(peers["methods"].values())


def plot_heldout(peers: dict, tm: dict, path: Path) -> None:
    """Per held-out camera, each method's median error per frame over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchmocap.atomic import atomic_path

    cams = peers["cameras"]
    cols = 2
    rows = math.ceil(len(cams) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(11, 3.2 * rows), sharex=True, squeeze=False)
    t0 = peers["frames"][0]
    for ax, cam in zip(axes.flat, cams):
        top = 0.0
        for m in _methods_in_order(peers, tm):
            if cam not in m["rows"]:
                continue
            y = np.array([np.nan if v is None else v for v in m["rows"][cam]["frame_median_px"]])
            t = (t0 + np.arange(len(y))) / peers["fps"]
            ax.plot(t, y, "--" if m["saw_heldout"] else "-", lw=1.6 if "torchmocap" in
                    m["label"] else 1.0, label=_name(m))
            if np.isfinite(y).any():
                top = max(top, float(np.nanpercentile(y, 98)))
        ax.set_title(f"held out: {cam}")
        ax.set_ylabel("median error (px)")
        ax.set_ylim(0, 1.3 * top if top > 0 else None)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(cams):]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8)
    # the legend's rows (about 0.2 inch each) below the panels and their x label
    legend_in = 0.35 + 0.2 * math.ceil(len(labels) / 2)
    fig.tight_layout(rect=(0, legend_in / fig.get_figheight(), 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def plot_bone_cv(peers: dict, tm: dict, path: Path) -> None:
    """Each bone's length CV per method (mean over its held-out reconstructions)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchmocap.atomic import atomic_path

    bones = [bone_name(b) for b in CV_BONES]
    methods = _methods_in_order(peers, tm)
    fig, ax = plt.subplots(figsize=(11, 5.5))
    width = 0.8 / max(len(methods), 1)
    for i, m in enumerate(methods):
        cv = [_mean([r["bone_cv_percent"].get(b) for r in m["rows"].values()]) for b in bones]
        x = np.arange(len(bones)) + (i - (len(methods) - 1) / 2) * width
        ax.bar(x, [np.nan if v is None else v for v in cv], width, label=_name(m),
               hatch="//" if m["saw_heldout"] else None)
    ax.set_xticks(np.arange(len(bones)))
    ax.set_xticklabels(bones, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("bone-length CV (%)")
    ax.grid(axis="y", alpha=0.3)
    fig.legend(*ax.get_legend_handles_labels(), loc="lower center", ncol=2, fontsize=8)
    # the legend's rows (about 0.2 inch each) and the rotated bone names below the axes
    legend_in = 0.2 + 0.2 * math.ceil(len(methods) / 2)
    fig.tight_layout(rect=(0, legend_in / fig.get_figheight(), 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


# ----------------------------------------------------------------------------- main
def _write_atomic(path: Path, text: str) -> None:
    from torchmocap.atomic import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--peers", type=Path, default=RESULTS / "peers.json",
                    help="peers.py's output")
    ap.add_argument("--runs", type=Path, action="append", default=None,
                    help="a torchmocap run directory or a folder of them (repeatable; default "
                         "runs/ here when it exists)")
    ap.add_argument("--recording", type=Path, default=RECORDING,
                    help="the recording the runs tracked (their tracks are scored against its "
                         "detections)")
    ap.add_argument("--keypoint-map", default="body_25b",
                    help="keypoint map placing BODY_25B on the runs' skeleton")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if not args.peers.is_file():
        print(f"report: no {args.peers}; run peers.py first", file=sys.stderr)
        return 2
    peers = json.loads(args.peers.read_text())
    paths = args.runs if args.runs is not None else ([RUNS] if RUNS.is_dir() else [])
    done, failed = find_runs(paths)
    runs, problems = [], []
    if done:
        det = load_detections(args.recording, peers["frames"][0], peers["frames"][1] + 1)
        if det.cameras != peers["cameras"]:
            print(f"report: {args.recording} has cameras {det.cameras}, peers.json "
                  f"{peers['cameras']}", file=sys.stderr)
            return 2
        for run in done:
            try:
                runs.append(read_run(run, det, args.keypoint_map))
            except (RunError, ValueError) as e:
                problems.append(str(e))
                print(f"report: {e}", file=sys.stderr)
    tm = torchmocap_methods(runs)
    notes = missing_notes(tm, peers["cameras"], failed, problems)
    args.out.mkdir(parents=True, exist_ok=True)
    _write_atomic(args.out / "table.md", table(peers, tm, notes))
    plot_heldout(peers, tm, args.out / "heldout_error.png")
    plot_bone_cv(peers, tm, args.out / "bone_cv.png")
    print(f"report: wrote {args.out / 'table.md'}, heldout_error.png, bone_cv.png "
          f"({len(runs)} torchmocap runs, {len(peers['methods'])} peer methods)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
