"""``torchmocap-aggregate MULTIRUN_DIR [--out DIR] [--metric KEY ...] [--over KEY ...]``: one
table and comparison plots from a sweep.

A job is a directory under ``MULTIRUN_DIR`` (at any depth) holding a ``metrics.json``. Its
settings are the overrides in ``.hydra/overrides.yaml`` (``key=value`` lines, as Hydra records
them), found in the job's directory or the nearest parent below ``MULTIRUN_DIR`` (then the
path below that parent is the setting ``part``, e.g. the clips of a ``torchmocap-tune`` trial).
A job without Hydra records (e.g. committed experiment runs that keep only ``metrics.json``) is
named by its path, ``run``, with ``seed<N>`` path parts dropped. Jobs are grouped by the swept
settings (those whose value differs between jobs), pooling the ``--over`` settings (default
``seed``); each metric is reported as ``mean ± std`` over a group's jobs (population std,
``ddof=0``, as :func:`numpy.std`), with the number of jobs that reported it.

Writes ``aggregate.md``, ``aggregate.csv`` and one ``aggregate_<metric>.png`` per metric into
``--out`` (default: ``MULTIRUN_DIR``), each atomically, and prints the markdown table. A metric
is a dotted path into ``metrics.json`` (``orientation_error_deg.mean``,
``proposal_mean.acceptance_rate``); the default is every one of :data:`DEFAULT_METRICS` that some
job reports. A directory without any job, or a metric no job reports: one line on stderr and
exit status 2.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "DEFAULT_METRICS",
    "Job",
    "SweepAggregateError",
    "SweepTable",
    "aggregate",
    "aggregate_sweep",
    "find_jobs",
    "main",
    "metric_value",
    "plot_table",
    "table_csv",
    "table_markdown",
]

#: metrics reported when none is asked for (those that no job has are left out)
DEFAULT_METRICS = (
    "orientation_error_deg.mean",
    "mpjpe_mm.mean",
    "mpjpe_root_relative_mm.mean",
    "marker_error_mm.mean",
    "silhouette_iou.mean",
    "ess_final_mean",
    "seconds_per_frame",
)

_SEED_PART = re.compile(r"^seed\d+$")


class SweepAggregateError(ValueError):
    """A sweep directory or a metric that cannot be aggregated; the message starts with the
    argument at fault (``multirun_dir``, ``metric``, ``over``)."""


@dataclass
class Job:
    """One job of a sweep: its directory, its settings (override key → value, as strings) and
    its ``metrics.json``."""

    path: Path
    settings: dict[str, str]
    metrics: dict[str, Any]


@dataclass
class SweepTable:
    """Grouped statistics of a sweep.

    Attributes:
        columns: the swept settings (one column each), in first-seen order.
        metrics: the metrics (dotted paths).
        rows: per group: ``{"settings": {column: value}, "jobs": n, "over": {key: [values]},
            "stats": {metric: (mean, std, count)}}`` (``nan`` where no job of the group has it).
        fixed: the settings every job shares.
        failed: directories of failed jobs (``failure.json`` and no ``metrics.json``).
    """

    columns: list[str]
    metrics: list[str]
    rows: list[dict[str, Any]]
    fixed: dict[str, str] = field(default_factory=dict)
    failed: list[Path] = field(default_factory=list)


def _parse_overrides(lines: Any, where: Path) -> dict[str, str]:
    if lines is None:
        return {}
    if not isinstance(lines, list):
        raise SweepAggregateError(f"multirun_dir: {where} is not a list of overrides")
    out: dict[str, str] = {}
    for line in lines:
        key, sep, value = str(line).partition("=")
        if not sep:
            continue
        out[key.lstrip("+~")] = value
    return out


def _read_overrides(path: Path) -> dict[str, str]:
    import yaml

    try:
        return _parse_overrides(yaml.safe_load(path.read_text(encoding="utf-8")), path)
    except (OSError, yaml.YAMLError) as e:
        raise SweepAggregateError(f"multirun_dir: cannot read {path}: {e}") from e


def find_jobs(multirun_dir: str | Path) -> tuple[list[Job], list[Path]]:
    """The jobs (directories with a ``metrics.json``) and the failed jobs (``failure.json``
    without ``metrics.json``) under ``multirun_dir``, sorted by path.

    Raises:
        SweepAggregateError: ``multirun_dir`` is not a directory, holds no job, or a
            ``metrics.json`` is unreadable.
    """
    root = Path(multirun_dir).expanduser()
    if not root.is_dir():
        what = "does not exist" if not root.exists() else "is not a directory"
        raise SweepAggregateError(f"multirun_dir: {root} {what}")
    jobs: list[Job] = []
    for mpath in sorted(root.rglob("metrics.json")):
        d = mpath.parent
        if ".hydra" in d.relative_to(root).parts:
            continue
        try:
            metrics = json.loads(mpath.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise SweepAggregateError(f"multirun_dir: unreadable {mpath}: {e}") from e
        if not isinstance(metrics, dict):
            raise SweepAggregateError(f"multirun_dir: {mpath} is not a JSON object")
        settings: dict[str, str] | None = None
        for anc in [d, *d.parents]:
            if anc != root and root not in anc.parents:
                break
            ov = anc / ".hydra" / "overrides.yaml"
            if ov.is_file():
                settings = _read_overrides(ov)
                if anc != d:
                    settings["part"] = d.relative_to(anc).as_posix()
                break
        if settings is None:
            parts = [p for p in d.relative_to(root).parts if not _SEED_PART.match(p)]
            settings = {"run": "/".join(parts) or "."}
        if "seed" not in settings and isinstance(metrics.get("seed"), int):
            settings["seed"] = str(metrics["seed"])
        jobs.append(Job(d, settings, metrics))
    done = {j.path for j in jobs}
    failed = sorted(p.parent for p in root.rglob("failure.json") if p.parent not in done)
    if not jobs:
        raise SweepAggregateError(
            f"multirun_dir: no job with a metrics.json under {root}"
            + (f" ({len(failed)} failed job(s) with failure.json)" if failed else
               " (is it the directory of a torchmocap-track -m sweep?)"))
    return jobs, failed


def metric_value(metrics: dict, key: str) -> float | None:
    """The number at dotted path ``key`` of a metrics dict, or None (missing, not a number)."""
    v: Any = metrics
    for part in key.split("."):
        if not isinstance(v, dict) or part not in v:
            return None
        v = v[part]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v)


def _numeric_keys(metrics: dict, prefix: str = "", depth: int = 2) -> list[str]:
    out = []
    for k, v in metrics.items():
        if isinstance(v, dict) and depth > 0:
            out += _numeric_keys(v, f"{prefix}{k}.", depth - 1)
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out.append(f"{prefix}{k}")
    return out


def _sort_key(value: str) -> tuple:
    try:
        return (0, float(value), value)
    except ValueError:
        return (1, 0.0, value)


def aggregate(jobs: Sequence[Job], metrics: Sequence[str] | None = None,
              over: Sequence[str] = ("seed",), failed: Sequence[Path] = ()) -> SweepTable:
    """Group ``jobs`` by their swept settings (pooling the ``over`` settings) and reduce each
    metric to ``(mean, std, count)`` per group (:func:`numpy.mean`, :func:`numpy.std`).

    Raises:
        SweepAggregateError: no jobs (``multirun_dir``), a metric no job reports (``metric``).
    """
    import numpy as np

    if not jobs:
        raise SweepAggregateError("multirun_dir: no jobs to aggregate")
    if metrics is None:
        metrics = [m for m in DEFAULT_METRICS
                   if any(metric_value(j.metrics, m) is not None for j in jobs)]
    else:
        metrics = list(metrics)
        for m in metrics:
            if not any(metric_value(j.metrics, m) is not None for j in jobs):
                avail = sorted({k for j in jobs for k in _numeric_keys(j.metrics)})
                raise SweepAggregateError(f"metric: {m!r} is a number in no job's metrics.json "
                                          f"(available: {', '.join(avail)})")
    keys: list[str] = []
    for j in jobs:
        keys += [k for k in j.settings if k not in keys]
    over = list(over)
    values = {k: {j.settings.get(k, "") for j in jobs} for k in keys}
    columns = [k for k in keys if k not in over and len(values[k]) > 1]
    fixed = {k: next(iter(values[k])) for k in keys if k not in over and len(values[k]) == 1}
    groups: dict[tuple, list[Job]] = {}
    for j in jobs:
        groups.setdefault(tuple(j.settings.get(k, "") for k in columns), []).append(j)
    rows = []
    for gkey in sorted(groups, key=lambda g: tuple(_sort_key(v) for v in g)):
        members = groups[gkey]
        stats = {}
        for m in metrics:
            v = np.array([x for x in (metric_value(j.metrics, m) for j in members)
                          if x is not None], dtype=np.float64)
            stats[m] = ((float(np.mean(v)), float(np.std(v)), int(v.size)) if v.size else
                        (math.nan, math.nan, 0))
        rows.append({"settings": dict(zip(columns, gkey)), "jobs": len(members),
                     "over": {k: sorted({j.settings[k] for j in members if k in j.settings},
                                        key=_sort_key) for k in over},
                     "stats": stats})
    return SweepTable(columns, list(metrics), rows, fixed, list(failed))


def _fmt(x: float) -> str:
    return "–" if not math.isfinite(x) else f"{x:.4g}"


def table_markdown(table: SweepTable, title: str = "") -> str:
    """The table as markdown: the fixed settings, then one row per group with
    ``mean ± std (n)`` per metric."""
    lines = [f"# {title}" if title else "# Sweep", ""]
    njobs = sum(r["jobs"] for r in table.rows)
    lines.append(f"{njobs} job(s) in {len(table.rows)} group(s)"
                 + (f", {len(table.failed)} failed" if table.failed else "")
                 + "; cells: mean ± std over "
                 + (", ".join(k for k in table.rows[0]["over"]) or "jobs")
                 + " (population std), (n) the jobs that report the metric.")
    if table.fixed:
        lines += ["", "Fixed: " + ", ".join(f"`{k}={v}`" for k, v in table.fixed.items())]
    head = [*table.columns, "jobs", *table.metrics]
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table.rows:
        cells = [r["settings"][k] for k in table.columns] + [str(r["jobs"])]
        for m in table.metrics:
            mean, std, n = r["stats"][m]
            cells.append("–" if n == 0 else f"{_fmt(mean)} ± {_fmt(std)} ({n})")
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    if table.failed:
        lines += ["", "Failed jobs (failure.json): " + ", ".join(str(p) for p in table.failed)]
    return "\n".join(lines) + "\n"


def table_csv(table: SweepTable) -> str:
    """The table as CSV: the swept settings, ``jobs``, the pooled values of each ``over``
    setting (``;``-separated), then ``<metric>_mean``, ``<metric>_std``, ``<metric>_n``."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    over = list(table.rows[0]["over"]) if table.rows else []
    w.writerow([*table.columns, "jobs", *over,
                *[f"{m}_{s}" for m in table.metrics for s in ("mean", "std", "n")]])
    for r in table.rows:
        row: list[Any] = [r["settings"][k] for k in table.columns] + [r["jobs"]]
        row += [";".join(r["over"][k]) for k in over]
        for m in table.metrics:
            mean, std, n = r["stats"][m]
            row += ["" if n == 0 else repr(mean), "" if n == 0 else repr(std), n]
        w.writerow(row)
    return buf.getvalue()


