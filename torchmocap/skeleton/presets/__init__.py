"""Preset skeletons shipped as YAML next to this module."""

from __future__ import annotations

from importlib import resources

from torchmocap.skeleton.skeleton import Skeleton

__all__ = ["human31", "upper_body", "preset", "PRESETS"]

PRESETS = ("human31", "upper_body")


def preset(name: str) -> Skeleton:
    """Load a preset skeleton by name (``human31`` or ``upper_body``)."""
    if name not in PRESETS:
        raise KeyError(f"unknown skeleton preset {name!r}; known presets: {list(PRESETS)}")
    import yaml

    text = resources.files(__name__).joinpath(f"{name}.yaml").read_text(encoding="utf-8")
    return Skeleton.from_dict(yaml.safe_load(text))


def human31() -> Skeleton:
    """The 31-DoF Pons-Moll et al. (2010) body model (21 joints, 1.75 m, Z up, facing -y)."""
    return preset("human31")


def upper_body() -> Skeleton:
    """Hauberg & Pedersen's arm-waving model: fixed torso, neck, shoulders, elbows, wrists."""
    return preset("upper_body")
