"""Typed errors of the motion readers and skeleton maps."""

from __future__ import annotations

from pathlib import Path

__all__ = ["MotionFormatError", "SkeletonMapError"]


class MotionFormatError(ValueError):
    """A motion file (BVH, ASF, AMC) is malformed or does not match its companion file.

    The message names the file and, where known, the 1-based line number:
    ``"walk.bvh:212: frame 3 has 95 values, expected 96"``. ``path`` and ``line`` are kept as
    attributes for programs that want them.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = None if path is None else str(path)
        self.line = line if line is not None and line >= 1 else None
        self.reason = message
        where = self.path or "<motion>"
        if self.line is not None:
            where = f"{where}:{self.line}"
        super().__init__(f"{where}: {message}")


class SkeletonMapError(ValueError):
    """A skeleton map is malformed, or a skeleton cannot be mapped onto human31."""
