"""Components whose state a track changes, saved in a tracker's checkpoints.

A few components learn something while a track runs — the sensor-to-bone calibration of the
tracking IMUs (Pons-Moll eq. 8, at the first frame), the capsule radii a body fit adapts to the
first frame's silhouettes. A resumed track must restore it, or it continues with another model.
Such a component inherits :class:`Stateful` and says what its state is; the tracker's
checkpoint stores every ``Stateful`` submodule's :meth:`~Stateful.checkpoint_state` under its
path and hands it back on resume, without knowing what it holds.

Example:
    >>> import torch
    >>> from torch import nn
    >>> class Offset(nn.Module, Stateful):
    ...     def __init__(self):
    ...         super().__init__()
    ...         self.register_buffer("value", torch.zeros(3))
    ...     def checkpoint_state(self):
    ...         return {"value": self.value.clone()}
    ...     def load_checkpoint_state(self, state):
    ...         self.value.copy_(state["value"])
    >>> a, b = Offset(), Offset()
    >>> a.value += 1
    >>> b.load_checkpoint_state(a.checkpoint_state()); b.value
    tensor([1., 1., 1.])
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["Stateful"]


class Stateful:
    """Mixin of a component with state that a tracker's checkpoint saves (module docstring).

    Subclasses implement both methods; the state is a dict of plain tensors (a checkpoint is
    read with ``torch.load(weights_only=True)``).
    """

    def checkpoint_state(self) -> dict[str, Tensor]:
        """The state to save (detached copies)."""
        raise NotImplementedError(f"{type(self).__name__} must implement checkpoint_state()")

    def load_checkpoint_state(self, state: dict[str, Tensor]) -> None:
        """Restore what :meth:`checkpoint_state` returned."""
        raise NotImplementedError(f"{type(self).__name__} must implement "
                                  "load_checkpoint_state()")
