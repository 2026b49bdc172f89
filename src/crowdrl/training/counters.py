"""A run's progress counters: what a checkpoint must hold to resume the loop where it stopped."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

TIMER_COUNTERS = ("collect_s", "update_s", "validate_s")


@dataclass
class Counters:
    """Frames, updates and episodes so far, the update credit not yet spent, the next training episode id,
    the best validation score and its frames, the frames of the last validation and checkpoint, and the
    seconds spent collecting, updating and validating up to the checkpoint (a resumed run's timers count
    the whole run)."""

    frames: int = 0
    updates: int = 0
    episodes: int = 0
    update_credit: float = 0.0
    next_train_episode: int = 0
    best_val: float = -math.inf
    best_frames: int = -1
    last_val: int = 0
    last_checkpoint: int = 0
    collect_s: float = 0.0
    update_s: float = 0.0
    validate_s: float = 0.0
    # the oracle's demonstrations (train.demonstrations): transitions stored before the first collected batch,
    # and the seconds spent solving and playing them (not frames)
    demo_transitions: int = 0
    demo_s: float = 0.0

    def timers(self) -> dict[str, float]:
        """The seconds spent so far as ``{"collect": ..., "update": ..., "validate": ...}``, and ``"demo"``
        (the oracle's demonstrations) in a run that has them."""
        out = {name.removesuffix("_s"): getattr(self, name) for name in TIMER_COUNTERS}
        if self.demo_s > 0:
            out["demo"] = self.demo_s
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Counters":
        """The counters of a checkpoint; ``ValueError`` naming a missing or unknown counter (the timers
        and the demonstrations' counters, which not every checkpoint has, are 0 in one without them)."""
        names = {f.name for f in fields(cls)}
        data = {**dict.fromkeys(TIMER_COUNTERS, 0.0), "demo_transitions": 0, "demo_s": 0.0, **data}
        if set(data) != names:
            raise ValueError(f"its counters differ from this code's: missing {sorted(names - set(data))}, "
                             f"unknown {sorted(set(data) - names)}")
        return cls(**data)


__all__ = ["Counters", "TIMER_COUNTERS"]