def _is_numeric(vals: Sequence[str]) -> bool:
    try:
        [float(v) for v in vals]
    except ValueError:
        return False
    return True


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def plot_table(table: SweepTable, out: str | Path, prefix: str = "aggregate") -> list[Path]:
    """One PNG per metric, ``<out>/<prefix>_<metric>.png``: lines over the swept setting when
    exactly one is numeric (one line per combination of the others), else bars per group;
    error bars are the std. Returns the written paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchmocap.atomic import atomic_path

    out = Path(out)
    numeric = [k for k in table.columns
               if _is_numeric([r["settings"][k] for r in table.rows])
               and len({r["settings"][k] for r in table.rows}) > 1]
    paths = []
    for m in table.metrics:
        if len(numeric) == 1:
            x_key = numeric[0]
            others = [k for k in table.columns if k != x_key]
            fig, ax = plt.subplots(figsize=(6.4, 4.0))
            lines: dict[tuple, list] = {}
            for r in table.rows:
                lines.setdefault(tuple(r["settings"][k] for k in others), []).append(r)
            xs_all = []
            for lkey, rs in lines.items():
                rs = sorted(rs, key=lambda r: float(r["settings"][x_key]))
                xs = [float(r["settings"][x_key]) for r in rs]
                xs_all += xs
                ys = [r["stats"][m][0] for r in rs]
                es = [r["stats"][m][1] for r in rs]
                label = ", ".join(f"{k}={v}" for k, v in zip(others, lkey)) or m
                ax.errorbar(xs, ys, yerr=es, marker="o", capsize=3, label=label)
            if min(xs_all) > 0 and max(xs_all) / min(xs_all) > 20:
                ax.set_xscale("log")
            ax.set_xlabel(x_key)
            if len(lines) > 1:
                ax.legend(fontsize=7)
        else:
            labels = [", ".join(f"{k}={r['settings'][k]}" for k in table.columns) or "all"
                      for r in table.rows]
            fig, ax = plt.subplots(figsize=(6.4, max(2.0, 0.35 * len(labels) + 1.2)))
            ys = [r["stats"][m][0] for r in table.rows]
            es = [r["stats"][m][1] for r in table.rows]
            ax.barh(range(len(labels)), ys, xerr=es, capsize=3, color="tab:blue", alpha=0.8)
            ax.set_yticks(range(len(labels)), labels, fontsize=7)
            ax.invert_yaxis()
        (ax.set_ylabel if len(numeric) == 1 else ax.set_xlabel)(m)
        ax.set_title(f"{m}: mean ± std", fontsize=9)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        path = out / f"{prefix}_{_safe(m)}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=100, format="png")
        plt.close(fig)
        paths.append(path)
    return paths


def aggregate_sweep(multirun_dir: str | Path, out: str | Path | None = None,
                    metrics: Sequence[str] | None = None, over: Sequence[str] = ("seed",),
                    plots: bool = True) -> dict[str, Any]:
    """Aggregate a sweep directory and write ``aggregate.md``, ``aggregate.csv`` and the plots
    into ``out`` (default ``multirun_dir``). Returns ``{"table", "markdown", "csv", "plots"}``
    (the table and the written paths).

    Raises:
        SweepAggregateError: see :func:`find_jobs` and :func:`aggregate`.
    """
    from torchmocap.atomic import atomic_path

    if isinstance(over, str) or any(not isinstance(k, str) or not k for k in over):
        raise SweepAggregateError(f"over: expected a list of setting names, got {over!r}")
    jobs, failed = find_jobs(multirun_dir)
    table = aggregate(jobs, metrics, over, failed)
    given = out is not None
    out = Path(multirun_dir if out is None else out).expanduser()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        where = "--out" if given else "multirun_dir"
        what = "a file, not a directory" if out.exists() and not out.is_dir() else \
            (e.strerror or str(e))
        raise SweepAggregateError(f"{where}: cannot write the tables into {out} ({what})"
                                  ) from None
    md = table_markdown(table, title=f"Sweep {Path(multirun_dir).name}")
    written: dict[str, Any] = {"table": table}
    for name, text in (("markdown", md), ("csv", table_csv(table))):
        path = out / f"aggregate.{'md' if name == 'markdown' else 'csv'}"
        with atomic_path(path) as tmp:
            tmp.write_text(text, encoding="utf-8")
        written[name] = path
    written["plots"] = plot_table(table, out) if plots else []
    return written


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit status (0 ok, 2 nothing to aggregate)."""
    parser = argparse.ArgumentParser(
        prog="torchmocap-aggregate",
        description="One table (markdown + CSV) and comparison plots from a torchmocap-track "
                    "multirun directory, grouped by the swept overrides (mean ± std over "
                    "seeds).")
    parser.add_argument("multirun_dir", help="sweep directory (e.g. multirun/track/<date>/"
                                             "<time>); jobs are found at any depth")
    parser.add_argument("--out", default=None, help="output directory (default: multirun_dir)")
    parser.add_argument("--metric", action="append", default=None, metavar="KEY",
                        help="dotted path into metrics.json, repeatable (default: "
                             + ", ".join(DEFAULT_METRICS) + ", those present)")
    parser.add_argument("--over", action="append", default=None, metavar="KEY",
                        help="setting pooled into mean ± std, repeatable (default: seed)")
    parser.add_argument("--no-plots", action="store_true", help="write the tables only")
    args = parser.parse_args(argv)
    try:
        res = aggregate_sweep(args.multirun_dir, args.out, args.metric,
                              args.over if args.over else ("seed",), plots=not args.no_plots)
    except (SweepAggregateError, OSError) as e:
        print(f"torchmocap-aggregate: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    try:
        print(res["markdown"].read_text(encoding="utf-8"), end="")
        print(f"wrote {res['markdown']}, {res['csv']}"
              + (f" and {len(res['plots'])} plot(s)" if res["plots"] else ""), file=sys.stderr)
    except BrokenPipeError:
        sys.stderr.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
