"""Optional ``torch.compile`` of hot functions, falling back to eager execution.

Components with a ``compile`` option (the silhouette and appearance terms, the sensor
manifold's ``g^{-1}``) wrap their core in :class:`CompiledFunction`. The first call compiles
(tens of seconds on a CPU, where Inductor's C++ backend needs a C++ compiler; the result is
cached on disk by torch, so later processes start faster), after which the core's hundred-odd
small tensor operations run as a few fused loops. Compiled code rounds differently from the
eager operations (fused multiply-adds, reordered sums), so a compiled run is not bit-identical
to an eager one: the option is off by default.

Falling back: when compiling or running the compiled code raises, the same call is repeated
eagerly. If the eager call succeeds, a warning names the failure and every later call runs
eagerly (e.g. no C++ compiler on the machine); if it raises too, its error propagates — the
input was at fault, not the compiler.

Threads: the kernels read the number of OpenMP threads when they run
(``cpp.dynamic_threads``), so ``torch.set_num_threads`` — the thread governor of the commands —
applies to them as to eager code.

Example:
    >>> import torch
    >>> f = CompiledFunction(lambda x: (x * x).sum(-1), "square_norm", enabled=False)
    >>> f(torch.ones(2, 3))
    tensor([3., 3.])
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch

__all__ = ["CompiledFunction"]

#: Inductor options of every compiled core: thread count read at run time
INDUCTOR_OPTIONS = {"cpp.dynamic_threads": True, "cpp.enable_loop_tail_vec": False}


class CompiledFunction:
    """``fn`` run through ``torch.compile`` (when ``enabled``), with the eager fallback of the
    module docstring.

    Args:
        fn: the function to compile (pure tensor code; Python control flow on shapes and
            Python values is fine, host reads of tensor values split the compiled graph).
        name: what a fallback warning calls it (e.g. the config key of the option).
        enabled: False runs ``fn`` as it is (the option off).
        dynamic: ``torch.compile``'s ``dynamic`` (None: static shapes first, dynamic after a
            shape changes).

    The compiled object is made on the first call and is not copied or pickled (a copy compiles
    again on its first call).
    """

    def __init__(self, fn: Callable, name: str, enabled: bool = True,
                 dynamic: bool | None = None) -> None:
        if not callable(fn):
            raise TypeError(f"fn: expected a callable, got {type(fn).__name__}")
        self.fn, self.name, self.dynamic = fn, str(name), dynamic
        self.enabled = bool(enabled)
        self._compiled: Callable | None = None

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if not self.enabled:
            return self.fn(*args, **kwargs)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, dynamic=self.dynamic,
                                           options=dict(INDUCTOR_OPTIONS))
        try:
            return self._compiled(*args, **kwargs)
        except Exception as e:  # any failure of the compiler: run eagerly
            out = self.fn(*args, **kwargs)  # bad inputs raise here, as without compile
            first = (str(e).strip().splitlines() or [""])[0][:200]
            warnings.warn(f"{self.name}: torch.compile failed ({type(e).__name__}: {first}); "
                          "running eagerly from now on", RuntimeWarning, stacklevel=2)
            self.enabled = False
            self._compiled = None
            return out

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_compiled"] = None
        return state

    def __deepcopy__(self, memo: dict) -> CompiledFunction:
        import copy

        out = CompiledFunction.__new__(CompiledFunction)
        memo[id(self)] = out
        out.__dict__.update(copy.deepcopy(self.__getstate__(), memo))
        return out

    def __repr__(self) -> str:
        return f"CompiledFunction({self.name}, enabled={self.enabled})"
