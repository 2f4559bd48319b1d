"""The margins of the recording checks (``torchmocap.data.recordings.checks``): their figures on
the intact recordings (every window of 10 frames of pose2sim_balancing, the bodytrack frame)
and on copies corrupted the way real recordings are; writes ``results/margins.md``.

    python experiments/recording_checks/margins.py [--data ../shared/data] [--out DIR]
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import re
import shutil
import tempfile
import warnings
from pathlib import Path

import torch

from torchmocap.data.recordings import checks
from torchmocap.data.recordings.bodytrack import load_bodytrack
from torchmocap.data.recordings.loader import load_recording

HERE = Path(__file__).resolve().parent
SCALE = 0.25


# ------------------------------------------------------------------ corruptions of a copy

def _toml(root: Path, fn) -> None:
    p = root / "calibration" / "Calib.toml"
    p.write_text(fn(p.read_text()))


def _sections(text):
    return re.split(r"(?m)^(?=\[)", text)


def swap_calibrations(root, a="cam_01", b="cam_02"):
    def fn(text):
        parts = _sections(text)
        ia = next(i for i, s in enumerate(parts) if s.startswith(f"[{a}]"))
        ib = next(i for i, s in enumerate(parts) if s.startswith(f"[{b}]"))
        parts[ia], parts[ib] = parts[ib].replace(b, a), parts[ia].replace(a, b)
        return "".join(parts)
    _toml(root, fn)


def millimetres(root):
    _toml(root, lambda text: re.sub(r"translation = \[([^\]]*)\]", lambda m: "translation = [ "
                                    + ", ".join(repr(1000 * float(v))
                                                for v in m.group(1).split(",")) + "]", text))


def far_camera(root, cam="cam_02"):
    def fn(text):
        parts = _sections(text)
        i = next(i for i, s in enumerate(parts) if s.startswith(f"[{cam}]"))
        parts[i] = re.sub(r"translation = \[[^\]]*\]", "translation = [ 1e6, 1e6, 1e6]",
                          parts[i])
        return "".join(parts)
    _toml(root, fn)


def _keypoints(root, cam, fn):
    for kind in ("pose-associated", "pose"):
        for p in sorted((root / kind / f"{cam}_json").glob("*.json")):
            data = json.loads(p.read_text())
            for person in data["people"]:
                k = person.get("pose_keypoints_2d", [])
                for i in range(0, len(k), 3):
                    if k[i + 2] > 0:
                        k[i], k[i + 1], k[i + 2] = fn(k[i], k[i + 1], k[i + 2])
            p.write_text(json.dumps(data))


def swap_detections(root, a="cam01", b="cam02"):
    for kind in ("pose-associated", "pose"):
        da, db, tmp = root / kind / f"{a}_json", root / kind / f"{b}_json", root / kind / "x"
        da.rename(tmp)
        db.rename(da)
        tmp.rename(db)
        for d, (old, new) in ((da, (b, a)), (db, (a, b))):
            for p in d.glob("*.json"):
                p.rename(d / p.name.replace(old, new))


CASES = {
    "intact": None,
    "translations x 1000 (mm in a metres file)": millimetres,
    "cam_01 <-> cam_02 calibrations": swap_calibrations,
    "cam01 <-> cam02 detections": swap_detections,
    "cam_02 1e6 m away": far_camera,
    "cam02 keypoints + (1e5, -1e5) px": lambda r: _keypoints(r, "cam02",
                                                           lambda u, v, c: (u + 1e5, v - 1e5, c)),
    "cam02 keypoints of half-size images": lambda r: _keypoints(r, "cam02",
                                                              lambda u, v, c: (u / 2, v / 2, c)),
    "cam02 confidences x 3": lambda r: _keypoints(r, "cam02", lambda u, v, c: (u, v, 3 * c)),
}


def _bodytrack_swap(a, b):
    def fn(root):
        cal = root / "CALIB"
        (cal / f"Camera{a}.cal").rename(cal / "tmp")
        (cal / f"Camera{b}.cal").rename(cal / f"Camera{a}.cal")
        (cal / "tmp").rename(cal / f"Camera{b}.cal")
    return fn


def _bodytrack_far(root):
    p = root / "CALIB" / "Camera3.cal"
    lines = p.read_text().splitlines()
    for i in (19, 20, 21):  # the translation (mm)
        lines[i] = str(float(lines[i]) + 1e6)
    p.write_text("\n".join(lines) + "\n")


BODYTRACK = {"intact": None, "Camera1 <-> Camera2": _bodytrack_swap(1, 2),
             "Camera1 <-> Camera3": _bodytrack_swap(1, 3), "Camera3 1 km away": _bodytrack_far}


# ------------------------------------------------------------------ figures

def keypoint_sets(seq, first: int = 10) -> dict:
    """Over the first ``first`` frames: the largest relative residual of every set of three
    or four views (each view against the triangulation of the set's others) and of every pair
    (each against their own), by whether the set holds an inconsistent view."""
    rig = copy.deepcopy(seq.rig).double()
    v = checks._Views(seq.joints2d[:first].double(), rig)
    C = rig.num_cameras
    out = {}
    for n in range(2, C + 1):
        for S in itertools.combinations(range(C), n):
            if n == 2:
                e = max(v.relative(list(S), c) for c in S)
            else:
                e = max(v.relative([o for o in S if o != c], c) for c in S)
            out[tuple(seq.rig.names[i] for i in S)] = e
    return out


def _load(root, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = load_recording(root, masks="none", scale=SCALE, checks="warn", **kw)
    said = [str(w.message) for w in caught if "codec's crop" not in str(w.message)]
    return seq, said


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default=str(HERE.parents[2] / "shared" / "data"))
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()
    data = Path(args.data)
    src = data / "multiview" / "pose2sim_balancing"
    rows = ["## pose2sim_balancing, every window of 10 frames (intact)", "",
            "| frames | consistent | stature m | per view: residual px (relative) | worst set "
            "of 3-4 views | worst pair |", "|---|---|---|---|---|---|"]
    worst_sets, worst_pairs = 0.0, 0.0
    plot: dict[str, list[tuple[str, float]]] = {"intact": [], "corrupted": []}
    full, _ = _load(src, subject={"frames": 1})
    for start in range(0, full.num_frames, 10):
        seq, said = _load(src, start=start, stop=start + 10)
        r = seq.meta.view_consistency
        sets = keypoint_sets(seq)
        big = max(e for k, e in sets.items() if len(k) >= 3)
        pair = max(e for k, e in sets.items() if len(k) == 2)
        worst_sets, worst_pairs = max(worst_sets, big), max(worst_pairs, pair)
        plot["intact"].append((f"frames {start}-{start + 9}", big))
        views = ", ".join(f"{n} {e['residual_px']:.0f} ({e['relative']:.3f})"
                          for n, e in r["views"].items())
        rows.append(f"| {start}-{start + 9} | {len(r['consistent_views'])}/4 | "
                    f"{r['stature_m']:.2f} | {views} | {big:.3f} | {pair:.3f} |"
                    + (f" warned: {said}" if said else ""))
    rows += ["", f"Largest over the windows: {worst_sets:.3f} (sets of three or four views; "
             f"limit {checks.MAX_VIEW_RESIDUAL}), {worst_pairs:.3f} (pairs; limit "
             f"{checks.MAX_PAIR_RESIDUAL}).", ""]
    rows += ["## Corrupted copies of pose2sim_balancing (frames 0-9)", "",
             "| case | consistent views | stature m | flagged: residual px (relative) | best "
             "set of 3-4 views holding a flagged view (best pair) | warnings / refusal |",
             "|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for name, fn in CASES.items():
            root = Path(tmp) / re.sub(r"\W+", "_", name)
            shutil.copytree(src, root, ignore=shutil.ignore_patterns("pose2sim_output"))
            if fn is not None:
                fn(root)
            seq, said = _load(root, stop=10)
            r = seq.meta.view_consistency
            bad = [n for n, e in r["views"].items() if e["status"] == "inconsistent"]
            flagged = ", ".join(f"{n} {r['views'][n]['residual_px']:.0f} "
                                f"({r['views'][n]['relative']:.3f})" for n in bad) or "-"
            sets = keypoint_sets(seq)
            holding = [e for k, e in sets.items() if len(k) >= 3 and set(k) & set(bad)]
            pairs = [e for k, e in sets.items() if len(k) == 2 and set(k) & set(bad)]
            best = f"{min(holding):.3f}" if holding else "-"
            if holding:
                plot["corrupted"].append((name, min(holding)))
            best += f" (pairs {min(pairs):.3f})" if pairs else ""
            try:
                checks.check_views(r, "refuse")
                refused = ""
            except checks.RecordingCheckError as e:
                refused = "refused: " + str(e)[:160] + " ..."
            said = [re.sub(r" \(/[^)]*\)", "", w) for w in said]  # without the temporary paths
            text = "; ".join(w[:120] for w in said if not w.startswith(("data.cameras",
                                                                          "data.unit")))
            rows.append(f"| {name} | {', '.join(r['consistent_views'])} | "
                        f"{r['stature_m']} | {flagged} | {best} | "
                        f"{'; '.join(x for x in (text, refused) if x) or 'silent'} |")
        rows += ["", "## The bodytrack frame (masks only)", "",
                 "| case | consistent views | per view: agreement (fraction of its mask covered "
                 "by the others' hull) | the best set of 3-4 views: its smallest agreement | "
                 "refusal |",
                 "|---|---|---|---|---|"]
        bsrc = data / "multiview" / "bodytrack_sequenceB_1"
        for name, fn in BODYTRACK.items():
            root = Path(tmp) / ("bt_" + re.sub(r"\W+", "_", name))
            shutil.copytree(bsrc, root)
            if fn is not None:
                fn(root)
            rig, _, masks = load_bodytrack(root, 0.5)
            r = checks.mask_consistency(masks, rig, [f"FG{i + 1}" for i in range(4)])
            rr = copy.deepcopy(rig).double()
            mins = []
            for n in (4, 3):
                for S in itertools.combinations(range(4), n):
                    mins.append(min(checks._mask_agreement(rr, masks, checks._hull_points(
                        rr, masks, [o for o in S if o != c], checks.HULL_VOXEL_M), c)[1]
                        for c in S))
            views = ", ".join(f"{n} {e['agreement']:.2f}" for n, e in r["views"].items())
            try:
                checks.check_views(r, "refuse")
                refused = "silent"
            except checks.RecordingCheckError as e:
                refused = "refused: " + str(e)[:140] + " ..."
            rows.append(f"| {name} | {', '.join(r['consistent_views']) or '-'} | {views} | "
                        f"{max(mins):.2f} | {refused} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "margins.md").write_text("\n".join(rows) + "\n")
    _plot(plot, out / "margins.png")
    print("\n".join(rows))


def _plot(plot, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    items = [(n, v, "tab:green") for n, v in plot["intact"]] + \
        [(n, v, "tab:red") for n, v in plot["corrupted"]]
    fig, ax = plt.subplots(figsize=(8, 0.32 * len(items) + 1.2))
    ax.barh(range(len(items)), [v for _, v, _ in items], color=[c for *_, c in items])
    ax.set_yticks(range(len(items)), [n for n, *_ in items], fontsize=8)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.axvline(checks.MAX_VIEW_RESIDUAL, color="k", ls="--", lw=1)
    ax.text(checks.MAX_VIEW_RESIDUAL, len(items) - 0.4, f" limit {checks.MAX_VIEW_RESIDUAL}",
            fontsize=8)
    ax.set_xlabel("largest residual / the subject's size in the view\n(green: the intact "
                  "recording's worst set of 3-4 views; red: the best set\nholding a corrupted "
                  "view)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
