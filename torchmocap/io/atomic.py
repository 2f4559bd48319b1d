"""Atomic file writes: write to a temporary file beside the target, then ``os.replace``.

A reader (or a crashed run) never sees a half-written file: either the old file or the complete
new one is there. Used for images, videos and GLB files written into run directories.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path"]


@contextmanager
def atomic_path(path: str | os.PathLike, mode: int = 0o644) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s directory; on success it replaces ``path``.

    The temporary file keeps ``path``'s suffix last (``.name.XXXX.tmp.png``) so writers that
    pick a format from the suffix (PIL, ffmpeg) still work. On an exception the temporary file
    is removed and ``path`` is left as it was.

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
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
