"""Cache of computed masks on disk, keyed by a content hash of everything they depend on.

A cache entry is a folder ``<cache_dir>/masks-<hash>/`` holding ``cam<c>/<t:05d>.png`` (1-bit
PNGs, the layout of a saved :class:`~torchmocap.data.Sequence`'s masks) and ``manifest.json``
(format, shape, the report). It is written into a temporary sibling folder and renamed into
place, so a reader never sees a half-written entry; an entry that cannot be read (a file
removed or damaged) is recomputed and replaced, with a warning.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmocap.data.recordings.masks.settings import MaskError, MaskSettings

__all__ = ["ALGORITHM_VERSION", "cached_masks", "content_key", "read_mask_folder",
           "write_mask_folder"]

#: part of every key: bump it when the masks a given input produces change
ALGORITHM_VERSION = 1
_FORMAT = "torchmocap-masks"
_FILE_CHUNK = 1 << 20


def _feed(h, obj: Any) -> None:
    """Feed a canonical, typed byte encoding of ``obj`` into the hash ``h``."""
    if obj is None or isinstance(obj, (bool, int, float, str)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif isinstance(obj, bytes):
        h.update(b"bytes:%d;" % len(obj) + obj)
    elif isinstance(obj, os.PathLike):
        p = Path(obj)
        if not p.is_file():
            raise MaskError(f"cache key: {p} is not a readable file")
        h.update(b"file:%d;" % p.stat().st_size)
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(_FILE_CHUNK), b""):
                h.update(block)
    elif isinstance(obj, (Tensor, np.ndarray)):
        a = obj.detach().cpu().contiguous().numpy() if isinstance(obj, Tensor) else \
            np.ascontiguousarray(obj)
        h.update(f"array:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    elif isinstance(obj, MaskSettings):
        _feed(h, obj.to_dict())
    elif isinstance(obj, torch.nn.Module):
        h.update(f"module:{type(obj).__name__};".encode())
        for name, buf in sorted(obj.state_dict().items()):
            _feed(h, name)
            _feed(h, buf)
    elif isinstance(obj, Mapping):
        h.update(b"map:%d;" % len(obj))
        for k in sorted(obj, key=str):
            _feed(h, str(k))
            _feed(h, obj[k])
    elif isinstance(obj, (list, tuple)):
        h.update(b"seq:%d;" % len(obj))
        for v in obj:
            _feed(h, v)
    else:
        raise MaskError(f"cache key: cannot hash a {type(obj).__name__}; expected tensors, "
                        "arrays, file paths, settings, numbers, strings, or lists/dicts of them")


def content_key(*parts: Any) -> str:
    """Hex digest (32 characters, BLAKE2b) of ``parts``' contents.

    Tensors and arrays hash their dtype, shape and bytes; ``Path`` objects the bytes of the
    file (a plain ``str`` is hashed as text, not as a file); modules (a ``CameraRig``) their
    buffers; :class:`MaskSettings` its dict form; mappings are hashed with sorted keys.

    Example:
        >>> content_key({"b": 1, "a": 2}) == content_key({"a": 2, "b": 1})
        True
    """
    h = hashlib.blake2b(digest_size=16)
    _feed(h, (_FORMAT, ALGORITHM_VERSION, parts))
    return h.hexdigest()


def write_mask_folder(folder: str | os.PathLike, masks: Tensor, report: Mapping | None = None
                      ) -> Path:
    """Write ``masks (T, C, H, W)`` bool as 1-bit PNGs ``cam<c>/<t:05d>.png`` and a
    ``manifest.json`` (with the JSON-safe ``report``) into ``folder``, which must not exist."""
    from PIL import Image

    folder = Path(folder)
    if not isinstance(masks, Tensor) or masks.dim() != 4 or masks.dtype != torch.bool:
        got = (f"{tuple(masks.shape)} {masks.dtype}" if isinstance(masks, Tensor)
               else type(masks).__name__)
        raise MaskError(f"masks: expected a (T, C, H, W) bool tensor, got {got}")
    manifest = {"format": _FORMAT, "version": ALGORITHM_VERSION, "shape": list(masks.shape),
                "report": dict(report or {})}
    try:
        text = json.dumps(manifest, indent=1, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise MaskError(f"report: expected JSON-safe values (numbers, strings, lists, dicts): "
                        f"{e}") from e
    m = masks.detach().cpu().numpy()
    T, C = m.shape[:2]
    folder.mkdir(parents=True)
    for c in range(C):
        (folder / f"cam{c}").mkdir()
        for t in range(T):
            Image.fromarray(m[t, c]).save(folder / f"cam{c}" / f"{t:05d}.png", optimize=True)
    (folder / "manifest.json").write_text(text)
    return folder


def read_mask_folder(folder: str | os.PathLike) -> tuple[Tensor, dict]:
    """Read what :func:`write_mask_folder` wrote: ``masks (T, C, H, W)`` bool and the report.

    Raises:
        MaskError: naming the file that is missing or malformed.
    """
    from PIL import Image

    folder = Path(folder)
    path = folder / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
        T, C, H, W = (int(v) for v in manifest["shape"])
        if manifest.get("format") != _FORMAT:
            raise ValueError(f"format {manifest.get('format')!r}")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise MaskError(f"{path}: not a mask manifest ({e})") from e
    out = np.zeros((T, C, H, W), dtype=bool)
    for c in range(C):
        for t in range(T):
            f = folder / f"cam{c}" / f"{t:05d}.png"
            try:
                with Image.open(f) as im:
                    a = np.asarray(im.convert("1"))
            except OSError as e:
                raise MaskError(f"{f}: cannot read mask ({e})") from e
            if a.shape != (H, W):
                raise MaskError(f"{f}: expected a {W}x{H} mask, got {a.shape[1]}x{a.shape[0]}")
            out[t, c] = a
    return torch.from_numpy(out), manifest.get("report", {})


def cached_masks(cache_dir: str | os.PathLike, key_inputs: Any,
                 compute_fn: Callable[[], tuple[Tensor, dict]]) -> tuple[Tensor, dict]:
    """Masks from the cache entry of ``key_inputs``, computed (and stored) when there is none.

    Args:
        cache_dir: folder of the cache entries (created when missing).
        key_inputs: everything the masks depend on, hashed by :func:`content_key` — e.g.
            ``(video_paths, calibration_path, keypoint_tensor, plates, settings)``. Include the
            settings: a changed setting must change the key.
        compute_fn: ``() -> (masks (T, C, H, W) bool, report)``, called on a miss.

    Returns:
        ``(masks, report)``; the report gains ``cache`` = ``{"key", "hit", "path"}``.

    Example:
        >>> import tempfile
        >>> fn = lambda: (torch.zeros(1, 2, 4, 4, dtype=torch.bool), {})
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _, r1 = cached_masks(d, ("clip", 1), fn)
        ...     _, r2 = cached_masks(d, ("clip", 1), fn)
        >>> r1["cache"]["hit"], r2["cache"]["hit"]
        (False, True)
    """
    key = content_key(key_inputs)
    root = Path(cache_dir)
    final = root / f"masks-{key}"
    if final.is_dir():
        try:
            masks, report = read_mask_folder(final)
            report["cache"] = {"key": key, "hit": True, "path": str(final)}
            return masks, report
        except MaskError as e:
            warnings.warn(f"mask cache entry {final} is unreadable ({e}); recomputing it",
                          stacklevel=2)
    masks, report = compute_fn()
    if not isinstance(masks, Tensor) or masks.dim() != 4 or masks.dtype != torch.bool:
        raise MaskError("compute_fn: expected it to return (masks (T, C, H, W) bool, report), "
                        f"got masks of {getattr(masks, 'shape', type(masks).__name__)}")
    report = dict(report)
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root, prefix=f".masks-{key}."))
    try:
        write_mask_folder(tmp / "entry", masks, report)
        stale = None
        if final.exists():  # an unreadable entry: move it aside, then replace it
            stale = Path(tempfile.mkdtemp(dir=root, prefix=f".stale-{key}."))
            os.replace(final, stale / "entry")
        try:
            os.replace(tmp / "entry", final)
        except OSError:
            if not final.is_dir():  # not a concurrent writer of the same entry: a real error
                raise
        if stale is not None:
            shutil.rmtree(stale, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    report["cache"] = {"key": key, "hit": False, "path": str(final)}
    return masks, report
