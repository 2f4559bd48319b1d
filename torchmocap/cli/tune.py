"""``torchmocap-tune``: the objective a sweeper tunes — one setting tracked on several training
clips — and, at the end of the sweep, the best setting tracked on held-out clips (Hydra CLI).

The command is ``torchmocap-track``'s config with ``+tune=default`` (``conf/tune/default.yaml``:
the ``tune`` settings, the report callback, ``outputs/tune`` and ``multirun/tune``
directories). A job composes that config once per training clip (``tune.train_clips``:
``data/clip`` options), tracks each into ``<job dir>/<clip>/`` exactly as ``torchmocap-track``
would (same outputs, same up-to-date skipping), writes ``<job dir>/tune.json`` and returns the
mean of the clips' ``tune.objective`` (a dotted path into ``metrics.json``; default the
validation orientation error, degrees) — the value a sweeper such as Optuna minimises. A failing
clip fails the trial (``failure.json`` in the clip's directory); in a multirun it returns the
worst value (``inf`` when minimising), so that the sweep goes on (Optuna refuses a NaN).

:class:`HeldOutReport` (a Hydra callback in ``tune/default.yaml``) then picks the job with the
lowest objective, tracks ``tune.heldout_clips`` with its settings into
``<sweep dir>/heldout/<clip>/`` (and, with ``tune.baseline``, with the swept settings left at
the preset's values into ``<sweep dir>/baseline/<clip>/``), and writes ``tune_report.json`` and
``tune_report.md`` into the sweep directory. It works with any sweeper and launcher (basic
grid, Optuna, submitit); the held-out clips are tracked in the process that ran the sweep.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import hydra
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from torchmocap.atomic import write_json_atomic
from torchmocap.cli.runs import (
    config_fingerprint,
    console_main,
    hydra_task,
    is_multirun,
    read_json,
    write_failure,
)

__all__ = ["HeldOutReport", "evaluate_clips", "main"]

TUNE_FILE = "tune.json"
REPORT_NAME = "tune_report"


def _clip_overrides(overrides: list[str], clip: str) -> list[str]:
    """``overrides`` with any ``data/clip`` choice replaced by ``clip``."""
    keep = [o for o in overrides
            if o.lstrip("+~").split("=", 1)[0] not in ("data/clip", "data.clip")]
    return [*keep, f"data/clip={clip}"]


def _check_clips(name: str, clips: Any) -> list[str]:
    if OmegaConf.is_config(clips):
        clips = OmegaConf.to_container(clips)
    if clips is None:
        clips = []
    if isinstance(clips, str) or not isinstance(clips, list) or \
            not all(isinstance(c, str) and c and "/" not in c for c in clips):
        raise ValueError(f"{name}: expected a list of data/clip option names, got {clips!r}")
    if len(set(clips)) != len(clips):
        raise ValueError(f"{name}: a clip is listed twice: {clips}")
    return list(clips)


def _searchpath(hydra_overrides: Any) -> list[str]:
    """The ``hydra.searchpath`` overrides among a run's Hydra overrides (the composed configs
    need them to find the same config files)."""
    return [str(o) for o in (hydra_overrides or [])
            if str(o).lstrip("+").split("=", 1)[0] == "hydra.searchpath"]


def evaluate_clips(clips: list[str], overrides: list[str], out: Path, config_name: str,
                   objective: str, searchpath: list[str] = ()) -> dict[str, Any]:
    """Track each clip (``data/clip=<clip>`` on top of ``overrides``) into ``out/<clip>/``.

    Must run inside a Hydra application (the configs are composed with :func:`hydra.compose`;
    ``searchpath``: the run's ``hydra.searchpath`` overrides).
    Returns ``{"clips": {clip: value}, "mean": mean value, "failed": {clip: error}}``; a clip
    whose run fails gets ``nan`` and a ``failure.json`` in its directory.
    """
    from hydra import compose

    from torchmocap.cli.aggregate import metric_value
    from torchmocap.cli.track import run

    values: dict[str, float] = {}
    failed: dict[str, str] = {}
    for clip in clips:
        d = out / clip
        d.mkdir(parents=True, exist_ok=True)
        cfg = None
        try:
            cfg = compose(config_name=config_name,
                          overrides=[*searchpath, *_clip_overrides(overrides, clip)])
            m = run(cfg, d)
            v = metric_value(m, objective)
            if v is None:
                raise KeyError(f"tune.objective: {objective!r} is not a number in the metrics "
                               f"of clip {clip}")
            values[clip] = v
        except Exception as e:  # noqa: BLE001 - recorded per clip; the trial fails
            try:
                fp = None if cfg is None else config_fingerprint(cfg)
            except Exception:  # noqa: BLE001
                fp = None
            failed[clip] = write_failure(d, e, fp, "torchmocap-tune")
            values[clip] = math.nan
            print(f"torchmocap-tune: error: {clip}: {failed[clip]}", file=sys.stderr)
    finite = [v for v in values.values() if math.isfinite(v)]
    mean = sum(finite) / len(finite) if finite and not failed else math.nan
    return {"clips": values, "mean": mean, "failed": failed}


def _json_safe(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _direction(tune) -> str:
    """``tune.direction``, checked: ``minimize`` or ``maximize``."""
    direction = (tune or {}).get("direction", "minimize")
    if direction not in ("minimize", "maximize"):
        raise ValueError(f"tune.direction: expected 'minimize' or 'maximize', got {direction!r}")
    return str(direction)


def _worst(cfg) -> float:
    """The worst objective value (a failed trial): a sweeper such as Optuna goes on."""
    tune = cfg.get("tune") or {}
    return math.inf if tune.get("direction", "minimize") == "minimize" else -math.inf


@hydra.main(config_path="../conf", config_name="track", version_base="1.3")
@hydra_task("torchmocap-tune", failed=_worst)
def _hydra_main(cfg: DictConfig, out: Path) -> float:
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    if "tune" not in cfg:
        raise ValueError("tune: no tune settings (select them with +tune=default)")
    _direction(cfg.tune)  # before any clip is tracked
    clips = _check_clips("tune.train_clips", cfg.tune.train_clips)
    _check_clips("tune.heldout_clips", cfg.tune.get("heldout_clips"))
    if not clips:
        raise ValueError("tune.train_clips: expected at least one clip")
    overrides = list(hc.overrides.task)
    objective = str(cfg.tune.get("objective", "orientation_error_deg.mean"))
    res = evaluate_clips(clips, overrides, out, hc.job.config_name, objective,
                         _searchpath(hc.overrides.hydra))
    write_json_atomic({"objective": _json_safe(res["mean"]), "objective_key": objective,
                       "clips": {k: _json_safe(v) for k, v in res["clips"].items()},
                       "failed": res["failed"], "overrides": overrides}, out / TUNE_FILE)
    print(f"torchmocap-tune: {objective} over {', '.join(clips)}: "
          + ", ".join(f"{k} {v:.3f}" for k, v in res["clips"].items())
          + f"; mean {res['mean']:.3f}")
    if res["failed"] and not is_multirun():
        sys.exit(2)
    if not math.isfinite(res["mean"]):  # the worst value: a sweeper (Optuna) goes on
        return _worst(cfg)
    return float(res["mean"])


class HeldOutReport(Callback):
    """Hydra callback: at the end of a run or sweep, track the held-out clips with the best
    job's settings and write ``tune_report.json`` / ``tune_report.md`` (see the module doc)."""

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._report(config, Path(str(config.hydra.run.dir)))

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._report(config, Path(str(config.hydra.sweep.dir)))

    def _report(self, config: DictConfig, root: Path) -> None:
        try:
            report = heldout_report(config, root)
        except Exception as e:  # noqa: BLE001 - a report failure must not hide the sweep
            print(f"torchmocap-tune: error: held-out report: {e}", file=sys.stderr)
            return
        if report is not None:
            print((root / f"{REPORT_NAME}.md").read_text(encoding="utf-8"), end="")


def _trials(root: Path) -> list[dict[str, Any]]:
    trials = []
    for p in sorted(root.rglob(TUNE_FILE)):
        rec = read_json(p)
        if isinstance(rec, dict):
            rec["dir"] = p.parent
            trials.append(rec)
    return trials


def _fmt(v: Any) -> str:
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.3f}"


