"""Nested settings of a data config (``data.keypoints``, ``data.subject``): defaults filled
in, unknown keys refused by their full name."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def with_defaults(prefix: str, given: Mapping[str, Any] | None,
                  defaults: Mapping[str, Any]) -> dict[str, Any]:
    """``defaults`` updated by ``given`` (None: the defaults).

    Raises:
        ValueError: a key of ``given`` not in ``defaults``, naming ``prefix``.
    """
    given = {} if given is None else dict(given)
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise ValueError(f"{prefix}: unknown setting(s) {unknown}; expected "
                         f"{sorted(defaults)}")
    return {**defaults, **given}
