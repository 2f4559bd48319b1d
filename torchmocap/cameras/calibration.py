"""Calibration readers and writers: Bouguet ``.cal`` files and OpenCV-style YAML/JSON rigs.

All readers return a :class:`~torchmocap.cameras.rig.CameraRig` in metres (``unit`` says what one
file unit is in metres) and raise :class:`~torchmocap.cameras.rig.CameraError` naming the file (and
line where there is one) for malformed content.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import yaml

from torchmocap.atomic import write_text_atomic
from torchmocap.cameras.rig import CameraError, CameraRig, _check_image_size

__all__ = [
    "UNITS",
    "load_rig_file",
    "read_bouguet_cal",
    "read_bouguet_rig",
    "read_rig",
    "rig_from_dict",
    "rig_to_dict",
    "write_rig",
]

#: metres per unit for the ``unit`` arguments
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "dm": 0.1, "in": 0.0254}

_BOUGUET_FIELDS = [
    ("fx", 1), ("fy", 2), ("cx", 3), ("cy", 4), ("skew (alpha_c)", 5),
    *[(f"kc[{i}]", 6 + i) for i in range(5)],
    *[(f"R[{i // 3}][{i % 3}]", 11 + i) for i in range(9)],
    *[(f"t[{i}]", 20 + i) for i in range(3)],
    *[(f"rodrigues[{i}]", 23 + i) for i in range(3)],
]


def _unit_scale(unit: str | float) -> float:
    if isinstance(unit, str):
        if unit not in UNITS:
            raise CameraError(f"unknown unit {unit!r}; expected one of {sorted(UNITS)} or a number "
                              "(metres per file unit)")
        return UNITS[unit]
    scale = float(unit)
    if not math.isfinite(scale) or scale <= 0:
        raise CameraError(f"unit must be a positive number of metres, got {unit!r}")
    return scale


def _rodrigues(r: torch.Tensor) -> torch.Tensor:
    theta = r.norm()
    if float(theta) < 1e-12:
        return torch.eye(3, dtype=r.dtype)
    k = r / theta
    Kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=r.dtype)
    return torch.eye(3, dtype=r.dtype) + torch.sin(theta) * Kx + (1 - torch.cos(theta)) * Kx @ Kx


def _read_bouguet_values(path: Path) -> tuple[list[float], list[int]]:
    from torchmocap.inputs import read_text_input

    text = read_text_input(path, CameraError, "Bouguet calibration (.cal: one number per line)")
    values, lines = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        for tok in line.split():
            try:
                v = float(tok)
            except ValueError as e:
                raise CameraError(f"{path}:{lineno}: not a number: {tok!r}") from e
            values.append(v)
            lines.append(lineno)
    return values, lines


def read_bouguet_cal(path: str | os.PathLike, unit: str | float = "mm",
                     image_size: Sequence[int] = (640, 480), rotation_tol: float = 1e-5
                     ) -> dict[str, torch.Tensor]:
    """Read one camera in Bouguet-toolbox layout (the bodytrack ``Camera*.cal`` files).

    Layout, 25 numbers (whitespace/newline separated, one per line in bodytrack): ``fx fy``,
    ``cx cy``, skew ``alpha_c`` (``K[0,1] = alpha_c·fx``), 5 distortion coefficients ``kc``
    (k1, k2, p1, p2, k3 — the OpenCV order), the 3×3 world-to-camera rotation row-major, the
    translation (file units), and the same rotation as a Rodrigues vector. Pixel coordinates
    have ``(0, 0)`` at the centre of the top-left pixel, as in OpenCV.

    Args:
        path: the ``.cal`` file.
        unit: file length unit: a key of :data:`UNITS` or metres per unit.
        image_size: (width, height); not stored in the file.
        rotation_tol: max abs deviation allowed between the matrix and the Rodrigues vector's
            rotation, and of ``R Rᵀ`` from the identity.

    Returns:
        dict with ``K (3, 3)``, ``dist (5,)``, ``R (3, 3)``, ``t (3,)`` (metres),
        ``image_size (2,)``, all float64.

    Raises:
        CameraError: naming the file and line for a wrong count of values, a non-finite value, a
            non-rotation matrix, or a Rodrigues vector that disagrees with the matrix (e.g. a
            transposed rotation).
    """
    path = Path(path)
    scale = _unit_scale(unit)
    values, lines = _read_bouguet_values(path)
    if len(values) != 25:
        where = f"{path}:{lines[-1]}" if values else str(path)
        raise CameraError(f"{where}: expected 25 numbers in Bouguet .cal layout (fx fy cx cy skew, "
                          f"5 distortion, 3x3 R, 3 t, 3 Rodrigues), found {len(values)}")
    for (name, _), v, ln in zip(_BOUGUET_FIELDS, values, lines):
        if not math.isfinite(v):
            raise CameraError(f"{path}:{ln}: {name} is not finite ({v})")
    v = torch.tensor(values, dtype=torch.float64)
    fx, fy, cx, cy, alpha = v[:5]
    if fx <= 0 or fy <= 0:
        raise CameraError(f"{path}:{lines[0]}: focal lengths must be positive, got {float(fx)}, "
                          f"{float(fy)}")
    K = torch.tensor([[fx, alpha * fx, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    dist = v[5:10].clone()
    R = v[10:19].reshape(3, 3).clone()
    t = v[19:22] * scale
    rvec = v[22:25]
    eye = torch.eye(3, dtype=torch.float64)
    if (R @ R.T - eye).abs().max() > rotation_tol or abs(float(torch.linalg.det(R)) - 1) > \
            rotation_tol:
        raise CameraError(f"{path}:{lines[10]}-{lines[18]}: the 3x3 matrix is not a rotation "
                          f"(max |R Rᵀ − I| = {float((R @ R.T - eye).abs().max()):.3g}, "
                          f"det = {float(torch.linalg.det(R)):.6f})")
    dev = float((_rodrigues(rvec) - R).abs().max())
    if dev > rotation_tol:
        raise CameraError(f"{path}:{lines[22]}-{lines[24]}: Rodrigues vector disagrees with the "
                          f"rotation matrix on lines {lines[10]}-{lines[18]} (max deviation "
                          f"{dev:.3g}); is the matrix transposed?")
    size = _check_image_size(image_size)
    return {"K": K, "dist": dist, "R": R, "t": t, "image_size": size}


def read_bouguet_rig(paths: Sequence[str | os.PathLike], unit: str | float = "mm",
                     image_size: Sequence[int] = (640, 480)) -> CameraRig:
    """Read several Bouguet ``.cal`` files into one :class:`CameraRig` (metres).

    Example (bodytrack): ``read_bouguet_rig(sorted(calib_dir.glob("Camera*.cal")), unit="mm")``.
    """
    if len(paths) == 0:
        raise CameraError("read_bouguet_rig: no calibration files given")
    cams = [read_bouguet_cal(p, unit, image_size) for p in paths]
    return CameraRig(torch.stack([c["K"] for c in cams]), torch.stack([c["R"] for c in cams]),
                     torch.stack([c["t"] for c in cams]),
                     torch.stack([c["image_size"] for c in cams]),
                     torch.stack([c["dist"] for c in cams]), [Path(p).stem for p in paths])


# --------------------------------------------------------------------------- YAML / JSON


def rig_to_dict(rig: CameraRig) -> dict[str, Any]:
    """Plain-python description of a rig (OpenCV field names, metres)."""
    cams = []
    for i in range(rig.num_cameras):
        cams.append({
            "name": rig.names[i],
            "image_width": int(rig.image_size[i, 0]),
            "image_height": int(rig.image_size[i, 1]),
            "camera_matrix": rig.K[i].double().tolist(),
            "distortion_coefficients": rig.dist[i].double().tolist(),
            "rotation_matrix": rig.R[i].double().tolist(),
            "translation": rig.t[i].double().tolist(),
        })
    return {"format": "torchmocap-rig", "version": 1, "unit": "m",
            "convention": "opencv: x_cam = R x_world + t; dist = k1 k2 p1 p2 k3",
            "cameras": cams}


def _matrix(value: Any, shape: tuple[int, ...], where: str, field: str) -> torch.Tensor:
    if isinstance(value, dict) and "data" in value:  # OpenCV FileStorage !!opencv-matrix
        value = value["data"]
    try:
        x = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as e:
        raise CameraError(f"{where}: {field} is not numeric ({e})") from e
    if x.numel() != math.prod(shape):
        raise CameraError(f"{where}: {field} must have {math.prod(shape)} values (shape {shape}), "
                          f"got {x.numel()}")
    if not bool(torch.isfinite(x).all()):
        raise CameraError(f"{where}: {field} contains non-finite values")
    return x.reshape(shape)


def _pixels(x: torch.Tensor, where: str, field: str) -> torch.Tensor:
    """Whole positive pixel counts (``int()`` would turn 640.5 into 640 silently)."""
    if not bool(((x > 0) & (x == x.round())).all()):
        raise CameraError(f"{where}: {field} must be positive whole numbers of pixels, got "
                          f"{x.tolist()}")
    return x.long()


def _first(d: dict[str, Any], keys: Sequence[str], where: str, required: bool = True) -> Any:
    for k in keys:
        if k in d:
            return d[k]
    if required:
        raise CameraError(f"{where}: missing field, expected one of {list(keys)}")
    return None


def rig_from_dict(data: dict[str, Any], source: str = "<dict>", unit: str | float | None = None
                  ) -> CameraRig:
    """Build a rig from :func:`rig_to_dict` output or an OpenCV FileStorage-style mapping.

    Accepts per camera ``camera_matrix``/``K``, ``distortion_coefficients``/``dist`` (4, 5, or more
    values; only k1 k2 p1 p2 k3 are used and extra non-zero terms are rejected),
    ``rotation_matrix``/``R`` or ``rvec`` (Rodrigues), ``translation``/``t``/``tvec``,
    ``image_width``/``image_height`` or ``image_size``. A single-camera mapping without a
    ``cameras`` list is accepted. ``unit`` overrides the file's ``unit`` (default metres).
    """
    if not isinstance(data, dict):
        raise CameraError(f"{source}: expected a mapping at the top level")
    cams = data.get("cameras", [data])
    if not isinstance(cams, list) or not cams:
        raise CameraError(f"{source}: 'cameras' must be a non-empty list")
    scale = _unit_scale(unit if unit is not None else data.get("unit", "m"))
    Ks, Rs, ts, ds, sizes, names = [], [], [], [], [], []
    for i, cam in enumerate(cams):
        where = f"{source}: camera {i}" if "cameras" in data else source
        if not isinstance(cam, dict):
            raise CameraError(f"{where}: expected a mapping")
        Ks.append(_matrix(_first(cam, ["camera_matrix", "K"], where), (3, 3), where, "K"))
        d = _first(cam, ["distortion_coefficients", "dist", "D"], where, required=False)
        if d is None:
            dist = torch.zeros(5, dtype=torch.float64)
        else:
            dd = _matrix(d, (len(d["data"]) if isinstance(d, dict) else len(d),), where, "dist")
            if dd.numel() < 4:
                raise CameraError(f"{where}: dist needs at least 4 values, got {dd.numel()}")
            dist = torch.zeros(5, dtype=torch.float64)
            dist[: min(5, dd.numel())] = dd[:5]
            if dd.numel() > 5 and bool((dd[5:] != 0).any()):
                raise CameraError(f"{where}: only the 5-coefficient model (k1 k2 p1 p2 k3) is "
                                  f"supported, got {dd.numel()} non-zero coefficients")
        ds.append(dist)
        Rv = _first(cam, ["rotation_matrix", "R"], where, required=False)
        if Rv is not None:
            Rs.append(_matrix(Rv, (3, 3), where, "R"))
        else:
            Rs.append(_rodrigues(_matrix(_first(cam, ["rvec"], where), (3,), where, "rvec")))
        ts.append(_matrix(_first(cam, ["translation", "t", "tvec", "T"], where), (3,), where,
                          "t") * scale)
        if "image_size" in cam:
            sizes.append(_pixels(_matrix(cam["image_size"], (2,), where, "image_size"), where,
                                 "image_size"))
        else:
            w = _first(cam, ["image_width", "width"], where)
            h = _first(cam, ["image_height", "height"], where)
            sizes.append(torch.cat([_pixels(_matrix([w], (1,), where, "image_width"), where,
                                            "image_width"),
                                    _pixels(_matrix([h], (1,), where, "image_height"), where,
                                            "image_height")]))
        names.append(str(cam.get("name", f"cam{i}")))
    try:
        return CameraRig(torch.stack(Ks), torch.stack(Rs), torch.stack(ts), torch.stack(sizes),
                         torch.stack(ds), names)
    except CameraError as e:
        raise CameraError(f"{source}: {e}") from e


class _OpenCVLoader(yaml.SafeLoader):
    pass


def _opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> dict[str, Any]:
    return loader.construct_mapping(node, deep=True)  # type: ignore[arg-type]


_OpenCVLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _opencv_matrix)


def read_rig(path: str | os.PathLike, unit: str | float | None = None) -> CameraRig:
    """Read a rig from ``.json`` or ``.yaml``/``.yml`` (our schema or OpenCV FileStorage YAML).

    OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix`` nodes are understood.
    """
    path = Path(path)
    return rig_from_dict(load_rig_file(path), str(path), unit)


def load_rig_file(path: str | os.PathLike) -> Any:
    """The parsed content of a ``.json`` file or an (OpenCV FileStorage) YAML file.

    OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix`` nodes (mappings with ``rows``,
    ``cols``, ``dt``, ``data``) are understood.

    Raises:
        CameraError: naming the file (and line) when it cannot be read or parsed.
    """
    from torchmocap.inputs import read_text_input, yaml_error_line

    path = Path(path)
    text = read_text_input(path, CameraError, "rig or calibration file (JSON or YAML)")
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        if text.startswith("%YAML:"):
            text = text.split("\n", 1)[1] if "\n" in text else ""
        return yaml.load(text, Loader=_OpenCVLoader)  # noqa: S506 - safe loader subclass
    except json.JSONDecodeError as e:
        raise CameraError(f"{path}:{e.lineno}: cannot parse ({e.msg})") from e
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
        line = "" if mark is None else f":{mark.line + 1}"
        raise CameraError(f"{path}{line}: cannot parse ({yaml_error_line(e, False)})") from e


def write_rig(rig: CameraRig, path: str | os.PathLike) -> Path:
    """Write a rig to ``.json`` or ``.yaml``/``.yml`` atomically
    (:func:`~torchmocap.atomic.write_text_atomic`)."""
    path = Path(path)
    data = rig_to_dict(rig)
    if path.suffix.lower() == ".json":
        text = json.dumps(data, indent=2)
    elif path.suffix.lower() in (".yaml", ".yml"):
        text = yaml.safe_dump(data, sort_keys=False)
    else:
        raise CameraError(f"{path}: unsupported extension {path.suffix!r}; use .json or .yaml")
    return write_text_atomic(path, text)
