"""torchmocap.compilation: the compile option's wrapper — off runs the function itself, a
compiler failure falls back to eager once with a warning, bad inputs still raise their own
error, copies and pickles drop the compiled object. (No real compilation here: the compiled
likelihood terms are tested in tests/likelihoods.)"""

from __future__ import annotations

import copy
import pickle
import warnings

import pytest
import torch

from torchmocap.compilation import CompiledFunction


def _square_norm(x: torch.Tensor) -> torch.Tensor:
    if x.dim() != 2:
        raise ValueError(f"x: expected (P, D), got {tuple(x.shape)}")
    return (x * x).sum(-1)


class _Compiler:
    """A stand-in for ``torch.compile`` that records its calls and returns ``make(fn)``."""

    def __init__(self, make):
        self.make, self.calls = make, []

    def __call__(self, fn, **kwargs):
        self.calls.append(kwargs)
        return self.make(fn)


def _failing(fn):
    def run(*args, **kwargs):
        raise RuntimeError("InvalidCxxCompiler: No working C++ compiler found\nmore lines")
    return run


def test_disabled_runs_the_function_itself(monkeypatch):
    comp = _Compiler(lambda fn: fn)
    monkeypatch.setattr(torch, "compile", comp)
    f = CompiledFunction(_square_norm, "terms.x.compile", enabled=False)
    assert torch.equal(f(torch.ones(2, 3)), torch.full((2,), 3.0))
    assert comp.calls == [] and not f.enabled


def test_compiles_once_with_run_time_threads(monkeypatch):
    comp = _Compiler(lambda fn: (lambda x: fn(x) + 1))  # marks results of the compiled path
    monkeypatch.setattr(torch, "compile", comp)
    f = CompiledFunction(_square_norm, "terms.x.compile", dynamic=False)
    for _ in range(3):
        assert torch.equal(f(torch.ones(2, 3)), torch.full((2,), 4.0))
    assert len(comp.calls) == 1
    assert comp.calls[0]["dynamic"] is False
    assert comp.calls[0]["options"]["cpp.dynamic_threads"] is True


def test_compiler_failure_falls_back_to_eager_once(monkeypatch):
    comp = _Compiler(_failing)
    monkeypatch.setattr(torch, "compile", comp)
    f = CompiledFunction(_square_norm, "terms.silhouette.compile")
    with pytest.warns(RuntimeWarning, match=r"terms\.silhouette\.compile: torch.compile failed "
                                            r"\(RuntimeError: InvalidCxxCompiler"):
        out = f(torch.ones(2, 3))
    assert torch.equal(out, torch.full((2,), 3.0)) and not f.enabled
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no second warning, no second compile
        assert torch.equal(f(2 * torch.ones(1, 2)), torch.full((1,), 8.0))
    assert len(comp.calls) == 1


def test_bad_input_raises_its_own_error(monkeypatch):
    monkeypatch.setattr(torch, "compile", _Compiler(_failing))
    f = CompiledFunction(_square_norm, "terms.x.compile")
    with pytest.raises(ValueError, match=r"x: expected \(P, D\)"):
        f(torch.ones(3))


def test_copies_and_pickles_compile_again(monkeypatch):
    comp = _Compiler(lambda fn: fn)
    monkeypatch.setattr(torch, "compile", comp)
    f = CompiledFunction(_square_norm, "terms.x.compile")
    f(torch.ones(1, 2))
    for g in (copy.deepcopy(f), pickle.loads(pickle.dumps(f))):
        assert g._compiled is None and g.enabled and g.name == "terms.x.compile"
        assert torch.equal(g(torch.ones(1, 2)), torch.full((1,), 2.0))
    assert len(comp.calls) == 3


def test_fn_must_be_callable():
    with pytest.raises(TypeError, match="fn: expected a callable"):
        CompiledFunction(3, "x")
