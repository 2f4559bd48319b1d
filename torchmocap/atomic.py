"""Atomic file writes: write to a temporary file beside the target, then ``os.replace``.

A reader (or a crashed run) never sees a half-written file: either the old file or the complete
new one is there. Every file the package writes goes through :func:`atomic_path` (JSON through
:func:`write_json_atomic`); whole directories (a saved sequence, a mask-cache entry) are
written beside their target and renamed into place by their writers.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["atomic_path", "write_json_atomic", "write_text_atomic"]


@contextmanager
def atomic_path(path: str | os.PathLike, mode: int = 0o644, durable: bool = False
                ) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s directory; on success it replaces ``path``.

    The temporary file keeps ``path``'s suffix last (``.name.XXXX.tmp.png``) so writers that
    pick a format from the suffix (PIL, ffmpeg) still work. On an exception the temporary file
    is removed and ``path`` is left as it was. ``mode``: the file's permissions; ``durable``:
    flush the file to disk before the rename (a power cut leaves the old or the new file).

    Example:
        >>> with atomic_path("/tmp/x.txt") as tmp:  # doctest: +SKIP
        ...     tmp.write_text("done")
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.",
                                suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, mode)
        if durable:
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | os.PathLike, text: str, durable: bool = True) -> Path:
    """Write ``text`` (UTF-8, ``\\n`` line ends) to ``path`` atomically (:func:`atomic_path`);
    returns the path."""
    with atomic_path(path, durable=durable) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="\n")
    return Path(path)


def write_json_atomic(obj: Any, path: str | os.PathLike) -> None:
    """Write ``obj`` as JSON (indented; tensors as lists, non-finite floats as null) to
    ``path`` atomically (:func:`atomic_path`, mode 0644)."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=2, allow_nan=False, default=_json_default)


def _json_default(x):
    import torch

    if isinstance(x, torch.Tensor):
        return x.tolist()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")
