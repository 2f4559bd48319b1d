"""Strategies (annealing schedules, resamplers) are objects that configs choose by their
``_target_``: :func:`as_strategy` accepts one, gives the default for ``None`` and refuses names."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ["as_strategy"]


def as_strategy(value: Any, arg: str, default: Callable[[], Any], example: str) -> Any:
    """``value`` itself when it is a callable object, ``default()`` for ``None``; a typed error
    naming ``arg`` otherwise (a name such as ``"systematic"`` too: there is no name lookup)."""
    if value is None:
        return default()
    if isinstance(value, str) or not callable(value):
        raise TypeError(f"{arg}: expected a {example}, got {value!r}")
    return value
