"""Assembling a run from configs: the sequence (:func:`load_sequence`), the runtime dependencies,
``build`` and the tracker presets (:func:`tracker_config`, :func:`build_tracker`).

Every component config has a ``_target_`` (a class, function or classmethod, from torchmocap or
any importable package). :func:`build` instantiates a config tree bottom-up with
``hydra.utils.instantiate`` — children first, then their parent with the built children — and
passes the **runtime dependencies** a constructor asks for by parameter name:

==================  ===============================================================================
``skeleton``        the tracking :class:`~torchmocap.skeleton.Skeleton` (the subject's model)
``body``            its :class:`~torchmocap.body.CapsuleBody`
``rig``             the :class:`~torchmocap.cameras.CameraRig` of the sequence's views
``manifold``        the :class:`~torchmocap.ik.SensorManifold` of the tracking IMUs (None without)
``depth_camera``    the one-camera rig of the depth points (None without depth)
``keypoint_names``  the column names of the sequence's 2D detections (``joint_names``)
``keypoint_map``    the subject's keypoint map fitted to the recording (``meta.keypoint_map``,
                    the map's YAML schema as a dict), else the detections' format name
==================  ===============================================================================

So a user's class enters a tracker through YAML alone::

    # my_term.yaml
    _target_: mypkg.likelihoods.MyTerm     # def __init__(self, body, rig, width=2.0)
    width: 3.0

and ``tracker.likelihood.terms.mine`` of that config builds ``MyTerm(body=<runtime body>,
rig=<runtime rig>, width=3.0)``. Dependencies are never looked up globally.

:func:`load_sequence` builds the ``data`` node of a run's config (a data source with
``_target_``: a synthesised clip, a recording, ...) into a :class:`~torchmocap.data.Sequence`,
noting the files it reads and caching it (``sequence_cache``); :func:`tracker_config` composes a
packaged preset (``conf/tracker/<name>.yaml``) with Hydra's compose API — the same config
``torchmocap-track tracker=<name> <overrides>`` resolves — and :func:`build_tracker` builds it
for the sequence's :class:`Runtime`. The command lines and the experiments assemble their runs
with these functions.

Example:
    >>> from torchmocap.assembly import tracker_config
    >>> cfg = tracker_config("p", ["noise@tracker.proposal.noise=gaussian"])
    >>> cfg.proposal.noise._target_
    'torchmocap.proposals.PassiveGaussianNoise'
"""

from __future__ import annotations

import hashlib
import inspect
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "DEPENDENCIES",
    "ComponentError",
    "Runtime",
    "build",
    "build_tracker",
    "load_sequence",
    "sequence_cache_dir",
    "tracker_config",
]

#: Names of the runtime dependencies :func:`build` passes to constructors that accept them.
DEPENDENCIES = ("skeleton", "body", "rig", "manifold", "depth_camera", "keypoint_names",
                "keypoint_map")


class ComponentError(ValueError):
    """A component config cannot be built (names the config path)."""


@dataclass
class Runtime:
    """The runtime dependencies of components (see the module docstring).

    Attributes:
        skeleton, body, rig, manifold, depth_camera, keypoint_names, keypoint_map: see
            :data:`DEPENDENCIES`.
        sensors: ``{sensor: bone}`` of the tracking IMUs.
    """

    skeleton: Any
    body: Any = None
    rig: Any = None
    manifold: Any = None
    sensors: dict[str, str] = field(default_factory=dict)
    depth_camera: Any = None
    keypoint_names: list[str] | None = None
    keypoint_map: Any = None

    @classmethod
    def from_sequence(cls, sequence, skeleton=None, dtype: torch.dtype = torch.float32
                      ) -> Runtime:
        """Dependencies for tracking ``sequence``: the subject's skeleton (``skeleton``, else
        the ground truth's, else ``sequence.meta.subject_skeleton``), its capsule body, the
        rig, the sensor manifold of the tracking IMUs, the names of the 2D detections'
        columns (``sequence.joint_names``) and their keypoint map (the subject's fitted map
        ``sequence.meta.keypoint_map``, else the format's name ``meta.keypoint_format``;
        a dict or a string: config values, which ``hydra.utils.instantiate`` passes unchanged
        where it would turn a dataclass into a config)."""
        from torchmocap.body import CapsuleBody
        from torchmocap.ik import SensorManifold
        from torchmocap.skeleton import Skeleton

        meta = sequence.meta
        if skeleton is None:
            if sequence.ground_truth is not None:
                skeleton = sequence.ground_truth.build_skeleton()
            elif meta.subject_skeleton is not None:
                skeleton = Skeleton.from_dict(meta.subject_skeleton)
            else:
                why = (meta.subject_fit or {}).get("skipped")
                raise ValueError("skeleton: required when the sequence has neither ground truth "
                                 "nor meta.subject_skeleton" + (f" (no subject fit: {why})"
                                                                if why else ""))
        skeleton = skeleton.to(dtype)
        sensors: dict[str, str] = {}
        if sequence.imu is not None:
            sensors = {n: b for n, b, t in zip(sequence.imu.names, sequence.imu.bones,
                                                sequence.imu.tracking.tolist()) if t}
        manifold = SensorManifold(skeleton, sensors) if sensors else None
        rig = None if sequence.rig is None else sequence.rig.to(dtype)
        depth_camera = None if sequence.depth is None else sequence.depth.camera.to(dtype)
        keypoint_names = (list(sequence.joint_names) if sequence.joints2d is not None
                          and sequence.joint_names else None)
        keypoint_map = None
        if keypoint_names is not None:
            keypoint_map = meta.keypoint_map or meta.keypoint_format
        return cls(skeleton=skeleton, body=CapsuleBody(skeleton).to(dtype), rig=rig,
                   manifold=manifold, sensors=sensors, depth_camera=depth_camera,
                   keypoint_names=keypoint_names, keypoint_map=keypoint_map)


