"""What the Hydra commands share: sequences from the ``data`` node, run fingerprints, atomic
JSON, failure records and the sweep status.

* A run's **fingerprint** hashes its resolved config (without ``progress``), the package's code
  and configs, and the content of every file the ``data`` node names. A run directory whose
  ``metrics.json`` carries the same fingerprint is complete and up to date: rerunning the same
  sweep into the same directory skips it, and a changed setting, data file or code reruns it.
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
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

__all__ = [
    "USER_ERRORS",
    "RunLockError",
    "SweepStatus",
    "acquire_lock",
    "release_lock",
    "code_fingerprint",
    "config_fingerprint",
    "console_main",
    "hydra_task",
    "is_multirun",
    "load_sequence",
    "read_json",
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
    """SHA-256 of the package's Python sources and packaged configs (sorted by path)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.suffix in (".py", ".yaml") and "__pycache__" not in p.parts:
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def _file_hashes(node) -> dict[str, str]:
    """Content hashes of the existing files a config node names (clips, scenario YAMLs)."""
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
    """Fingerprint of a run: resolved config (minus ``exclude`` keys and ``hydra``), the code,
    and the content of the data files the config names. ``threads`` is left out: how many
    cores a run used says nothing about what it computed."""
    from omegaconf import OmegaConf

    c = OmegaConf.to_container(cfg, resolve=True)
    for k in exclude + ("hydra",):
        c.pop(k, None)
    blob = json.dumps({"config": c, "code": code_fingerprint(),
                       "files": _file_hashes(c.get("data", {}))}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def load_sequence(cfg, min_frames: int = 2):
    """Build the ``data`` node (a sequence source with ``_target_``; its ``seed`` defaults to
    the run's, and ``evaluation.heldout_camera`` is passed to a source that holds one out).
    With ``sequence_cache: <dir>`` in the config, the sequence is saved under
    ``<dir>/<fingerprint of the data node, the code and the data files>`` and read back by later
    runs with the same data settings (e.g. every tracker and seed of a sweep)."""
    from hydra.utils import get_object
    from omegaconf import OmegaConf

    from torchmocap.assembly import _accepts, build

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
    cache = cfg.get("sequence_cache")
    key = None
    if cache:
        from torchmocap.data import Sequence, SequenceFormatError

        node = OmegaConf.to_container(cfg.data, resolve=True)
        blob = json.dumps({"data": node, "extra": extra, "code": code_fingerprint(),
                           "files": _file_hashes(node)}, sort_keys=True, default=str)
        key = Path(str(cache)).expanduser() / hashlib.sha256(blob.encode()).hexdigest()[:16]
        if (key / "manifest.json").is_file():
            try:
                return Sequence.load(key)
            except (SequenceFormatError, OSError, ValueError):
                pass  # unreadable: rebuild and replace it
    seq = build(cfg.data, None, _path="data", **extra)
    if key is not None:
        try:
            seq.save(key, overwrite=True)
        except OSError:  # another job of the sweep is writing the same entry
            pass
    return seq


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


def hydra_task(command: str, failed: Any = None, fingerprint=None):
    """Decorator of a Hydra command's body ``fn(cfg, out) -> value`` (``out``: the job's
    directory) giving it the commands' error contract.

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
