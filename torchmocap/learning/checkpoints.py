"""Training checkpoints of learned likelihood terms.

A checkpoint is a weights file (:func:`~torchmocap.likelihoods.learned.write_weights`: ``term``,
``config``, ``state_dict``) with the training state beside it — optimiser and LR-schedule state,
epoch, step, the data-order generator's state, the metrics so far and the training config — so
``weights=<checkpoint.pt>`` loads it into a tracker directly, and ``resume=<checkpoint.pt>``
continues the training where it stopped. Files are written atomically
(:func:`~torchmocap.atomic.atomic_path`) and read with ``torch.load(weights_only=True)``; a
checkpoint of another term or architecture raises
:class:`~torchmocap.likelihoods.learned.ArchitectureMismatchError` naming every differing setting.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from torchmocap.likelihoods.learned import (
    ArchitectureMismatchError,
    LearnedLikelihood,
    WeightsError,
    compare_configs,
    read_weights,
    write_weights,
)

__all__ = ["ArchitectureMismatchError", "CheckpointState", "load_checkpoint",
           "save_checkpoint"]

CheckpointState = dict[str, Any]


def save_checkpoint(path: str | os.PathLike, term: LearnedLikelihood, *,
                    optimizer: torch.optim.Optimizer | None = None, scheduler=None,
                    epoch: int = 0, step: int = 0, generator: torch.Generator | None = None,
                    metrics: list[dict] | None = None, train_config: dict | None = None,
                    extra_parameters: dict[str, torch.Tensor] | None = None) -> Path:
    """Write ``term``'s weights and the training state to ``path`` atomically."""
    payload = term.weights_payload()
    payload.update({
        "epoch": int(epoch), "step": int(step),
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "scheduler": None if scheduler is None else scheduler.state_dict(),
        "generator": None if generator is None else generator.get_state(),
        "metrics": list(metrics or []),
        "train_config": dict(train_config or {}),
        "extra_parameters": {k: v.detach().cpu().clone()
                             for k, v in (extra_parameters or {}).items()},
    })
    return write_weights(path, payload)


def load_checkpoint(path: str | os.PathLike, term: LearnedLikelihood, *,
                    optimizer: torch.optim.Optimizer | None = None, scheduler=None,
                    generator: torch.Generator | None = None,
                    extra_parameters: dict[str, torch.Tensor] | None = None
                    ) -> CheckpointState:
    """Load a checkpoint into ``term`` (and the optimiser, scheduler, generator, extra
    parameters when given); returns the payload (``epoch``, ``step``, ``metrics``, ...).

    Raises:
        FileNotFoundError, WeightsError: unreadable or not a checkpoint;
        ArchitectureMismatchError: written for another architecture (names the settings).
    """
    term.load_weights(path)  # checks term name and config, loads the network
    payload = read_weights(path)
    if optimizer is not None:
        if payload.get("optimizer") is None:
            raise WeightsError(f"resume: {path} holds weights only (no optimiser state); "
                               "start a new training with it as init_weights instead")
        optimizer.load_state_dict(payload["optimizer"])
    if scheduler is not None and payload.get("scheduler") is not None:
        scheduler.load_state_dict(payload["scheduler"])
    if generator is not None and payload.get("generator") is not None:
        generator.set_state(payload["generator"])
    if extra_parameters:
        saved = payload.get("extra_parameters") or {}
        diff = compare_configs({k: list(v.shape) for k, v in saved.items()},
                               {k: list(v.shape) for k, v in extra_parameters.items()})
        if diff:
            raise ArchitectureMismatchError(f"resume: {path}: extra parameters differ: "
                                            + "; ".join(diff))
        with torch.no_grad():
            for k, v in extra_parameters.items():
                v.copy_(saved[k])
    return payload
