"""Learned likelihood terms: the shared machinery (weights files, architecture checks, MLPs).

A learned term is an ordinary :class:`~torchmocap.likelihoods.Likelihood` whose energy is
computed by a small network ``net`` (an ``nn.Module`` holding every trainable parameter). The
term itself holds the runtime dependencies (``body``, ``rig``) and the per-frame preprocessing;
the network is independent of them, so one network can be trained on many subjects and rigs
(``term = LearnedFeatureLikelihood(body, rig, net=shared_net)``).

Two terms ship (see :mod:`~torchmocap.likelihoods.learned_features` and
:mod:`~torchmocap.likelihoods.learned_render`); both follow this file's contract:

- ``term.config``: every constructor setting that changes the energy (architecture and feature
  settings), a plain dict; it is written into every weights file and compared on load, so a
  file of another architecture fails with :class:`ArchitectureMismatchError` naming each key
  that differs;
- ``weights``: a path to a weights file, ``"bundled"`` (the file shipped in
  ``torchmocap/assets/learned/``) or ``None`` (random initialisation — for training).

Weights files are plain dicts of tensors, numbers and strings, written atomically (temporary
file renamed into place, :func:`~torchmocap.atomic.atomic_path`) and read with
``torch.load(weights_only=True)``::

    {"format": "torchmocap-learned-likelihood", "version": 1, "term": "<class name>",
     "config": {...}, "state_dict": {...}, ...}

A training checkpoint (:mod:`torchmocap.learning.checkpoints`) is a weights file with extra
keys (optimiser state, epoch, ...), so ``weights=<checkpoint.pt>`` works too.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchmocap.likelihoods.base import Likelihood

__all__ = [
    "ArchitectureMismatchError",
    "LearnedLikelihood",
    "WEIGHTS_FORMAT",
    "WeightsError",
    "bilinear_lookup",
    "bundled_weights_path",
    "compare_configs",
    "mlp",
    "pool_views",
    "read_weights",
    "write_weights",
]

#: ``format`` key of every weights file.
WEIGHTS_FORMAT = "torchmocap-learned-likelihood"
WEIGHTS_VERSION = 1


class WeightsError(ValueError):
    """A weights file cannot be used (unreadable, not a weights file, another term)."""


class ArchitectureMismatchError(WeightsError):
    """A weights file was written for another architecture or feature settings; the message
    names every differing key with the file's and the config's value."""


def bundled_weights_path(name: str) -> Path:
    """Path of a weights file shipped in ``torchmocap/assets/learned/``."""
    from importlib import resources

    return Path(str(resources.files("torchmocap") / "assets" / "learned" / name))


def mlp(sizes: Sequence[int], final_bias: bool = True) -> nn.Sequential:
    """``Linear -> SiLU -> ... -> Linear`` through ``sizes`` (no activation after the last).

    SiLU, not ReLU: an unrolled optimiser trains through the energy's gradient in the pose,
    whose derivative in the biases (and anything that only shifts pre-activations) vanishes
    almost everywhere with ReLU."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        last = i == len(sizes) - 2
        layers.append(nn.Linear(sizes[i], sizes[i + 1], bias=final_bias or not last))
        if not last:
            layers.append(nn.SiLU())
    return nn.Sequential(*layers)


def pool_views(v: torch.Tensor, view_valid: torch.Tensor) -> torch.Tensor:
    """Permutation-invariant pooling over views: ``v (P, C, F)`` -> ``(P, 2F)``, the mean and the
    maximum over the views with ``view_valid (C,)`` (dropped views are left out; with no valid
    view the result is zeros, the same for every particle)."""
    P, C, F = v.shape
    m = view_valid.to(device=v.device, dtype=torch.bool)
    if not bool(m.any()):
        return v.new_zeros(P, 2 * F)
    vv = v[:, m]
    return torch.cat([vv.mean(1), vv.amax(1)], -1)


def _resolve(weights, bundled: str) -> Path:
    if isinstance(weights, os.PathLike):
        weights = os.fspath(weights)
    if not isinstance(weights, str) or not weights:
        raise WeightsError(f"weights: expected a file path, 'bundled' or null, got {weights!r}")
    p = bundled_weights_path(bundled) if weights == "bundled" else Path(weights).expanduser()
    if not p.is_file():
        what = "the bundled weights file is missing" if weights == "bundled" else "no such file"
        raise FileNotFoundError(f"weights: {what}: {p.absolute()}")
    return p


