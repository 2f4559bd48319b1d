"""What the Hydra commands share: sequences from the ``data`` node, run fingerprints, atomic
JSON, failure records and the sweep status.

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
import tempfile
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

__all__ = [
    "USER_ERRORS",
    "RunLockError",
    "SweepStatus",
    "acquire_lock",
    "check_added_settings",
    "release_lock",
    "code_fingerprint",
    "completed_run",
    "config_fingerprint",
    "console_main",
    "hydra_task",
    "is_multirun",
    "load_sequence",
    "read_json",
    "reported_warnings",
    "run_fingerprint",
    "sequence_cache_dir",
    "write_failure",
    "write_json_atomic",
]

FAILURE_FILE = "failure.json"
LOCK_FILE = ".torchmocap.lock"
_failures: list[str] = []  # this process's sweep failures (filled by SweepStatus)


def write_json_atomic(obj: Any, path: Path) -> None:
    """Write JSON to ``path`` through a temporary file and a rename (mode 0644)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(obj, f, indent=2, allow_nan=False, default=_json_default)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _json_default(x):
    import math

    import torch

    if isinstance(x, torch.Tensor):
        x = x.tolist()
        return x
    if isinstance(x, float) and not math.isfinite(x):
        return None
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def read_json(path: Path) -> Any | None:
    """JSON content of ``path``, or None when it is missing or unreadable."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """SHA-256 of the package's files — Python sources, packaged configs and bundled assets
    (the default clip, body mesh and learned weights) — sorted by path."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _file_hashes(node) -> dict[str, str]:
    """Content hashes of the existing files a config node names (clips, scenario YAMLs,
    weights)."""
    from omegaconf import OmegaConf

    out: dict[str, str] = {}

    def visit(v):
        if isinstance(v, dict):
            for x in v.values():
                visit(x)
        elif isinstance(v, list):
            for x in v:
                visit(x)
        elif isinstance(v, str) and len(v) < 4096:
            p = Path(v).expanduser()
            if p.is_file():
                out[v] = hashlib.sha256(p.read_bytes()).hexdigest()[:16]

    visit(OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node)
    return out


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
    named = {k: _file_hashes(c.get(k, {})) for k in ("data", "tracker")}
    blob = json.dumps({"config": c, "code": code_fingerprint(), "files": named},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def run_fingerprint(settings: str, inputs: dict[str, str] | None) -> str:
    """The fingerprint of a run: its settings' fingerprint (:func:`config_fingerprint`) and
    the digests of the input files its data source read (``Sequence.meta["inputs"]``)."""
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


def sequence_cache_dir(cfg) -> Path | None:
    """The ``sequence_cache`` directory (created when missing), or None when unset.

    Raises:
        NotADirectoryError: the setting names an existing file, or a directory that cannot be
            created or written.
    """
    cache = cfg.get("sequence_cache")
    if not cache:
        return None
    d = Path(str(cache)).expanduser()
    if d.exists() and not d.is_dir():
        raise NotADirectoryError(f"sequence_cache: {d} is a file; expected a directory (or "
                                 "null: no cache)")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise NotADirectoryError(f"sequence_cache: cannot create the directory {d} "
                                 f"({e.strerror or e})") from None
    if not os.access(d, os.W_OK | os.X_OK):
        raise NotADirectoryError(f"sequence_cache: the directory {d} is not writable")
    return d


def load_sequence(cfg, min_frames: int = 2):
    """Build the ``data`` node (a sequence source with ``_target_``; its ``seed`` defaults to
    the run's, and ``evaluation.heldout_camera`` is passed to a source that holds one out),
    noting every file it reads: ``meta["inputs"]`` holds their digests
    (:mod:`torchmocap.inputs`).

    With ``sequence_cache: <dir>`` in the config, the sequence is saved under
    ``<dir>/<fingerprint of the data node, the code and the files it names>`` and read back by
    later runs with the same data settings (e.g. every tracker and seed of a sweep) while the
    input files it was built from are unchanged; otherwise it is rebuilt and replaced. A cache
    entry that cannot be written is reported with a warning (the run goes on uncached)."""
    import warnings

    from hydra.utils import get_object
    from omegaconf import OmegaConf

    from torchmocap.assembly import _accepts, build
    from torchmocap.inputs import changed_inputs, input_log

    extra = {}
    fn = get_object(cfg.data._target_)
    if "seed" not in cfg.data and _accepts(fn, "seed")[0]:
        extra["seed"] = int(cfg.seed)
    if _accepts(fn, "min_frames")[0]:
        extra["min_frames"] = min_frames
    held = (cfg.get("evaluation") or {}).get("heldout_camera")
    if held is not None:
        if not _accepts(fn, "heldout_camera")[0]:
            raise ValueError(f"evaluation.heldout_camera: the data source {cfg.data._target_} "
                             "cannot hold a camera out (a recording can: data=recording)")
        extra["heldout_camera"] = held
    cache = sequence_cache_dir(cfg)
    key = None
    if cache is not None:
        from torchmocap.data import Sequence, SequenceFormatError

        node = OmegaConf.to_container(cfg.data, resolve=True)
        blob = json.dumps({"data": node, "extra": extra, "code": code_fingerprint(),
                           "files": _file_hashes(node)}, sort_keys=True, default=str)
        key = cache / hashlib.sha256(blob.encode()).hexdigest()[:16]
        if (key / "manifest.json").is_file():
            try:
                seq = Sequence.load(key)
            except (SequenceFormatError, OSError, ValueError):
                seq = None  # unreadable: rebuild and replace it
            inputs = None if seq is None else seq.meta.get("inputs")
            if isinstance(inputs, dict) and not changed_inputs(inputs):
                return seq
    with input_log() as log:
        seq = build(cfg.data, None, _path="data", **extra)
    seq.meta["inputs"] = log.digests()
    if key is not None:
        try:
            seq.save(key, overwrite=True)
        except OSError as e:
            if not (key / "manifest.json").is_file():  # not another job's entry of the sweep
                warnings.warn(f"sequence_cache: cannot write {key} ({e.strerror or e}); the "
                              "sequence is not cached", stacklevel=2)
    return seq


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
    def _guard(directory: str) -> None:
        try:
            acquire_lock(Path(directory))
        except RunLockError as e:
            print(f"torchmocap: error: {e}", file=sys.stderr)
            sys.exit(2)

    def on_run_start(self, config, **kwargs) -> None:
        self._guard(str(config.hydra.run.dir))

    def on_run_end(self, config, **kwargs) -> None:
        release_lock(Path(str(config.hydra.run.dir)))

    def on_multirun_start(self, config, **kwargs) -> None:
        self._start = time.time() - 1.0
        _failures.clear()
        self._guard(str(config.hydra.sweep.dir))

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


def console_main(hydra_main, argv=None) -> None:
    """Run a Hydra main as a console command: the repository's ``conf/`` search-path warning
    silenced (it exists only in a checkout), ``argv`` (a function of ``sys.argv[1:]``) applied
    first, and exit status 2 when any job of a sweep failed."""
    import warnings

    warnings.filterwarnings("ignore", message=r".*provider=hydra\.searchpath in main.*")
    if argv is not None:
        sys.argv[1:] = argv(sys.argv[1:])
    hydra_main()
    if sweep_failed():
        sys.exit(2)
