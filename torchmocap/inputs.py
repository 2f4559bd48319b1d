"""The files a run reads, by content: the input log of a data source, and text inputs read with
errors that name the file.

Every reader of an input file (motion files, skeleton maps, scenario and rig YAML, calibrations,
videos and images, masks, keypoint JSON) calls :func:`note_input` — or reads the file with
:func:`read_text_input`, which notes it — and so does every search of a folder whose content
decides what is read (the ``.asf`` files beside an AMC, a recording's folders). While an
:func:`input_log` is open, the noted files are collected;
:func:`torchmocap.assembly.load_sequence` opens one around a data source, stores the files'
digests in ``Sequence.meta.inputs``, and a run, or a cached sequence, is up to date only
while :func:`changed_inputs` finds none of them changed. Which files a source reads is
thus what it actually read (the ASF found beside an AMC, a scenario's ``base:`` chain, every
mask and keypoint file of a recording), not what a config names.

Digests are SHA-256 of the whole content (first 16 hex digits): a touched but unchanged file
does not rerun anything, and any change of content does. They are memoised per process by
``(path, size, mtime_ns, inode)``, so a file is read once per process however often it is
checked; hashing runs at about 1 GB/s (a 100 MB video: ~0.1 s). A folder's digest is that of
its sorted entry names (a file added or removed there changes it); a path that does not exist
has the digest ``"-"`` (it appearing later is a change).
"""

from __future__ import annotations

import functools
import hashlib
import os
import stat
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

__all__ = ["InputLog", "changed_inputs", "code_fingerprint", "file_digest", "input_log",
           "named_file_digests", "note_input", "read_text_input", "yaml_error_line"]

_LOGS: ContextVar[tuple[InputLog, ...]] = ContextVar("torchmocap_input_logs", default=())
_DIGESTS: dict[tuple[str, int, int, int], str] = {}
_CHUNK = 1 << 20


class InputLog:
    """The files noted while the log was open (absolute paths, in the order first read)."""

    def __init__(self) -> None:
        self._paths: dict[str, None] = {}

    @property
    def paths(self) -> list[str]:
        return list(self._paths)

    def add(self, path: str) -> None:
        self._paths.setdefault(path)

    def digests(self) -> dict[str, str]:
        """``{path: digest}`` of every noted file or folder (:func:`file_digest`)."""
        return {p: file_digest(p) for p in self._paths}


@contextmanager
def input_log() -> Iterator[InputLog]:
    """Collect the files noted by the readers until the block ends (logs nest: an outer log
    also gets what an inner one collects)."""
    log = InputLog()
    token = _LOGS.set((*_LOGS.get(), log))
    try:
        yield log
    finally:
        _LOGS.reset(token)


def note_input(path: str | os.PathLike) -> None:
    """Record ``path`` as read in every open :func:`input_log` (nothing when none is open)."""
    logs = _LOGS.get()
    if logs:
        p = str(Path(path).expanduser().absolute())
        for log in logs:
            log.add(p)


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 (16 hex digits) of a file's content — memoised by path, size, modification time
    and inode — or of a folder's sorted entry names (``dir:<digest>``); ``"-"`` when ``path``
    does not exist or cannot be read."""
    p = str(Path(path).expanduser().absolute())
    try:
        st = os.stat(p)
        if stat.S_ISDIR(st.st_mode):
            names = sorted(e.name + ("/" if e.is_dir() else "") for e in os.scandir(p))
            return "dir:" + hashlib.sha256("\n".join(names).encode()).hexdigest()[:16]
    except OSError:
        return "-"
    key = (p, st.st_size, st.st_mtime_ns, st.st_ino)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        try:
            with open(p, "rb") as f:
                while chunk := f.read(_CHUNK):
                    h.update(chunk)
        except OSError:
            return "-"
        _DIGESTS[key] = h.hexdigest()[:16]
    return _DIGESTS[key]


def changed_inputs(recorded: Mapping[str, str]) -> list[str]:
    """The files and folders of ``recorded`` (``{path: digest}``, as :meth:`InputLog.digests`
    gives) whose digest differs now."""
    return [p for p, d in recorded.items() if file_digest(p) != d]


def read_text_input(path: str | os.PathLike, error: type[Exception] = ValueError,
                    what: str = "text file") -> str:
    """The text of the input file ``path`` (UTF-8; a byte-order mark is dropped), noted as
    read.

    Raises:
        error: ``path`` cannot be read, or is not UTF-8 text (a binary file): the message names
            the file, the offending byte and ``what`` was expected.
    """
    p = Path(path)
    note_input(p)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise error(f"{p}: cannot read ({e.strerror or e})") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{p}: not a text file (byte 0x{raw[e.start]:02x} at offset {e.start} is "
                    f"not UTF-8); expected a {what}") from None


def yaml_error_line(e: Exception, position: bool = True) -> str:
    """A YAML parse error on one line: ``line L, column C: <problem> (<context>)`` (PyYAML's
    own message spans several lines, of which a one-line report would keep the least useful);
    without ``position`` (the caller names the line) from ``<problem>`` on."""
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or str(e).strip().splitlines()[0]
    context = getattr(e, "context", None)
    where = "" if mark is None or not position else \
        f"line {mark.line + 1}, column {mark.column + 1}: "
    return f"{where}{problem}" + (f" ({context})" if context else "")


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """SHA-256 of the package's files — Python sources, packaged configs and bundled assets
    (the default clip, body mesh and learned weights) — sorted by path."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def named_file_digests(node) -> dict[str, str]:
    """Content hashes of the existing files a config node names (clips, scenario YAMLs,
    weights): ``{string: digest}`` of every string value that is a file's path."""
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
