"""Writing a rig in the multi-view ecosystem's calibration formats (what the readers of
:mod:`torchmocap.cameras.formats` read back).

* :func:`write_toml_calibration`: Pose2Sim / anipose TOML, one table per camera with ``name``,
  ``size`` [w, h], ``matrix``, ``distortions`` (k1, k2, p1, p2, and k3 when it is not zero),
  ``rotation`` (Rodrigues vector, world to camera), ``translation`` and ``fisheye = false``;
  an optional ``[metadata]`` table.
* :func:`write_opencv_calibration`: OpenCV FileStorage ``intri.yml`` (``names``, ``K_<n>``,
  ``dist_<n>`` 1×5, ``H_<n>``, ``W_<n>``) and ``extri.yml`` (``R_<n>`` Rodrigues 3×1,
  ``Rot_<n>`` 3×3, ``T_<n>`` 3×1): EasyMocap's layout, readable by ``cv2.FileStorage``.
* :func:`write_calibration` picks the writer from the path, like
  :func:`~torchmocap.cameras.read_calibration`.

Every file is written atomically (:func:`torchmocap.atomic.atomic_path`); numbers are written
with Python's shortest round-trip representation, so a rig read back is the rig written (to
the float64 rounding of the Rodrigues conversion, ~1e-15).

Example:
    >>> import tempfile, pathlib
    >>> from torchmocap.cameras import make_ring_rig, read_toml_calibration
    >>> rig = make_ring_rig(2)
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "Calib.toml"
    >>> back = read_toml_calibration(write_toml_calibration(rig, path))
    >>> bool(torch.allclose(back.R, rig.R, atol=1e-12)), back.names
    (True, ['ring0', 'ring1'])
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path

import torch

from torchmocap.cameras.calibration import _unit_scale, write_rig
from torchmocap.cameras.rig import CameraError, CameraRig
from torchmocap.geometry import so3_log

__all__ = ["write_calibration", "write_opencv_calibration", "write_toml_calibration"]

_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _num(x: float) -> str:
    """A float in a form TOML, YAML 1.1 (PyYAML) and OpenCV all read back exactly."""
    x = float(x)
    if not math.isfinite(x):
        raise CameraError(f"cannot write the non-finite value {x}")
    s = repr(x)
    if "e" in s:
        mant, exp = s.split("e")
        if "." not in mant:
            mant += ".0"
        if exp[0] not in "+-":
            exp = "+" + exp
        s = f"{mant}e{exp}"
    return s


def _vector(values) -> str:
    return "[ " + ", ".join(_num(v) for v in values) + "]"


def _check_rig(rig) -> CameraRig:
    if not isinstance(rig, CameraRig):
        raise CameraError(f"rig: expected a CameraRig, got {type(rig).__name__}")
    if len(set(rig.names)) != len(rig.names):
        raise CameraError(f"rig: camera names must be unique to be written, got {rig.names}")
    return rig


def _rodrigues_of(R: torch.Tensor) -> torch.Tensor:
    return so3_log(R.double().cpu())


def write_toml_calibration(rig: CameraRig, path: str | os.PathLike, unit: str | float = "m",
                           metadata: Mapping[str, bool | int | float | str] | None = None
                           ) -> Path:
    """Write ``rig`` as a Pose2Sim / anipose calibration TOML.

    Args:
        rig: the cameras (any dtype; written in float64).
        path: the ``.toml`` file (its folder is created).
        unit: length unit of ``translation``: a key of
            :data:`~torchmocap.cameras.calibration.UNITS` or metres per unit (Pose2Sim:
            metres).
        metadata: an optional ``[metadata]`` table of plain values (Pose2Sim writes
            ``adjusted`` and ``error``); none by default.

    Returns:
        ``path``.

    Raises:
        CameraError: not a rig, duplicate camera names, a metadata value that is not a plain
            number, bool or string.
    """
    rig = _check_rig(rig)
    scale = _unit_scale(unit)
    lines: list[str] = []
    rvecs = _rodrigues_of(rig.R)
    for c, name in enumerate(rig.names):
        key = name if _KEY.match(name) else json.dumps(name)
        K = rig.K[c].double().tolist()
        d = rig.dist[c].double().tolist()
        dist = d if d[4] != 0 else d[:4]
        w, h = (float(v) for v in rig.image_size[c].tolist())
        lines += [
            f"[{key}]",
            f"name = {json.dumps(name)}",
            f"size = {_vector([w, h])}",
            "matrix = [ " + ", ".join(_vector(row) for row in K) + "]",
            f"distortions = {_vector(dist)}",
            f"rotation = {_vector(rvecs[c].tolist())}",
            f"translation = {_vector((rig.t[c].double() / scale).tolist())}",
            "fisheye = false",
            "",
        ]
    if metadata:
        lines.append("[metadata]")
        for k, v in metadata.items():
            if not _KEY.match(str(k)):
                raise CameraError(f"metadata: key {k!r} is not a bare TOML key")
            if isinstance(v, bool):
                text = "true" if v else "false"
            elif isinstance(v, (int, float)):
                text = str(v) if isinstance(v, int) else _num(v)
            elif isinstance(v, str):
                text = json.dumps(v)
            else:
                raise CameraError(f"metadata: {k} = {v!r} is not a number, bool or string")
            lines.append(f"{k} = {text}")
        lines.append("")
    from torchmocap.atomic import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return path


def _matrix_node(key: str, rows: int, cols: int, values) -> list[str]:
    return [f"{key}: !!opencv-matrix", f"   rows: {rows}", f"   cols: {cols}", "   dt: d",
            f"   data: {_vector(values)}"]


def write_opencv_calibration(rig: CameraRig, folder: str | os.PathLike, unit: str | float = "m",
                             suffix: str = ".yml") -> tuple[Path, Path]:
    """Write ``rig`` as OpenCV FileStorage ``intri.yml`` + ``extri.yml`` (EasyMocap).

    Args:
        rig: the cameras; their names become the keys' suffixes (``K_<name>``), so they must be
            letters, digits, ``_`` or ``-``.
        folder: where both files go (created).
        unit: length unit of ``T_<name>``.
        suffix: ``".yml"`` or ``".yaml"``.

    Returns:
        the paths of ``intri`` and ``extri``.

    Raises:
        CameraError: a camera name that cannot be part of a FileStorage key, duplicate names,
            a suffix that is neither.
    """
    rig = _check_rig(rig)
    if suffix not in (".yml", ".yaml"):
        raise CameraError(f"suffix: expected '.yml' or '.yaml', got {suffix!r}")
    bad = [n for n in rig.names if not _KEY.match(n)]
    if bad:
        raise CameraError(f"rig: camera name(s) {bad} cannot be part of an OpenCV FileStorage "
                          "key (letters, digits, '_' and '-' only)")
    scale = _unit_scale(unit)
    head = ["%YAML:1.0", "---", "names:"] + [f'   - "{n}"' for n in rig.names]
    intri, extri = list(head), list(head)
    rvecs = _rodrigues_of(rig.R)
    for c, n in enumerate(rig.names):
        intri += _matrix_node(f"K_{n}", 3, 3, rig.K[c].double().reshape(-1).tolist())
        intri += _matrix_node(f"dist_{n}", 1, 5, rig.dist[c].double().tolist())
        w, h = (int(v) for v in rig.image_size[c].tolist())
        intri += [f"H_{n}: {h}", f"W_{n}: {w}"]
        extri += _matrix_node(f"R_{n}", 3, 1, rvecs[c].tolist())
        extri += _matrix_node(f"Rot_{n}", 3, 3, rig.R[c].double().reshape(-1).tolist())
        extri += _matrix_node(f"T_{n}", 3, 1, (rig.t[c].double() / scale).tolist())
    from torchmocap.atomic import atomic_path

    folder = Path(folder)
    paths = (folder / f"intri{suffix}", folder / f"extri{suffix}")
    for p, lines in zip(paths, (intri, extri)):
        with atomic_path(p) as tmp:
            tmp.write_text("\n".join(lines) + "\n")
    return paths


def write_calibration(rig: CameraRig, path: str | os.PathLike, unit: str | float = "m"
                      ) -> list[Path]:
    """Write ``rig`` in the format ``path`` names.

    * ``*.toml``: :func:`write_toml_calibration`;
    * ``intri.yml``/``extri.yml`` (either, or ``.yaml``), or a path without a suffix (a
      folder): :func:`write_opencv_calibration` there;
    * another ``.yaml``/``.yml``/``.json`` file: :func:`~torchmocap.cameras.write_rig` (the
      project's own schema, metres; ``unit`` must be metres).

    Returns:
        the files written.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".toml":
        return [write_toml_calibration(rig, p, unit)]
    if suffix in (".yml", ".yaml") and p.stem.lower() in ("intri", "extri"):
        return list(write_opencv_calibration(rig, p.parent, unit, p.suffix))
    if suffix == "":
        return list(write_opencv_calibration(rig, p, unit))
    if suffix in (".yml", ".yaml", ".json"):
        if _unit_scale(unit) != 1.0:
            raise CameraError(f"unit: {p.name} is written in metres (the project's rig schema); "
                              f"got unit {unit!r}")
        return [write_rig(_check_rig(rig), p)]
    raise CameraError(f"{p}: unknown calibration format {p.suffix!r} (expected .toml, "
                      "intri.yml/extri.yml or a folder, .yml/.yaml or .json)")