def heldout_report(config: DictConfig, root: Path) -> dict[str, Any] | None:
    """Pick the best job under ``root``, track the held-out clips and write the report; returns
    the report (None when ``root`` holds no job of this command)."""
    trials = _trials(root)
    if not trials:
        return None
    tune = config.tune
    objective = str(tune.get("objective", "orientation_error_deg.mean"))
    direction = _direction(tune)
    ok = [t for t in trials if isinstance(t.get("objective"), (int, float))]
    report: dict[str, Any] = {"objective_key": objective, "direction": direction,
                              "trials": len(trials), "failed_trials": len(trials) - len(ok),
                              "train_clips": list(tune.train_clips)}
    if not ok:
        report["best"] = None
    else:
        pick = min if direction == "minimize" else max
        best = pick(ok, key=lambda t: t["objective"])
        # the swept settings: overrides whose value differs between the trials
        settings = [dict(o.partition("=")[::2] for o in t.get("overrides", [])) for t in trials]
        varying = {k for k in set().union(*settings)
                   if len({s.get(k) for s in settings}) > 1}
        best_ov = list(best.get("overrides", []))
        report["best"] = {"dir": str(best["dir"]), "objective": best["objective"],
                          "clips": best.get("clips", {}),
                          "settings": [o for o in best_ov if o.partition("=")[0] in varying],
                          "overrides": best_ov}
        heldout = _check_clips("tune.heldout_clips", tune.get("heldout_clips"))
        if heldout:
            name = str(OmegaConf.select(config, "hydra.job.config_name", default="track"))
            sp = _searchpath(OmegaConf.select(config, "hydra.overrides.hydra"))
            res = evaluate_clips(heldout, best_ov, root / "heldout", name, objective, sp)
            report["heldout"] = {"clips": {k: _json_safe(v) for k, v in res["clips"].items()},
                                 "mean": _json_safe(res["mean"]), "failed": res["failed"]}
            if tune.get("baseline", True) and report["best"]["settings"] and len(trials) > 1:
                base_ov = [o for o in best_ov if o.partition("=")[0] not in varying]
                res = evaluate_clips(heldout, base_ov, root / "baseline", name, objective, sp)
                report["baseline"] = {"overrides": base_ov,
                                      "clips": {k: _json_safe(v)
                                                for k, v in res["clips"].items()},
                                      "mean": _json_safe(res["mean"]), "failed": res["failed"]}
    write_json_atomic(report, root / f"{REPORT_NAME}.json")
    _write_markdown(report, root / f"{REPORT_NAME}.md")
    return report


