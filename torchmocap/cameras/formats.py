"""Calibration files of the multi-view ecosystem, read into one :class:`CameraRig` (metres).

* Pose2Sim / anipose TOML (:func:`read_toml_calibration`): one table per camera with ``name``,
  ``size`` [w, h], ``matrix`` K, ``distortions`` [k1, k2, p1, p2(, k3)], ``rotation`` (Rodrigues,
  world to camera) and ``translation``; a ``[metadata]`` table is ignored.
* OpenCV / EasyMocap ``intri.yml`` + ``extri.yml`` (:func:`read_opencv_calibration`), FileStorage
  YAML with ``names`` and per camera ``K_<n>``, ``dist_<n>``, ``R_<n>`` (Rodrigues) or
  ``Rot_<n>`` (3x3), ``T_<n>``, and optionally ``H_<n>``/``W_<n>``.
* A folder of Bouguet ``.cal`` files (:func:`read_bouguet_folder`), paired with cameras by the
  number in the file name (``Camera2.cal`` is camera 2, whatever else is there).
* :func:`read_calibration` picks the reader from what a path holds.

Cameras are named as in the file; :func:`camera_key` reduces a name to what identifies a camera
across the files of a recording (``cam01``, ``cam_01``, ``Camera1``, ``CAM1`` and ``1`` all
give ``"1"``).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from torchmocap.cameras.calibration import (
    _matrix,
    _rodrigues,
    _unit_scale,
    load_rig_file,
    read_bouguet_rig,
    read_rig,
    rig_from_dict,
)
from torchmocap.cameras.rig import CameraError, CameraRig, _check_image_size

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = [
    "bouguet_calibration_files",
    "calibration_files",
    "camera_key",
    "concat_rigs",
    "read_bouguet_folder",
    "read_calibration",
    "read_opencv_calibration",
    "read_toml_calibration",
]

ImageSizes = Mapping[str, Sequence[int]] | Sequence[int] | Sequence[Sequence[int]] | torch.Tensor

_TOML_FIELDS = ("size", "matrix", "distortions", "rotation", "translation")


def camera_key(name: str) -> str:
    """What identifies a camera across the files of a recording: the first number in its name
    (without leading zeros), else its lower-case letters and digits.

    Example:
        >>> {camera_key(n) for n in ("cam01", "cam_01", "Camera1", "CAM1", "1", "cam01_json")}
        {'1'}
        >>> camera_key("Left-View")
        'leftview'
    """
    m = re.search(r"\d+", str(name))
    return str(int(m.group())) if m else re.sub(r"[^0-9a-z]", "", str(name).lower())


def concat_rigs(rigs: Sequence[CameraRig]) -> CameraRig:
    """One rig with the cameras of ``rigs`` in order (names kept)."""
    if not rigs:
        raise CameraError("concat_rigs: no rigs given")
    return CameraRig(torch.cat([r.K for r in rigs]), torch.cat([r.R for r in rigs]),
                     torch.cat([r.t for r in rigs]), torch.cat([r.image_size for r in rigs]),
                     torch.cat([r.dist for r in rigs]), [n for r in rigs for n in r.names])


def _rotation(value: Any, where: str, field: str) -> torch.Tensor:
    """A 3x3 rotation from a Rodrigues vector (3 values) or a matrix (9 values)."""
    raw = value["data"] if isinstance(value, dict) and "data" in value else value
    try:
        n = torch.as_tensor(raw, dtype=torch.float64).numel()
    except (TypeError, ValueError, RuntimeError) as e:
        raise CameraError(f"{where}: {field} is not numeric ({e})") from e
    if n == 3:
        return _rodrigues(_matrix(value, (3,), where, field))
    if n != 9:
        raise CameraError(f"{where}: {field} must have 3 values (a Rodrigues vector) or 9 (a "
                          f"3x3 matrix), got {n}")
    return _matrix(value, (3, 3), where, field)


def _sizes_for(names: Sequence[str], image_sizes: ImageSizes | None, source: str) -> torch.Tensor:
    """``(C, 2)`` image sizes of the cameras ``names`` from the caller's ``image_sizes``: one
    ``(w, h)`` for all, one per camera in order, or a mapping keyed by camera name (matched by
    :func:`camera_key`)."""
    if image_sizes is None:
        raise CameraError(f"{source}: the file does not store the image size of camera(s) "
                          f"{list(names)}; pass image_sizes (width, height), e.g. from the videos")
    if isinstance(image_sizes, Mapping):
        by_key = {camera_key(k): k for k in image_sizes}  # values are read only when needed
        missing = [n for n in names if camera_key(n) not in by_key]
        if missing:
            raise CameraError(f"{source}: image_sizes has no entry for camera(s) {missing} "
                              f"(given: {sorted(image_sizes)})")
        return torch.stack([_check_image_size(image_sizes[by_key[camera_key(n)]],
                                              name=f"image_sizes[{n!r}]") for n in names])
    return _check_image_size(image_sizes, len(names), name="image_sizes")


# --------------------------------------------------------------------------- TOML


def read_toml_calibration(path: str | os.PathLike, unit: str | float = "m") -> CameraRig:
    """Read a Pose2Sim / anipose calibration TOML.

    Each camera is a table (``[cam_01]``) with ``size = [width, height]`` (pixels), ``matrix``
    (3x3 K, pixels), ``distortions`` (k1, k2, p1, p2, optionally k3; a 4-value list gets
    ``k3 = 0``), ``rotation`` (Rodrigues vector of the world-to-camera rotation, or a 3x3
    matrix), ``translation`` (file units; Pose2Sim writes metres, anipose the units of its
    calibration board) and an optional ``name`` (else the table's key). ``[metadata]`` is
    ignored. ``fisheye = true`` cameras are refused: only the pinhole Brown–Conrady model is
    supported.

    Args:
        path: the ``.toml`` file.
        unit: length unit of ``translation``: a key of
            :data:`~torchmocap.cameras.calibration.UNITS` or metres per unit.

    Returns:
        a float64 :class:`CameraRig` in metres, cameras in file order, named by ``name``.

    Raises:
        CameraError: naming the file and camera table for a parse error, a missing or malformed
            field, a fisheye camera, or a file without cameras.
    """
    from torchmocap.inputs import read_text_input

    path = Path(path)
    text = read_text_input(path, CameraError, "TOML calibration")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CameraError(f"{path}: not a valid TOML file ({e})") from e
    rigs = []
    for key, table in data.items():
        if key == "metadata":
            continue
        where = f"{path} [{key}]"
        if not isinstance(table, dict):
            raise CameraError(f"{where}: expected a camera table with {list(_TOML_FIELDS)}, got "
                              f"a {type(table).__name__}")
        missing = [f for f in _TOML_FIELDS if f not in table]
        if missing:
            raise CameraError(f"{where}: missing camera field(s) {missing}; a calibration TOML "
                              f"camera has {list(_TOML_FIELDS)}")
        if table.get("fisheye", False) is not False:
            raise CameraError(f"{where}: fisheye = {table['fisheye']!r}: the fisheye lens model "
                              "is not supported (pinhole with k1 k2 p1 p2 k3 only); calibrate "
                              "these cameras with the pinhole model")
        cam: dict[str, Any] = {
            "name": str(table.get("name", key)), "K": table["matrix"],
            "dist": table["distortions"], "t": table["translation"],
            "image_size": table["size"],
            "R": _rotation(table["rotation"], where, "rotation").tolist()}
        rigs.append(rig_from_dict(cam, where, unit))
    if not rigs:
        raise CameraError(f"{path}: no camera tables (expected [<camera>] tables with "
                          f"{list(_TOML_FIELDS)})")
    return concat_rigs(rigs)


# --------------------------------------------------------------------------- intri / extri


def _need(data: dict[str, Any], key: str, path: Path, camera: str) -> Any:
    if key not in data:
        raise CameraError(f"{path}: missing {key} (camera {camera!r} is in 'names')")
    return data[key]


def read_opencv_calibration(intri: str | os.PathLike, extri: str | os.PathLike | None = None,
                            image_sizes: ImageSizes | None = None,
                            unit: str | float = "m") -> CameraRig:
    """Read an OpenCV FileStorage ``intri.yml`` + ``extri.yml`` pair (EasyMocap's layout).

    ``intri.yml``: ``names`` (list of camera names), ``K_<n>`` (3x3), ``dist_<n>`` (4, 5 or more
    coefficients, OpenCV order; terms past k3 must be zero), optionally ``H_<n>``, ``W_<n>``
    (image height and width). ``extri.yml``: ``R_<n>`` (Rodrigues 3x1, or a 3x3 matrix) and/or
    ``Rot_<n>`` (3x3; when both are given they must agree), ``T_<n>`` (3x1, file units).

    Args:
        intri: the intrinsics file.
        extri: the extrinsics file; default ``extri.yml`` (same suffix) beside ``intri``.
        image_sizes: ``(width, height)`` for cameras whose ``H_``/``W_`` are absent: one for
            all, one per camera in ``names`` order, or a mapping by camera name.
        unit: length unit of ``T_<n>``.

    Returns:
        a float64 :class:`CameraRig` in metres, cameras in ``names`` order.

    Raises:
        CameraError: naming the file and the key of a missing or malformed entry.
    """
    intri = Path(intri)
    extri = intri.with_name("extri" + intri.suffix) if extri is None else Path(extri)
    data_i, data_e = load_rig_file(intri), load_rig_file(extri)
    for p, d in ((intri, data_i), (extri, data_e)):
        if not isinstance(d, dict):
            raise CameraError(f"{p}: expected an OpenCV FileStorage mapping at the top level")
    names = data_i.get("names", data_e.get("names"))
    if not isinstance(names, list) or not names:
        raise CameraError(f"{intri}: expected a non-empty 'names' list of cameras")
    names = [str(n) for n in names]
    cams: list[dict[str, Any]] = []
    for n in names:
        cam: dict[str, Any] = {"name": n, "K": _need(data_i, f"K_{n}", intri, n),
                               "t": _need(data_e, f"T_{n}", extri, n)}
        if f"dist_{n}" in data_i:
            cam["dist"] = data_i[f"dist_{n}"]
        rvec, rot = data_e.get(f"R_{n}"), data_e.get(f"Rot_{n}")
        if rvec is None and rot is None:
            raise CameraError(f"{extri}: missing R_{n} (Rodrigues) or Rot_{n} (3x3) of camera "
                              f"{n!r}")
        R = None if rvec is None else _rotation(rvec, str(extri), f"R_{n}")
        if rot is not None:
            R_mat = _rotation(rot, str(extri), f"Rot_{n}")
            if R is not None and float((R - R_mat).abs().max()) > 1e-5:
                raise CameraError(f"{extri}: R_{n} and Rot_{n} disagree (max deviation "
                                  f"{float((R - R_mat).abs().max()):.3g})")
            R = R_mat
        cam["R"] = R.tolist()
        h, w = data_i.get(f"H_{n}"), data_i.get(f"W_{n}")
        if (h is None) != (w is None):
            raise CameraError(f"{intri}: camera {n!r} has only one of H_{n}, W_{n}")
        if h is not None:
            cam["image_size"] = [w, h]
        cams.append(cam)
    lacking = [c["name"] for c in cams if "image_size" not in c]
    if lacking:
        sizes = _sizes_for(lacking, image_sizes, str(intri))
        for c, s in zip([c for c in cams if "image_size" not in c], sizes.tolist()):
            c["image_size"] = s
    return rig_from_dict({"cameras": cams}, f"{intri} + {extri.name}", unit)


# --------------------------------------------------------------------------- Bouguet folder


def bouguet_calibration_files(folder: str | os.PathLike) -> list[tuple[int, Path]]:
    """The ``.cal`` files of ``folder`` with their camera numbers (the number in the file name:
    ``Camera2.cal`` is camera 2), sorted by number.

    Raises:
        CameraError: no ``.cal`` file, a name without a number, two files of one number, or a
            gap in the numbers (a missing ``Camera2.cal`` between 1 and 3 is named; pairing by
            position would give camera 2 the third file's calibration).
    """
    from torchmocap.inputs import note_input

    folder = Path(folder)
    note_input(folder)  # the files there decide the pairing
    files = sorted(p for p in folder.glob("*") if p.suffix.lower() == ".cal" and p.is_file())
    if not files:
        raise CameraError(f"{folder}: no Bouguet calibration files (*.cal)")
    by_num: dict[int, Path] = {}
    for p in files:
        m = re.search(r"(\d+)\D*$", p.stem)
        if m is None:
            raise CameraError(f"{p}: no camera number in the file name (expected e.g. "
                              "Camera1.cal)")
        i = int(m.group(1))
        if i in by_num:
            raise CameraError(f"{folder}: {by_num[i].name} and {p.name} are both camera {i}")
        by_num[i] = p
    nums = sorted(by_num)
    gaps = sorted(set(range(nums[0], nums[-1] + 1)) - set(nums))
    if gaps:
        stem = re.sub(r"\d+(\D*)$", r"{}\1", by_num[nums[0]].stem)
        named = ", ".join(stem.format(g) + ".cal" for g in gaps)
        raise CameraError(f"{folder}: missing {named} (found {[by_num[i].name for i in nums]}); "
                          "the cameras are numbered by file name")
    return [(i, by_num[i]) for i in nums]


def read_bouguet_folder(folder: str | os.PathLike, unit: str | float = "mm",
                        image_sizes: ImageSizes | None = (640, 480)) -> CameraRig:
    """Read a folder of Bouguet ``.cal`` files (:func:`bouguet_calibration_files` order).

    Args:
        folder: e.g. bodytrack's ``CALIB``.
        unit: file length unit (bodytrack: millimetres).
        image_sizes: the files do not store image sizes: one ``(w, h)`` for all, one per camera
            in number order, or a mapping by camera name (``Camera1``, or anything with the
            same :func:`camera_key`).

    Returns:
        a float64 :class:`CameraRig` in metres named by the file stems (``Camera1``, ...).
    """
    files = bouguet_calibration_files(folder)
    names = [p.stem for _, p in files]
    sizes = _sizes_for(names, image_sizes, str(folder))
    rigs = [read_bouguet_rig([p], unit, s) for (_, p), s in zip(files, sizes.tolist())]
    return concat_rigs(rigs)


# --------------------------------------------------------------------------- dispatch


def calibration_files(folder: str | os.PathLike) -> dict[str, list[Path]]:
    """The calibrations a folder holds, by kind: ``"toml"`` (``*.toml`` files),
    ``"intri/extri"`` (``intri.yml`` and ``extri.yml``, or ``.yaml``) and ``"bouguet"``
    (``*.cal`` files); empty when it holds none (or is not a folder)."""
    from torchmocap.inputs import note_input

    folder = Path(folder)
    if not folder.is_dir():
        return {}
    note_input(folder)  # a calibration added there changes what is read
    found: dict[str, list[Path]] = {}
    tomls = sorted(p for p in folder.glob("*.toml") if p.is_file())
    if tomls:
        found["toml"] = tomls
    for suffix in (".yml", ".yaml"):
        if (folder / f"intri{suffix}").is_file():
            found["intri/extri"] = [folder / f"intri{suffix}", folder / f"extri{suffix}"]
            break
    cals = sorted(p for p in folder.glob("*") if p.suffix.lower() == ".cal" and p.is_file())
    if cals:
        found["bouguet"] = cals
    return found


def read_calibration(path: str | os.PathLike, image_sizes: ImageSizes | None = None,
                     unit: str | float | None = None) -> CameraRig:
    """Read a calibration in any supported format, chosen from what ``path`` is or holds.

    * a ``.toml`` file: :func:`read_toml_calibration` (default unit metres);
    * ``intri.yml``/``extri.yml`` (either file) or a folder holding them:
      :func:`read_opencv_calibration` (metres);
    * a ``.cal`` file or a folder of them: Bouguet (:func:`read_bouguet_folder`, millimetres);
    * another ``.yaml``/``.yml``/``.json`` file: :func:`~torchmocap.cameras.read_rig` (the
      file's ``unit``, default metres);
    * a folder with exactly one of the above kinds (``.toml`` files: exactly one).

    Args:
        path: file or folder.
        image_sizes: ``(width, height)`` for formats that do not store it (Bouguet files,
            intri.yml without ``H_``/``W_``): one for all, one per camera, or a mapping by
            camera name. Ignored where the file has sizes.
        unit: length unit of the file's translations; None = the format's default above.

    Raises:
        CameraError: a path that is none of these, a folder with none or several kinds (named),
            and every error of the readers.
    """
    p = Path(path)
    if unit is not None:
        _unit_scale(unit)
    if p.is_file():
        suffix = p.suffix.lower()
        if suffix == ".toml":
            return read_toml_calibration(p, unit or "m")
        if suffix == ".cal":
            sizes = _sizes_for([p.stem], image_sizes, str(p))
            return read_bouguet_rig([p], unit or "mm", sizes[0])
        if suffix in (".yml", ".yaml") and p.stem.lower() in ("intri", "extri"):
            return read_opencv_calibration(p.with_name("intri" + p.suffix),
                                           p.with_name("extri" + p.suffix), image_sizes,
                                           unit or "m")
        if suffix in (".yml", ".yaml", ".json"):
            return read_rig(p, unit)
        raise CameraError(f"{p}: unknown calibration format {p.suffix!r} (expected .toml, .cal, "
                          ".yml/.yaml or .json)")
    if not p.is_dir():
        raise CameraError(f"{p}: no such calibration file or folder")
    kinds = calibration_files(p)
    if not kinds:
        raise CameraError(f"{p}: no calibration found (expected a .toml file, intri.yml + "
                          "extri.yml, or Bouguet *.cal files)")
    if len(kinds) > 1:
        what = "; ".join(f"{k}: {[q.name for q in v]}" for k, v in kinds.items())
        raise CameraError(f"{p}: several calibrations ({what}); pass the file to use")
    kind, files = next(iter(kinds.items()))
    if kind == "toml":
        if len(files) > 1:
            raise CameraError(f"{p}: several .toml files {[q.name for q in files]}; pass the "
                              "one to use")
        return read_toml_calibration(files[0], unit or "m")
    if kind == "intri/extri":
        return read_opencv_calibration(files[0], files[1], image_sizes, unit or "m")
    return read_bouguet_folder(p, unit or "mm", image_sizes)
