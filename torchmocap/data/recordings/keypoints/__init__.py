"""Where a recording's 2D keypoints come from: the keypoint-source registry.

A **keypoint source** gives, for every loaded frame and camera, the people it detected —
``people[t][c]``, a ``(P, K, 3)`` tensor of (u, v, confidence) in the full-size images' pixels
(confidence 0: missed) — and their keypoint format. The loader
(:func:`~torchmocap.data.recordings.load_recording`) then picks the subject among several
people, scales the pixels and fits the subject; what a source does is only *finding* the
detections: reading a detector's files beside the videos, or running a detector on the frames.

Sources are chosen by name with ``data.keypoints.source``. Each name is a config file
``torchmocap/conf/keypoint_source/<name>.yaml`` holding the source's ``_target_`` (a
:class:`KeypointSource` subclass) and its settings with their defaults; the user overrides them
in ``data.keypoints`` (on the command line ``+data.keypoints.folder=raw``). Adding a source is
one module (the class) and one config file; a source outside the package is named by the path
of its config file (``data.keypoints.source=my/detector.yaml``). Built in:

* ``openpose`` (:class:`~torchmocap.data.recordings.keypoints.openpose.OpenPoseJson`): OpenPose
  JSON per frame and camera (``pose-associated/<cam>_json/`` or ``pose/<cam>_json/``; BODY_25,
  BODY_25B, COCO-17, HALPE-26 — what OpenPose, MMPose/RTMPose and Pose2Sim write).

``source: auto`` takes the first source, in name order, whose files the recording has
(:meth:`KeypointSource.available`: a source that computes its keypoints is never chosen
without being named), else none; ``none`` loads no keypoints.

Example:
    >>> from torchmocap.data.recordings.keypoints import keypoint_sources
    >>> "openpose" in keypoint_sources()
    True
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "KEYPOINT_SETTINGS",
    "KeypointDetections",
    "KeypointRequest",
    "KeypointSource",
    "build_keypoint_source",
    "choose_keypoint_source",
    "keypoint_settings",
    "keypoint_sources",
]

#: the ``data.keypoints`` settings every source shares, with their defaults (a source's own
#: settings and defaults come from its config file)
KEYPOINT_SETTINGS = {"source": "auto", "format": "auto", "min_confidence": 0.1}
#: names of ``data.keypoints.source`` that are not config files
_SPECIAL = ("auto", "none")


@dataclass
class KeypointRequest:
    """What the loader asks a source for.

    Attributes:
        root: the recording folder.
        cameras: the loaded cameras' files
            (:class:`~torchmocap.data.recordings.files.RecordingCamera`), in the loaded order.
        frames: the loaded frame indices (of the videos / image folders).
        format: the requested keypoint format (``auto``: the source's, or detected).
        videos: the opened frame sources of ``cameras``
            (:func:`~torchmocap.io.frames.open_frames`), for sources that read the images.
    """

    root: Path
    cameras: Sequence[Any]
    frames: range
    format: str = "auto"
    videos: Sequence[Any] = ()


@dataclass
class KeypointDetections:
    """A source's answer.

    Attributes:
        people: ``people[t][c]`` ``(P, K, 3)`` float64 (u, v, confidence) in the full-size
            images' pixels, for every requested frame ``t`` and camera ``c`` (``P`` may be 0).
        format: the keypoint format (a :data:`~torchmocap.io.openpose.KEYPOINT_FORMATS` name).
        associated: every view holds at most the subject (the detections were associated
            with one person already): no selection among people is needed.
        report: what the source did, for ``meta.keypoint_report`` (JSON-ready).
    """

    people: list[list[torch.Tensor]]
    format: str
    associated: bool = False
    report: dict[str, Any] = field(default_factory=dict)


class KeypointSource(ABC):
    """A source of a recording's 2D keypoints (module docstring).

    Subclasses take their settings as keyword arguments (from the config file and
    ``data.keypoints``), check them in ``__init__`` (errors name ``data.keypoints.<key>``) and
    implement :meth:`read`.
    """

    #: the name it is registered under (its config file's name)
    name: str = ""
    #: its detections of a view depend on the other views read with it (a cross-view check):
    #: with a held-out camera the tracked views are read again without it
    views_interact: bool = False

    def available(self, request: KeypointRequest) -> bool:
        """Whether the recording has this source's keypoints for every requested camera
        without computing anything (``source: auto`` takes such a source). Default: no."""
        return False

    @abstractmethod
    def read(self, request: KeypointRequest) -> KeypointDetections:
        """The detections of every requested frame and camera.

        Raises:
            RecordingLayoutError: files missing for a camera (named).
            FrameSourceError: a frame without detections file (named).
            KeypointFormatError: files of another format, unreadable.
        """


def _config_dir():
    return resources.files("torchmocap") / "conf" / "keypoint_source"


def keypoint_sources() -> list[str]:
    """Names of the registered keypoint sources (``conf/keypoint_source/*.yaml``)."""
    return sorted(p.name[:-5] for p in _config_dir().iterdir() if p.name.endswith(".yaml"))


def _is_path(name: str) -> bool:
    return name.lower().endswith((".yaml", ".yml"))


def _source_name(name: str) -> str:
    """The name a source is reported under: its config file's stem."""
    return Path(name).stem if _is_path(name) else name


def _source_config(name: str) -> dict[str, Any]:
    """The config of the source ``name``: a registered name, or the path of a YAML file of the
    same schema (a user's own source outside the package)."""
    import yaml

    from torchmocap.inputs import read_text_input, yaml_error_line

    if _is_path(name):
        where = f"data.keypoints.source: {name}"
        try:
            text = read_text_input(Path(name).expanduser(), ValueError,
                                   "keypoint source config (YAML)")
        except ValueError as e:
            raise ValueError(f"data.keypoints.source: {e}") from None
    else:
        known = keypoint_sources()
        if name not in known:
            raise ValueError(f"data.keypoints.source: unknown source {name!r}; expected one of "
                             f"{[*_SPECIAL, *known]} or a source config's YAML path")
        where = f"conf/keypoint_source/{name}.yaml"
        text = (_config_dir() / f"{name}.yaml").read_text(encoding="utf-8")
    try:
        cfg = yaml.safe_load(text) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{where}: not valid YAML ({yaml_error_line(e)})") from None
    if not isinstance(cfg, dict) or not isinstance(cfg.get("_target_"), str):
        raise ValueError(f"{where}: expected a mapping with a _target_ (a KeypointSource "
                         "class)")
    return cfg


def keypoint_settings(keypoints: Mapping[str, Any] | None) -> dict[str, Any]:
    """The checked ``data.keypoints`` settings: the shared ones (:data:`KEYPOINT_SETTINGS`)
    and the chosen source's own, defaults filled in from its config file.

    Raises:
        ValueError: an unknown source or setting, or a bad value (named
            ``data.keypoints.<key>``).
    """
    from torchmocap.io.openpose import keypoint_format

    given = {} if keypoints is None else dict(keypoints)
    source = given.get("source", KEYPOINT_SETTINGS["source"])
    if not isinstance(source, str):
        raise ValueError(f"data.keypoints.source: expected a source name, got {source!r}")
    own: dict[str, Any] = {}
    if source not in _SPECIAL:
        own = {k: v for k, v in _source_config(source).items() if not k.startswith("_")}
    defaults = {**KEYPOINT_SETTINGS, **own}
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        where = f"the {source!r} source's settings" if own else "the shared settings"
        raise ValueError(f"data.keypoints: unknown setting(s) {unknown}; expected "
                         f"{sorted(defaults)} ({where})")
    s = {**defaults, **given}
    if s["format"] != "auto":
        keypoint_format(s["format"])
    mc = s["min_confidence"]
    if isinstance(mc, bool) or not isinstance(mc, (int, float)) or not 0 <= mc <= 1:
        raise ValueError(f"data.keypoints.min_confidence: expected a number in [0, 1], got "
                         f"{mc!r}")
    return s


def build_keypoint_source(name: str, settings: Mapping[str, Any]) -> KeypointSource:
    """The source registered as ``name``, built with its own settings from ``settings`` (the
    checked ``data.keypoints``, :func:`keypoint_settings`)."""
    from hydra.utils import get_object

    cfg = _source_config(name)
    try:
        cls = get_object(cfg["_target_"])
    except Exception as e:
        raise ValueError(f"data.keypoints.source: cannot import the _target_ "
                         f"{cfg['_target_']!r} of source {name!r} ({type(e).__name__}: {e})"
                         ) from None
    if not (isinstance(cls, type) and issubclass(cls, KeypointSource)):
        raise ValueError(f"data.keypoints.source: the _target_ {cfg['_target_']!r} of source "
                         f"{name!r} is not a KeypointSource class")
    own = {k: settings[k] for k in cfg if not k.startswith("_")}
    source = cls(**own)
    source.name = _source_name(name)
    return source


def choose_keypoint_source(settings: Mapping[str, Any], request: KeypointRequest
                           ) -> KeypointSource | None:
    """The source ``data.keypoints.source`` names (``auto``: the first registered one whose
    files the recording has, else None; ``none``: None)."""
    name = settings["source"]
    if name == "none":
        return None
    if name != "auto":
        return build_keypoint_source(name, settings)
    for candidate in keypoint_sources():
        own = _source_config(candidate)
        source = build_keypoint_source(candidate, {k: own[k] for k in own
                                                   if not k.startswith("_")})
        if source.available(request):
            return source
    return None