def _write_markdown(report: dict[str, Any], path: Path) -> None:
    from torchmocap.atomic import atomic_path

    lines = [f"# Tuning report: {path.parent.name}", "",
             f"Objective: `{report['objective_key']}` ({report['direction']}), mean over the "
             f"training clips {', '.join(report['train_clips'])}; {report['trials']} trial(s), "
             f"{report['failed_trials']} failed.", ""]
    best = report.get("best")
    if best is None:
        lines.append("No trial finished: nothing to report.")
    else:
        settings = ", ".join(f"`{s}`" for s in best["settings"]) or "(the only trial)"
        lines += [f"Best: {settings} — training objective {_fmt(best['objective'])} "
                  f"({best['dir']}).", ""]
        base = report.get("baseline")
        head = ["split", "clip", "best"] + (["preset"] if base else [])
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for clip, v in best["clips"].items():
            lines.append("| " + " | ".join(["train", clip, _fmt(v)]
                                          + (["–"] if base else [])) + " |")
        ho = report.get("heldout")
        if ho:
            for clip, v in ho["clips"].items():
                row = ["held-out", clip, _fmt(v)]
                if base:
                    row.append(_fmt(base["clips"].get(clip)))
                lines.append("| " + " | ".join(row) + " |")
            row = ["held-out", "**mean**", f"**{_fmt(ho['mean'])}**"]
            if base:
                row.append(f"**{_fmt(base['mean'])}**")
            lines.append("| " + " | ".join(row) + " |")
        if base:
            lines += ["", "preset: the same settings with the tuned ones left at the "
                          "preset's values."]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _with_tune_settings(args: list[str]) -> list[str]:
    """``args`` with ``+tune=default`` before the first override (Hydra parses the overrides as
    one run of positional arguments; first, so that an experiment file given later can set
    ``tune.*``), unless a ``tune`` option is chosen already (``tune=X`` becomes ``+tune=X``:
    the group is not in ``torchmocap-track``'s defaults)."""
    if any(a.lstrip("+~").split("=", 1)[0] == "tune" for a in args):
        return ["+" + a if a.startswith("tune=") else a for a in args]
    for i, a in enumerate(args):
        if not a.startswith("-") and ("=" in a or a.startswith("~")):
            return [*args[:i], "+tune=default", *args[i:]]
    return [*args, "+tune=default"]


def main() -> None:
    """Console entry point (exit status 2 when a run, or any job of a sweep, failed)."""
    console_main(_hydra_main, argv=_with_tune_settings)


if __name__ == "__main__":
    main()