def _accepts(fn, name: str) -> tuple[bool, bool]:
    """(accepts a keyword ``name``, it is required) for a callable."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return False, False
    p = sig.parameters.get(name)
    if p is None or p.kind in (p.POSITIONAL_ONLY, p.VAR_POSITIONAL):
        return False, False
    return True, p.default is inspect.Parameter.empty


def _is_component(node) -> bool:
    from omegaconf import DictConfig

    return isinstance(node, (Mapping, DictConfig)) and "_target_" in node


def _build_value(v, runtime, path):
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if _is_component(v):
        return build(v, runtime, _path=path)
    if isinstance(v, (Mapping, DictConfig)):
        return {k: _build_value(x, runtime, f"{path}.{k}") for k, x in v.items()}
    if isinstance(v, (ListConfig, list, tuple)):
        return [_build_value(x, runtime, f"{path}[{i}]") for i, x in enumerate(v)]
    if OmegaConf.is_config(v):
        return OmegaConf.to_container(v, resolve=True)
    return v


def build(node, runtime: Runtime | None = None, *, _path: str = "", **kwargs):
    """Instantiate a component config tree (``_target_`` nodes, bottom-up).

    Args:
        node: a ``DictConfig``/dict with ``_target_`` (children with ``_target_`` are built
            first; ``_partial_: true`` gives a ``functools.partial``).
        runtime: the :class:`Runtime` whose dependencies are passed to constructors asking for
            them by name (:data:`DEPENDENCIES`), unless the config sets them.
        kwargs: extra arguments of the top-level component (e.g. ``seed``).
    Raises:
        ComponentError: an unknown ``_target_``, a missing runtime dependency, or a constructor
            that rejected its arguments — naming the config path.
    """
    from hydra.utils import get_object, instantiate
    from omegaconf import DictConfig, OmegaConf

    where = _path or "<root>"
    if not _is_component(node):
        raise ComponentError(f"{where}: expected a config with a _target_, got "
                             f"{type(node).__name__}")
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    target = node["_target_"]
    try:
        fn = get_object(target)
    except Exception as e:
        raise ComponentError(f"{where}: cannot import _target_ {target!r} "
                             f"({type(e).__name__}: {e})") from None
    own = {k: v for k, v in node.items() if k.startswith("_")}
    children = {k: _build_value(v, runtime, f"{_path}.{k}" if _path else k)
                for k, v in node.items() if not k.startswith("_")}
    deps = {}
    for name in DEPENDENCIES:
        if name in children or name in kwargs:
            continue
        ok, required = _accepts(fn, name)
        if not ok:
            continue
        value = None if runtime is None else getattr(runtime, name)
        if value is None and required:
            what = ("tracking IMUs (a sensor manifold)" if name == "manifold"
                    else f"a runtime {name}")
            raise ComponentError(f"{where}: {target} needs {what}, which this sequence / "
                                 "runtime does not provide")
        if value is not None:
            deps[name] = value
    try:
        return instantiate(own, **children, **deps, **kwargs, _recursive_=False,
                           _convert_="all")
    except Exception as e:
        cause = e.__cause__ if e.__cause__ is not None else e
        msg = str(cause.args[0]) if isinstance(cause, KeyError) and cause.args else str(cause)
        if isinstance(cause, TypeError) and "argument" in msg:  # a signature mismatch
            msg = f"{target}: {msg}"
        raise ComponentError(msg if msg.startswith(where) else f"{where}: {msg}") from cause


def tracker_config(preset: str = "p", overrides: Sequence[str] = ()):
    """The ``tracker`` node of ``torchmocap-track tracker=<preset> <overrides>`` (a
    ``DictConfig``), composed with Hydra's compose API from the packaged configs.

    ``overrides`` use the command line's syntax, e.g. ``tracker.num_particles=100`` or
    ``noise@tracker.proposal.noise=gaussian``.
    """
    import warnings

    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    args = [f"tracker={preset}", *overrides]
    with warnings.catch_warnings():  # the repository's conf/ need not exist here
        warnings.filterwarnings("ignore", message=r".*provider=hydra\.searchpath in main.*")
        if GlobalHydra.instance().is_initialized():
            return compose(config_name="track", overrides=args).tracker
        with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
            return compose(config_name="track", overrides=args).tracker


def build_tracker(config, runtime: Runtime, seed: int = 0):
    """Build a :class:`~torchmocap.filters.Tracker` from its config node (e.g. from
    :func:`tracker_config`) for the given runtime dependencies."""
    import numbers

    from torchmocap.filters.tracking.tracker import Tracker

    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        # int() would silently run 1.5 as seed 1
        raise ValueError(f"seed: expected an integer, got {seed!r}")
    tracker = build(config, runtime, _path="tracker", seed=int(seed))
    if not isinstance(tracker, Tracker):
        raise ComponentError(f"tracker: _target_ built a {type(tracker).__name__}, expected a "
                             "torchmocap.filters.Tracker")
    return tracker


def sequence_cache_dir(cfg) -> Path | None:
    """The ``sequence_cache`` directory (created when missing), or None when unset.

    Raises:
        NotADirectoryError: the setting names an existing file, or a directory that cannot be
            created or written.
    """
    cache = cfg.get("sequence_cache")
    if not cache:
        return None
    d = Path(str(cache)).expanduser()
    if d.exists() and not d.is_dir():
        raise NotADirectoryError(f"sequence_cache: {d} is a file; expected a directory (or "
                                 "null: no cache)")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise NotADirectoryError(f"sequence_cache: cannot create the directory {d} "
                                 f"({e.strerror or e})") from None
    if not os.access(d, os.W_OK | os.X_OK):
        raise NotADirectoryError(f"sequence_cache: the directory {d} is not writable")
    return d


def load_sequence(cfg, min_frames: int = 2, min_views: int | None = None):
    """Build the ``data`` node (a sequence source with ``_target_``; its ``seed`` defaults to
    the run's, and ``evaluation.heldout_camera`` is passed to a source that holds one out),
    noting every file it reads: ``meta.inputs`` holds their digests
    (:mod:`torchmocap.inputs`).

    With ``sequence_cache: <dir>`` in the config, the sequence is saved under
    ``<dir>/<fingerprint of the data node, the code and the files it names>`` and read back by
    later runs with the same data settings (e.g. every tracker and seed of a sweep) while the
    input files it was built from are unchanged; otherwise it is rebuilt and replaced. A cache
    entry that cannot be written is reported with a warning (the run goes on uncached).
    ``min_frames`` and ``min_views`` (the views a tracker needs, None: any) are passed to a
    source that accepts them."""
    import warnings

    from hydra.utils import get_object
    from omegaconf import OmegaConf

    from torchmocap.inputs import changed_inputs, code_fingerprint, input_log, named_file_digests

    extra = {}
    fn = get_object(cfg.data._target_)
    if "seed" not in cfg.data and _accepts(fn, "seed")[0]:
        extra["seed"] = int(cfg.seed)
    if _accepts(fn, "min_frames")[0]:
        extra["min_frames"] = min_frames
    if min_views is not None and _accepts(fn, "min_views")[0]:
        extra["min_views"] = min_views  # e.g. a recording's tracked views (checked first)
    held = (cfg.get("evaluation") or {}).get("heldout_camera")
    if held is not None:
        if not _accepts(fn, "heldout_camera")[0]:
            raise ValueError(f"evaluation.heldout_camera: the data source {cfg.data._target_} "
                             "cannot hold a camera out (a recording can: data=recording)")
        extra["heldout_camera"] = held
    cache = sequence_cache_dir(cfg)
    key = None
    if cache is not None:
        from torchmocap.data import Sequence, SequenceFormatError

        node = OmegaConf.to_container(cfg.data, resolve=True)
        blob = json.dumps({"data": node, "extra": extra, "code": code_fingerprint(),
                           "files": named_file_digests(node)}, sort_keys=True, default=str)
        key = cache / hashlib.sha256(blob.encode()).hexdigest()[:16]
        if (key / "manifest.json").is_file():
            try:
                seq = Sequence.load(key)
            except (SequenceFormatError, OSError, ValueError):
                seq = None  # unreadable: rebuild and replace it
            inputs = None if seq is None else seq.meta.inputs
            if isinstance(inputs, dict) and not changed_inputs(inputs):
                return seq
    with input_log() as log:
        seq = build(cfg.data, None, _path="data", **extra)
    seq.meta.inputs = log.digests()
    if key is not None:
        try:
            seq.save(key, overwrite=True)
        except OSError as e:
            if not (key / "manifest.json").is_file():  # not another job's entry of the sweep
                warnings.warn(f"sequence_cache: cannot write {key} ({e.strerror or e}); the "
                              "sequence is not cached", stacklevel=2)
    return seq
