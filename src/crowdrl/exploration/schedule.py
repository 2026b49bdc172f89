"""Schedules of a coefficient over a clock (frames, updates, ...): constant, linear, exponential.

>>> linear_schedule(0.5, 0.1, 100, 50)
0.3
>>> beta = make_schedule("exp", 0.01, decay=1e-5, clock=lambda: 100_000)   # 0.01 * (1 - 1e-5) ** 100_000
>>> round(beta(), 6)
0.003679
"""

from __future__ import annotations

import math
from typing import Any, Callable, Union

SCHEDULES = ("constant", "linear", "exp")
Schedule = Union[float, Callable[[], float]]


def linear_schedule(start: float, end: float, duration: int, t: int) -> float:
    """``start`` → ``end`` linearly over ``duration`` steps, then ``end`` (``start`` before step 0).

    The trainer's ε and dropout-p schedules (over collected frames) and ``make_schedule("linear")``.
    """
    return end + (start - end) * min(1.0, max(0.0, 1.0 - t / duration))


def exp_schedule(start: float, decay: float, t: int) -> float:
    """``start * (1 - decay) ** t`` (RE3's β_t = β₀(1 − ρ)^t)."""
    return start * (1.0 - decay) ** t


def make_schedule(kind: str, start: float, *, end: float | None = None, duration: int | None = None,
                  decay: float | None = None, clock: Callable[[], int] | None = None) -> Schedule:
    """A float for ``constant``, else a zero-argument callable reading ``clock()``.

    ``linear`` needs ``end`` and ``duration`` (``start -> end`` over ``duration`` ticks, then ``end``);
    ``exp`` needs ``decay`` in ``[0, 1)``. Missing or out-of-range parameters raise ``ValueError``
    naming them.
    """
    if kind not in SCHEDULES:
        raise ValueError(f"schedule: unknown {kind!r}; allowed: {', '.join(SCHEDULES)}")
    if kind == "constant":
        return float(start)
    if clock is None:
        raise ValueError(f"a {kind} schedule needs a clock (a callable returning the current step)")
    if kind == "linear":
        if end is None or duration is None:
            raise ValueError("a linear schedule needs its end value and its duration")
        if duration < 1:
            raise ValueError(f"a linear schedule's duration must be >= 1, got {duration}")
        return lambda: linear_schedule(start, end, duration, clock())
    if decay is None:
        raise ValueError("an exp schedule needs its decay rate")
    if not (math.isfinite(decay) and 0.0 <= decay < 1.0):
        raise ValueError(f"an exp schedule's decay rate must lie in [0, 1), got {decay}")
    return lambda: exp_schedule(start, decay, clock())


def beta_schedule_of(x: Any) -> str:
    """The schedule of an exploration config's ``beta``: ``x.beta_schedule``, or for ``None`` linear
    when ``x.beta_end`` is given, else constant."""
    if x.beta_schedule is not None:
        return x.beta_schedule
    return "constant" if x.beta_end is None else "linear"


__all__ = ["SCHEDULES", "beta_schedule_of", "exp_schedule", "linear_schedule", "make_schedule"]