def read_weights(path: str | os.PathLike) -> dict[str, Any]:
    """Read a weights file or training checkpoint (``torch.load(weights_only=True)``).

    Raises:
        FileNotFoundError: no such file (naming ``weights``).
        WeightsError: not a torchmocap weights file.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"weights: no such file: {p.absolute()}")
    try:
        payload = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # junk, text, a foreign pickle
        raise WeightsError(f"weights: {p} is not a torchmocap weights file "
                           f"({type(e).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != WEIGHTS_FORMAT:
        raise WeightsError(f"weights: {p} is not a torchmocap weights file (format "
                           f"{payload.get('format') if isinstance(payload, dict) else None!r})")
    if payload.get("version") != WEIGHTS_VERSION:
        raise WeightsError(f"weights: {p} has format version {payload.get('version')!r}; this "
                           f"torchmocap reads version {WEIGHTS_VERSION}")
    for k in ("term", "config", "state_dict"):
        if k not in payload:
            raise WeightsError(f"weights: {p} has no {k!r} entry")
    return payload


def write_weights(path: str | os.PathLike, payload: Mapping[str, Any]) -> Path:
    """Write ``payload`` (with ``term``, ``config``, ``state_dict``) atomically
    (:func:`~torchmocap.atomic.atomic_path`)."""
    from torchmocap.atomic import atomic_path

    p = Path(path)
    full = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, **payload}
    with atomic_path(p, durable=True) as tmp:
        with open(tmp, "wb") as f:  # a file object: the archive name is not the temporary one
            torch.save(full, f)
    return p


def compare_configs(saved: Mapping[str, Any], current: Mapping[str, Any]) -> list[str]:
    """``"key: file X, config Y"`` for every key whose value differs (missing keys included)."""
    out = []
    for k in sorted(set(saved) | set(current)):
        a, b = saved.get(k, "<absent>"), current.get(k, "<absent>")
        if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
            same = list(a) == list(b)
        else:
            same = a == b
        if not same:
            out.append(f"{k}: file {a!r}, config {b!r}")
    return out


class LearnedLikelihood(Likelihood):
    """Base class of learned terms: ``net`` holds the parameters, ``config`` the settings.

    Subclasses set ``bundled`` (the asset file name) and build ``self.net`` before calling
    :meth:`_init_weights`.
    """

    bundled: str = ""

    @property
    def config(self) -> dict[str, Any]:
        """Every setting that changes the energy (stored in and checked against weights)."""
        raise NotImplementedError

    def _init_weights(self, weights) -> None:
        self.weights_path: str | None = None
        if weights is not None:
            self.load_weights(_resolve(weights, self.bundled))

    def load_weights(self, path: str | os.PathLike) -> None:
        """Load ``state_dict`` from a weights file after checking the term and its config.

        Raises:
            WeightsError: another term's file; ArchitectureMismatchError: other settings.
        """
        payload = read_weights(path)
        name = type(self).__name__
        if payload["term"] != name:
            raise WeightsError(f"weights: {path} holds a {payload['term']} network, not a "
                               f"{name}")
        diff = compare_configs(payload["config"], self.config)
        if diff:
            raise ArchitectureMismatchError(
                f"weights: {path} was trained with other settings than this {name}: "
                + "; ".join(diff) + " (set the config to the file's values)")
        try:
            self.net.load_state_dict(payload["state_dict"])
        except RuntimeError as e:  # shapes: cannot happen when the configs agree
            raise ArchitectureMismatchError(f"weights: {path}: {e}") from None
        self.weights_path = str(path)

    def weights_payload(self) -> dict[str, Any]:
        """The ``term``, ``config`` and ``state_dict`` entries of a weights file."""
        return {"term": type(self).__name__, "config": dict(self.config),
                "state_dict": {k: v.detach().cpu().clone()
                               for k, v in self.net.state_dict().items()}}

    def save_weights(self, path: str | os.PathLike) -> Path:
        """Write this term's weights file (atomically)."""
        return write_weights(path, self.weights_payload())

    def _net_dtype(self) -> torch.dtype:
        return next(self.net.parameters()).dtype

    def bind(self, body, rig) -> LearnedLikelihood:
        """The same term for another subject / rig, sharing this term's ``net`` (training on
        many clips: one network, one term per sequence)."""
        return type(self)(body, rig, net=self.net, **self.config)


def bilinear_lookup(img: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Bilinear values of ``img (C, F, H, W)`` at pixels ``px, py (C, M)`` (pixel ``x`` covers
    ``[x - 0.5, x + 0.5)``; zero outside): ``(C, F, M)``.

    Built from gathers and products (not ``grid_sample``), so it is twice differentiable in the
    pixel coordinates — an unrolled optimiser differentiates the energy's gradient.
    """
    C, Fn, H, W = img.shape
    M = px.shape[-1]
    x0 = px.detach().floor()
    y0 = py.detach().floor()
    fx, fy = px - x0, py - y0
    flat = torch.cat([img.reshape(C, Fn, H * W), img.new_zeros(C, Fn, 1)], -1)  # zero pixel
    out = None
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                      (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi <= W - 1) & (yi >= 0) & (yi <= H - 1)
        idx = torch.where(inside, yi * W + xi, torch.full_like(xi, H * W)).long()
        v = torch.gather(flat, 2, idx[:, None].expand(C, Fn, M)) * w[:, None]
        out = v if out is None else out + v
    return out
