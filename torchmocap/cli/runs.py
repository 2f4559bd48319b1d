"""What the Hydra commands share: run fingerprints, failure records and the sweep status (the
sequence of the ``data`` node is built by :func:`torchmocap.assembly.load_sequence`).

* A run's **fingerprint** hashes its resolved config (without ``progress``), the package's code,
  configs and bundled assets, the content of every file the ``data`` and ``tracker`` nodes name,
  and the content of every input file its data source read (:mod:`torchmocap.inputs`: the ASF
  beside an AMC, a scenario's ``base:`` chain, every video, image, mask and keypoint file of a
  recording, and the listings of the folders searched for them). ``metrics.json`` records those
  inputs with their digests; a run directory whose ``metrics.json`` has the fingerprint that
  this config and the recorded inputs give now is complete and up to date
  (:func:`completed_run`): rerunning the same sweep into the same directory skips it, and a
  changed setting, input file or code reruns it. ``docs/reliability.md`` has the details.
* A failing job writes ``failure.json`` (the error and its traceback) into its own directory,
  prints one line on stderr and — in a multirun — lets the sweep go on;
  :class:`SweepStatus` (a Hydra callback) counts this sweep's failures at its end, and the
  command exits with status 2 when any job failed. :func:`hydra_task` gives every Hydra
  command that contract and :func:`console_main` its entry point.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import sys
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from torchmocap.atomic import write_json_atomic
from torchmocap.inputs import code_fingerprint, named_file_digests

__all__ = [
    "USER_ERRORS",
    "RunLockError",
    "SweepStatus",
    "acquire_lock",
    "check_added_settings",
    "check_sweep_choices",
    "release_lock",
    "completed_run",
    "config_fingerprint",
    "console_main",
    "hydra_task",
    "is_multirun",
    "read_json",
    "reported_warnings",
    "run_fingerprint",
    "sweep_overrides",
    "write_failure",
]

FAILURE_FILE = "failure.json"
LOCK_FILE = ".torchmocap.lock"
_failures: list[str] = []  # this process's sweep failures (filled by SweepStatus)


def read_json(path: Path) -> Any | None:
    """JSON content of ``path``, or None when it is missing or unreadable."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def config_fingerprint(cfg, exclude: tuple[str, ...] = ("progress", "threads")) -> str:
    """Fingerprint of a run's settings: resolved config (minus ``exclude`` keys and
    ``hydra``), the code, and the content of the files the ``data`` and ``tracker`` nodes
    name. ``threads`` is left out: how many cores a run used says nothing about what it
    computed. The files a data source finds and reads by itself join it in
    :func:`run_fingerprint`."""
    from omegaconf import OmegaConf

    c = OmegaConf.to_container(cfg, resolve=True)
    for k in exclude + ("hydra",):
        c.pop(k, None)
    named = {k: named_file_digests(c.get(k, {})) for k in ("data", "tracker")}
    blob = json.dumps({"config": c, "code": code_fingerprint(), "files": named},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def run_fingerprint(settings: str, inputs: dict[str, str] | None) -> str:
    """The fingerprint of a run: its settings' fingerprint (:func:`config_fingerprint`) and
    the digests of the input files its data source read (``Sequence.meta.inputs``)."""
    blob = json.dumps({"settings": settings, "inputs": inputs or {}}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def completed_run(out: Path, settings: str) -> dict | None:
    """``out/metrics.json`` when the run there is complete and up to date: written with the
    settings fingerprint ``settings`` and input files whose content is unchanged (the digests
    of the files it recorded in ``inputs`` are taken again); None otherwise."""
    from torchmocap.inputs import file_digest

    done = read_json(Path(out) / "metrics.json")
    if not isinstance(done, dict) or not isinstance(done.get("inputs"), dict):
        return None
    now = {p: file_digest(p) for p in done["inputs"]}
    return done if done.get("fingerprint") == run_fingerprint(settings, now) else None


@contextmanager
def reported_warnings(command: str) -> Iterator[list[str]]:
    """Show each warning (a ``UserWarning``: a sanity check, a guessed unit) raised inside the
    block once, when it is raised, as one line ``<command>: warning: <message>`` on stderr, and
    collect the messages (for the run's ``metrics.json``); other categories are shown as
    usual."""
    import warnings

    seen: list[str] = []
    with warnings.catch_warnings():
        shown = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if not issubclass(category, UserWarning):
                return shown(message, category, filename, lineno, file, line)
            text = " ".join(str(message).split())
            if text not in seen:
                seen.append(text)
                print(f"{command}: warning: {text}", file=sys.stderr)

        warnings.showwarning = show
        yield seen


def write_failure(out: Path, error: BaseException, fingerprint: str | None, command: str) -> str:
    """Write ``out/failure.json`` for ``error``; returns the one-line message."""
    msg = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)
    line = (msg.strip().splitlines() or [type(error).__name__])[0]
    record = {"command": command, "error": line, "type": type(error).__name__,
              "fingerprint": fingerprint, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
              "traceback": traceback.format_exception(type(error), error, error.__traceback__)}
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(record, out / FAILURE_FILE)
    except OSError:
        pass
    return line


class RunLockError(RuntimeError):
    """Another live process is writing into the same run or sweep directory."""


def acquire_lock(directory: Path) -> Path:
    """Create ``directory/.torchmocap.lock`` holding this process's id; refuse when another
    live process holds it (a lock left by a dead process is taken over)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    lock = directory / LOCK_FILE
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _alive(pid):
                raise RunLockError(f"{directory} is in use by process {pid}; choose another "
                                   "run directory or wait for it to finish") from None
            lock.unlink(missing_ok=True)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        return lock
    raise RunLockError(f"{directory}: cannot take the lock {lock}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def release_lock(directory: Path) -> None:
    lock = Path(directory) / LOCK_FILE
    try:
        if int(lock.read_text().strip() or 0) == os.getpid():
            lock.unlink()
    except (OSError, ValueError):
        pass


class SweepStatus(Callback):
    """Hydra callback: guards run and sweep directories with a lock (two processes never mix
    their records in one directory: the second is refused before Hydra writes anything), and at
    the end of a multirun counts the jobs of *this* sweep that wrote a ``failure.json`` and
    reports them; the command then exits with status 2."""

    def __init__(self) -> None:
        self._start = time.time()

    @staticmethod
    def _guard(directory: str, setting: str) -> None:
        try:
            acquire_lock(Path(directory))
        except RunLockError as e:
            print(f"torchmocap: error: {e}", file=sys.stderr)
            sys.exit(2)
        except OSError as e:  # before Hydra's log file fails on it with a long traceback
            why = e.strerror or type(e).__name__
            where = f": {e.filename}" if e.filename and str(e.filename) != directory else ""
            print(f"torchmocap: error: {setting}: cannot write the directory {directory} "
                  f"({why}{where}); choose a writable one", file=sys.stderr)
            sys.exit(2)

    def on_run_start(self, config, **kwargs) -> None:
        self._guard(str(config.hydra.run.dir), "hydra.run.dir")

    def on_run_end(self, config, **kwargs) -> None:
        release_lock(Path(str(config.hydra.run.dir)))

    def on_multirun_start(self, config, **kwargs) -> None:
        self._start = time.time() - 1.0
        _failures.clear()
        check_sweep_choices(config)
        self._guard(str(config.hydra.sweep.dir), "hydra.sweep.dir")

    def on_multirun_end(self, config, **kwargs) -> None:
        release_lock(Path(str(config.hydra.sweep.dir)))
        root = Path(str(config.hydra.sweep.dir))
        failed = sorted(str(p.parent) for p in root.rglob(FAILURE_FILE)
                        if p.stat().st_mtime >= self._start)
        _failures[:] = failed
        if failed:
            print(f"{len(failed)} job(s) of the sweep failed (see failure.json in each):",
                  file=sys.stderr)
            for f in failed:
                rec = read_json(Path(f) / FAILURE_FILE) or {}
                print(f"  {f}: {rec.get('error', '?')}", file=sys.stderr)


def sweep_failed() -> bool:
    """Whether the multirun that just ended in this process had a failing job."""
    return bool(_failures)


#: exception types that are a setting or the data, not a bug: one line on stderr, no traceback
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, LookupError, OSError, TypeError)


def is_multirun() -> bool:
    """Whether this process runs a job of a Hydra multirun."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def check_added_settings(cfg, command: str) -> None:
    """Refuse a setting added on the command line with ``+`` that the command does not read.

    ``+overlay=5`` (a typo of ``overlays``) would otherwise add a key nothing reads, and the
    run would silently ignore it. A key under a component (a node with ``_target_``:
    ``+tracker.foo``, ``+data.scenario_overrides.<key>``) is left to the component, which
    checks its own arguments; config groups chosen with ``+`` (``+experiment=...``,
    ``+tune=default``) are choices, not settings. Does nothing outside a Hydra run.

    Raises:
        KeyError: naming the key, with the closest existing setting when there is one.
    """
    import difflib

    from hydra.core.hydra_config import HydraConfig
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import DictConfig, OmegaConf

    if not HydraConfig.initialized():
        return
    hc = HydraConfig.get()
    choices = set(hc.runtime.choices)
    for o in OverridesParser.create().parse_overrides([str(x) for x in hc.overrides.task]):
        key = o.key_or_group
        if not o.is_add() or key in choices or f"{key}@{o.package}" in choices or \
                key.split(".")[0] == "hydra":
            continue
        parts = key.split(".")
        parents = [OmegaConf.select(cfg, ".".join(parts[:i])) for i in range(1, len(parts))]
        if any(isinstance(n, DictConfig) and "_target_" in n for n in parents):
            continue  # a component's argument: it checks its own
        siblings = parents[-1] if parents else cfg
        known = [k for k in siblings if k != parts[-1]] if isinstance(siblings, DictConfig) \
            else []
        near = difflib.get_close_matches(parts[-1], known, n=1)
        hint = f" (did you mean {'.'.join([*parts[:-1], near[0]])}?)" if near else ""
        raise KeyError(f"{key}: not a setting of {command}{hint}; an added key (+{key}) that "
                       "nothing reads would be ignored")


def hydra_task(command: str, failed: Any = None, fingerprint=None):
    """Decorator of a Hydra command's body ``fn(cfg, out) -> value`` (``out``: the job's
    directory) giving it the commands' error contract (and refusing added settings that the
    command does not read, :func:`check_added_settings`).

    A raised error writes ``out/failure.json`` (the error, its traceback and, when
    ``fingerprint(cfg)`` is given, the run's fingerprint) and prints
    ``<command>: error: <one line>`` on stderr; then a single run exits with status 2 and a job
    of a multirun returns ``failed`` (or ``failed(cfg)`` when callable: e.g. the worst value
    for a sweeper) so that the sweep goes on. An error that is not one of :data:`USER_ERRORS`
    in a single run is a bug: it is re-raised with its traceback (after the record is
    written)."""

    def decorate(fn):
        @functools.wraps(fn)
        def task(cfg):
            from hydra.core.hydra_config import HydraConfig

            out = Path(HydraConfig.get().runtime.output_dir)
            multirun = is_multirun()
            try:
                check_added_settings(cfg, command)
                return fn(cfg, out)
            except Exception as e:
                fp = None
                if fingerprint is not None:
                    try:
                        fp = fingerprint(cfg)
                    except Exception:
                        fp = None
                line = write_failure(out, e, fp, command)
                if not isinstance(e, USER_ERRORS) and not multirun:
                    raise  # a bug: show the traceback
                print(f"{command}: error: {line}", file=sys.stderr)
                if multirun:
                    return failed(cfg) if callable(failed) else failed
                sys.exit(2)

        return task

    return decorate


#: Hydra flags followed by a value (not an override)
_VALUE_FLAGS = ("-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir", "-p",
                "--package", "--info", "-i", "--experimental-rerun", "-sc",
                "--shell-completion")


def sweep_overrides(args: list[str]) -> list[str]:
    """A multirun's command line with its settings deferred to the jobs.

    Hydra composes a multirun's base config (the one its sweep directory and launcher come
    from) without the sweeps: with the default of a swept group. A setting valid for every
    swept preset but not for the default (``-m tracker=p,g tracker.inference.layers=3``: the
    default LS has no annealing layers) would then fail there, before any job. Written as a
    one-value sweep (``tracker.inference.layers=choice(3)``) it is left out of the base config
    and set in each job, where a key a preset lacks is still an error of that job. Only
    settings of the form ``key=value`` are deferred, and only when a config group is swept;
    other arguments are returned unchanged.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType

    if not any(a in ("-m", "--multirun") for a in args):
        return list(args)
    parser = OverridesParser.create()
    parsed: list = []
    skip = False
    for a in args:
        if skip or a.startswith("-"):
            skip = not skip and a in _VALUE_FLAGS
            parsed.append(None)
            continue
        try:
            parsed.append(parser.parse_override(a))
        except Exception:
            parsed.append(None)
    groups = _config_groups()
    swept = [o for o in parsed if o is not None and o.is_sweep_override()
             and o.key_or_group.split("@")[0] in groups]
    if not swept:
        return list(args)
    out = []
    for a, o in zip(args, parsed):
        if (o is None or o.is_sweep_override() or o.type != OverrideType.CHANGE
                or o.is_hydra_override() or o.key_or_group.split("@")[0] in groups
                or o.package is not None or "=" not in a):
            out.append(a)
            continue
        value = a.split("=", 1)[1]
        deferred = f"{o.key_or_group}=choice({value})"
        try:
            ok = parser.parse_override(deferred).is_sweep_override() and value != ""
        except Exception:
            ok = False
        out.append(deferred if ok else a)
    return out


def _config_groups() -> set[str]:
    """Names of the config groups of the packaged configs and of the repository's ``conf/``
    (when run from its root)."""
    from importlib import resources

    names = {p.name for p in (resources.files("torchmocap") / "conf").iterdir()
             if p.is_dir() and not p.name.startswith("_")}
    local = Path("conf")
    if local.is_dir():
        names |= {p.name for p in local.iterdir() if p.is_dir()}
    return names


def _group_options(config, group: str) -> set[str] | None:
    """The options of config group ``group`` in every config source of the run
    (``hydra.runtime.config_sources``: the packaged configs, the search path's folders); None
    when a source cannot be listed."""
    from importlib import resources

    found: set[str] = set()
    for src in config.hydra.runtime.config_sources:
        schema, path = str(src.schema), str(src.path)
        try:
            if schema == "file":
                folder = Path(path) / group
            elif schema == "pkg":
                folder = resources.files(path.replace("/", ".")) / group
            else:
                continue
            if folder.is_dir():
                found |= {p.name.rsplit(".", 1)[0] for p in folder.iterdir()
                          if p.name.endswith((".yaml", ".yml"))}
        except (ModuleNotFoundError, OSError, TypeError, ValueError):
            return None
    return found


def check_sweep_choices(config) -> None:
    """Refuse a multirun sweeping a config group over an option that does not exist
    (``tracker=p,nope``) before any job runs, naming it and the group's options."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        overrides = OverridesParser.create().parse_overrides(
            [str(x) for x in config.hydra.overrides.task])
    except Exception:
        return  # Hydra reports it
    for o in overrides:
        group = o.key_or_group.split("@")[0]
        if not o.is_sweep_override() or o.is_hydra_override():
            continue
        options = _group_options(config, group)
        if not options:
            continue  # not a config group (or not listable: Hydra checks it)
        try:
            values = [str(v) for v in o.sweep_string_iterator()]
        except Exception:
            continue  # a range or glob: Hydra checks it
        unknown = [v for v in values if v not in options]
        if unknown:
            print(f"torchmocap: error: {group}={','.join(values)}: no {group} "
                  f"{'option' if len(unknown) == 1 else 'options'} {', '.join(unknown)}; "
                  f"the options are {', '.join(sorted(options))}", file=sys.stderr)
            sys.exit(2)


def console_main(hydra_main, argv=None) -> None:
    """Run a Hydra main as a console command: the repository's ``conf/`` search-path warning
    silenced (it exists only in a checkout), ``argv`` (a function of ``sys.argv[1:]``) applied
    first, then a multirun's settings deferred to its jobs (:func:`sweep_overrides`), and exit
    status 2 when any job of a sweep failed."""
    import warnings

    warnings.filterwarnings("ignore", message=r".*provider=hydra\.searchpath in main.*")
    if argv is not None:
        sys.argv[1:] = argv(sys.argv[1:])
    sys.argv[1:] = sweep_overrides(sys.argv[1:])
    hydra_main()
    if sweep_failed():
        sys.exit(2)
