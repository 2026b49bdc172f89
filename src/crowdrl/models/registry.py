"""Registry of state encoders: ``(robot_rc [*, 9], humans_rc [*, N, 5]) -> [*, embedding_dim]``.

Every encoder is an ``nn.Module`` class exposing ``embedding_dim`` (an int attribute or
property); it is registered under a name with :func:`register_encoder` and built with
:func:`make_encoder`.
"""

from __future__ import annotations

from typing import Callable, TypeVar

from torch import nn

ENCODERS: dict[str, type[nn.Module]] = {}

_M = TypeVar("_M", bound=type[nn.Module])


def register_encoder(name: str) -> Callable[[_M], _M]:
    """Class decorator registering an encoder under ``name`` (which must be new)."""

    def decorator(cls: _M) -> _M:
        if name in ENCODERS and ENCODERS[name] is not cls:
            raise ValueError(f"encoder {name!r} is already registered ({ENCODERS[name].__qualname__})")
        ENCODERS[name] = cls
        return cls

    return decorator


def make_encoder(name: str, **kwargs) -> nn.Module:
    """Build the encoder registered as ``name`` with ``kwargs``; unknown names raise ``ValueError``."""
    try:
        cls = ENCODERS[name]
    except KeyError:
        raise ValueError(f"unknown encoder {name!r}; allowed: {sorted(ENCODERS)}") from None
    return cls(**kwargs)
