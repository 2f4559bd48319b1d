"""Phenotypes by name, by values or drawn from a seed: what a scenario's ``phenotype`` says.

A phenotype specification is one of

* ``None`` or ``"default"``: Anny's default body (every parameter 0.5);
* a name of ``torchmocap/conf/phenotypes.yaml`` (:func:`named_phenotypes`: ``child``, ``heavy``,
  ``slim``, ``tall``, ``short``, ``male``, ``female``);
* a mapping ``{parameter: value}`` (:data:`~torchmocap.body.PHENOTYPE_NAMES`, each in [0, 1];
  the others 0.5);
* ``"random"``: drawn from a seed (:func:`random_phenotype`) — either sex, children to old
  adults, slim to heavy, short to tall.

:func:`resolve_phenotype` turns any of them into a ``{name: float}`` dict of all six
parameters, raising :class:`~torchmocap.body.PhenotypeError` (a ``ValueError``) that names the
setting on an unknown name, an unknown parameter or a value outside [0, 1].
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from functools import lru_cache
from importlib import resources
from typing import Any

import torch

from torchmocap.body.anny_model import PHENOTYPE_NAMES
from torchmocap.body.parametric import PhenotypeError

__all__ = ["RANDOM_RANGES", "named_phenotypes", "random_phenotype", "resolve_phenotype"]

#: the ranges :func:`random_phenotype` draws each parameter from, uniformly (gender: one sex or
#: the other, then within 0.2 of it)
RANDOM_RANGES: dict[str, tuple[float, float]] = {
    "gender": (0.0, 0.2), "age": (0.3, 0.9), "muscle": (0.2, 0.8), "weight": (0.05, 0.95),
    "height": (0.1, 0.9), "proportions": (0.2, 0.8)}


@lru_cache(maxsize=1)
def _named() -> dict[str, dict[str, float]]:
    import yaml

    text = (resources.files("torchmocap") / "conf" / "phenotypes.yaml").read_text()
    data = yaml.safe_load(text) or {}
    return {str(k): dict(v or {}) for k, v in data.items()}


def named_phenotypes() -> dict[str, dict[str, float]]:
    """The named phenotypes of ``torchmocap/conf/phenotypes.yaml`` (name → the values it sets)."""
    return {k: dict(v) for k, v in _named().items()}


def random_phenotype(seed: int) -> dict[str, float]:
    """A phenotype drawn from ``seed`` (:data:`RANDOM_RANGES`; the same seed, the same body on
    every platform)."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise PhenotypeError(f"phenotype_seed: expected an integer, got {seed!r}")
    h = hashlib.sha256(f"phenotype:{seed}".encode()).digest()
    g = torch.Generator().manual_seed(int.from_bytes(h[:8], "little") & ((1 << 63) - 1))
    u = torch.rand(len(PHENOTYPE_NAMES) + 1, generator=g, dtype=torch.float64).tolist()
    out = {}
    for i, name in enumerate(PHENOTYPE_NAMES):
        lo, hi = RANDOM_RANGES[name]
        out[name] = lo + (hi - lo) * u[i]
    if u[-1] < 0.5:  # the other sex
        out["gender"] = 1.0 - out["gender"]
    return {k: round(v, 4) for k, v in out.items()}


def resolve_phenotype(spec: Any = None, seed: int = 0, setting: str = "phenotype"
                      ) -> dict[str, float]:
    """All six parameters ``{name: float}`` of a phenotype specification (module docstring).

    Args:
        spec: ``None``, a name, ``"random"`` or a mapping of values.
        seed: the seed of ``"random"``.
        setting: the setting's name in error messages (e.g. ``scenario.phenotype``).

    Raises:
        PhenotypeError: an unknown name or parameter, a value that is not a number in [0, 1].
    """
    if spec is None:
        values: Mapping[str, Any] = {}
    elif isinstance(spec, str):
        if spec == "random":
            values = random_phenotype(seed)
        elif spec in _named():
            values = _named()[spec]
        else:
            raise PhenotypeError(f"{setting}: unknown phenotype {spec!r}; expected one of "
                                 f"{sorted(_named())}, 'random' or a mapping of "
                                 f"{list(PHENOTYPE_NAMES)} to values in [0, 1]")
    elif isinstance(spec, Mapping):
        values = spec
    else:
        raise PhenotypeError(f"{setting}: expected a phenotype name, 'random' or a mapping of "
                             f"{list(PHENOTYPE_NAMES)} to values in [0, 1], got "
                             f"{type(spec).__name__}")
    unknown = sorted(str(k) for k in values if k not in PHENOTYPE_NAMES)
    if unknown:
        raise PhenotypeError(f"{setting}: unknown parameter(s) {unknown}; known: "
                             f"{list(PHENOTYPE_NAMES)}")
    out = {}
    for name in PHENOTYPE_NAMES:
        v = values.get(name, 0.5)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or not 0.0 <= float(v) <= 1.0:
            raise PhenotypeError(f"{setting}.{name}: expected a number in [0, 1], got {v!r}")
        out[name] = float(v)
    return out
