"""What a data source (the ``_target_`` of a ``data`` config) can provide, known before it loads.

A source declares the observation modalities its sequences can hold and the tracker presets
made for them with :func:`data_source`; a run whose tracker needs a modality the source can
never provide (IMUs of a video recording) is refused before any file is read, naming the
presets to use (:func:`check_source_modalities`).

Example:
    >>> @data_source(provides=("images", "rig"), trackers=("real_frame",))
    ... def my_source(path: str, seed: int = 0): ...
    >>> source_modalities(my_source)
    ('images', 'rig')
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from torchmocap.data.sequence import MODALITIES

__all__ = ["check_source_modalities", "data_source", "source_modalities", "source_trackers"]


def data_source(provides: Sequence[str], trackers: Sequence[str] = ()) -> Callable:
    """Declare what a data source can provide: ``provides`` (modality names,
    :data:`~torchmocap.data.MODALITIES`) and ``trackers`` (the presets made for its data)."""
    bad = [m for m in provides if m not in MODALITIES]
    if bad:
        raise ValueError(f"provides: unknown modalities {bad}; expected names in "
                         f"{list(MODALITIES)}")

    def mark(fn: Callable) -> Callable:
        fn.provides = tuple(provides)
        fn.trackers = tuple(trackers)
        return fn

    return mark


def source_modalities(fn: Callable) -> tuple[str, ...]:
    """The modalities ``fn`` declared (every modality when it declared none)."""
    return getattr(fn, "provides", MODALITIES)


def source_trackers(fn: Callable) -> tuple[str, ...]:
    """The presets ``fn`` declared for its data (none when it declared none)."""
    return getattr(fn, "trackers", ())


def check_source_modalities(fn: Callable, requires: Sequence[str], tracker: str, where: str,
                            users: Callable[[str], list[str]] | None = None) -> None:
    """Refuse a tracker that needs a modality the source ``fn`` never provides.

    Args:
        fn: the data source.
        requires: the modalities the tracker's components read.
        tracker: the tracker's name; where: the source's config name (for the message).
        users: ``users(modality) -> ["path (Class)", ...]`` of the components reading it.

    Raises:
        ValueError: naming the modality, the components and the source's presets.
    """
    have = source_modalities(fn)
    for m in requires:
        if m not in have:
            who = f" (for {', '.join(users(m))})" if users is not None and users(m) else ""
            presets = source_trackers(fn)
            hint = (f"; track it with tracker={' | '.join(presets)}" if presets else "")
            raise ValueError(f"tracker {tracker!r} needs {m!r} observations{who}, which {where} "
                             f"never provides (it provides {', '.join(have)}){hint}")
