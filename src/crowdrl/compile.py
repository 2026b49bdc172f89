"""A function compiled by ``torch.compile`` on first call, with an eager fallback."""

from __future__ import annotations

import warnings
from typing import Any, Callable

import torch
from torch import nn
from torch._dynamo.exc import BackendCompilerFailed
from torch._inductor.exc import InductorError


# Inductor's C++ wrapper: the compiled graph's kernel calls are made from C++ rather than a
# generated Python function: a faster D3QN update (docs/benchmarks.md).
CPP_WRAPPER: dict[str, Any] = {"cpp_wrapper": True}


class LazyCompiled:
    """Calls ``fn`` through ``torch.compile(fn, dynamic=dynamic)``, compiled on first use.

    Falls back to plain ``fn`` (warning once, naming ``what`` and ``hint``) if compilation
    fails, e.g. on a machine without a C++ compiler. Inside an outer compiled region it calls
    ``fn`` directly, so the outer graph traces and fuses it instead of nesting a compilation; so
    it does under ``torch.jit`` tracing (the ONNX export of :mod:`crowdrl.export`).
    ``enabled=False`` always runs ``fn`` eagerly. ``options`` go to inductor (``torch.compile``'s
    ``options``), e.g. ``{"cpp_wrapper": True}``.
    """

    def __init__(self, fn: Callable, *, dynamic: bool | None, what: str, hint: str = "",
                 enabled: bool = True, options: dict[str, Any] | None = None) -> None:
        self.fn = fn
        self.dynamic = dynamic
        self.options = dict(options or {})
        self.what = what
        self.hint = hint
        self.enabled = bool(enabled)
        self._compiled: Callable | None = None

    def __call__(self, *args: Any) -> Any:
        if not self.enabled or torch.compiler.is_compiling() or torch.jit.is_tracing():
            return self.fn(*args)
        if self._compiled is None:
            self._compiled = torch.compile(self.fn, dynamic=self.dynamic, options=self.options or None)
        try:
            return self._compiled(*args)
        except (BackendCompilerFailed, InductorError) as exc:  # pragma: no cover - depends on the toolchain
            warnings.warn(f"compiling {self.what} failed ({type(exc).__name__}: {exc}); using eager torch"
                          + (f" ({self.hint})" if self.hint else ""), RuntimeWarning)
            self.enabled = False
            return self.fn(*args)


class CompiledModule(nn.Module):
    """``module`` called through ``torch.compile`` (a :class:`LazyCompiled`), for acting.

    The parameters are ``module``'s own (shared, not copied), so training it updates what this
    computes. Each batch shape compiles its own static graph (a run meets a few: the collector's,
    the planner's candidates, validation's and the test's; a static graph runs faster than a
    dynamic-shape one, docs/benchmarks.md). Random ops (dropout) draw from torch's generator as in
    eager (inductor's ``fallback_random``), so the random stream is eager's; the outputs equal
    eager's to float rounding (inductor fuses and reorders some sums).

    >>> net = nn.Linear(3, 2)
    >>> fast = CompiledModule(net, what="a linear layer")  # compiled on the first call
    >>> fast.module is net
    True
    """

    def __init__(self, module: nn.Module, *, what: str) -> None:
        super().__init__()
        self.module = module
        self._call = LazyCompiled(module, dynamic=False, what=what, options={**CPP_WRAPPER, "fallback_random": True})

    def forward(self, *args: torch.Tensor) -> torch.Tensor:
        return self._call(*args)


__all__ = ["CPP_WRAPPER", "CompiledModule", "LazyCompiled"]
