"""Intrinsic-reward exploration (ICM, RE3) as an :class:`~crowdrl.exploration.strategy.ExplorationStrategy`.

The strategy puts an :class:`~crowdrl.exploration.intrinsic.IntrinsicRewardTransform` in the replay
buffer: every sampled batch gets ``r = r_ext + beta * r_in``, ``r_in`` computed with the bonus's
networks as they are. The bonus's own step (ICM's forward and inverse models) is an auxiliary
learner, :class:`BonusLearner`, that the trainer steps on the same sampled batch before the Q
update. With n-step returns (n > 1) the bonus is that of the window's first transition
``(s_t, a_t, s_{t+1})``, so the strategy asks the buffer to keep ``s_{t+1}``
(:attr:`~IntrinsicExploration.reads_successor`).

``config`` holds ``beta``, ``beta_schedule``/``beta_end``/``beta_decay``, ``anneal_frames`` and the
stable-bonus options (``reward_norm``, ``reward_center``, ``reward_clip``, ``obs_norm``,
``obs_clip``, ``terminal_value``), plus what its bonus reads (``icm_*``, ``re3_k``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable, Iterable

from tensordict import TensorDictBase
from torch import Tensor, nn

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.exploration.icm import FEATURE_NORMS, ICM
from crowdrl.exploration.intrinsic import IntrinsicBonus, IntrinsicRewardTransform, seeded_init
from crowdrl.exploration.normalize import ObservationNormalizer, RewardNormalizer
from crowdrl.exploration.re3 import RE3
from crowdrl.exploration.schedule import beta_schedule_of, make_schedule
from crowdrl.exploration.strategy import ExplorationStrategy, ReplayContext, register_strategy

#: ``make_bonus(config, encoder, context)``: the bonus on its own feature encoder
BonusBuilder = Callable[[Any, nn.Module, ReplayContext], IntrinsicBonus]


class BonusLearner(AuxiliaryLearner):
    """The bonus's training step on the batch its transform scored last (the sample the trainer
    passes): :meth:`IntrinsicRewardTransform.learn_from_last`. Its scalars are logged with the
    strategy's (``intrinsic_*``); the bonus and its optimiser are saved by the strategy."""

    def __init__(self, transform: IntrinsicRewardTransform) -> None:
        self.transform = transform

    def step(self, sample: TensorDictBase) -> dict[str, float]:
        self.transform.learn_from_last()
        return {}

    def parameters(self) -> Iterable[Tensor]:
        return [p for p in self.transform.bonus.parameters() if p.requires_grad]


class IntrinsicExploration(ExplorationStrategy):
    """ε-greedy acting (ε = 0 in the shipped configs) plus an intrinsic bonus built by ``make_bonus``."""

    reads_successor = True

    def __init__(self, config: Any, make_bonus: BonusBuilder) -> None:
        super().__init__(config)
        self.make_bonus = make_bonus
        self.bonus: IntrinsicBonus | None = None
        self.transform: IntrinsicRewardTransform | None = None

    def replay_transform(self, context: ReplayContext) -> IntrinsicRewardTransform:
        """The bonus on a fresh feature encoder of the agent's architecture (both initialised from
        ``context.seed`` without touching the global RNG, so a ``beta = 0`` run follows the
        extrinsic-only run bit for bit) and its sample-time transform."""
        x = self.config
        with seeded_init(context.seed):
            encoder = context.make_encoder()
        self.bonus = self.make_bonus(x, encoder, context).to(context.device)
        beta = make_schedule(beta_schedule_of(x), x.beta, end=x.beta_end, duration=x.anneal_frames,
                             decay=x.beta_decay, clock=context.frames)
        reward_norm = RewardNormalizer(x.reward_norm, center=x.reward_center, clip=x.reward_clip)
        self.transform = IntrinsicRewardTransform(
            self.bonus, beta, obs_keys=context.obs_keys, next_obs_keys=context.next_obs_keys, update_bonus=False,
            obs_norm=ObservationNormalizer(clip=x.obs_clip) if x.obs_norm else None,
            reward_norm=None if reward_norm.is_identity else reward_norm,
            terminal_value_gamma=context.gamma if x.terminal_value else None)
        return self.transform

    def reward_bonus(self) -> Callable[[TensorDictBase], TensorDictBase]:
        transform = self._transform()
        return lambda td: transform.add_bonus(td, learn=False, record=False, grouped=True)

    def learners(self) -> list[AuxiliaryLearner]:
        return [BonusLearner(self._transform())]

    def scalars(self) -> dict[str, float]:
        return {**super().scalars(), **{f"intrinsic_{k}": v for k, v in self._transform().last_stats.items()}}

    def state_dict(self) -> dict[str, Any]:
        """The bonus, its optimiser (if it learns), the options' running statistics and the last
        batch's scalars (``bonus``, ``bonus_optimizer``, ``intrinsic_norm``, ``intrinsic_stats``)."""
        transform = self._transform()
        payload = {"intrinsic_stats": dict(transform.last_stats), "intrinsic_norm": transform.stats_state_dict(),
                   "bonus": self.bonus.state_dict()}
        if getattr(self.bonus, "optimizer", None) is not None:
            payload["bonus_optimizer"] = self.bonus.optimizer.state_dict()
        return payload

    def load_state_dict(self, payload: dict[str, Any]) -> None:
        transform = self._transform()
        if payload.get("intrinsic_stats") is not None:
            transform.last_stats = dict(payload["intrinsic_stats"])
        transform.load_stats_state_dict(payload["intrinsic_norm"])
        self.bonus.load_state_dict(payload["bonus"])
        if "bonus_optimizer" in payload:
            self.bonus.optimizer.load_state_dict(payload["bonus_optimizer"])

    def _transform(self) -> IntrinsicRewardTransform:
        if self.transform is None:
            raise RuntimeError(f"{type(self).__name__}: build the replay transform (replay_transform()) first")
        return self.transform


def icm_bonus(x: Any, encoder: nn.Module, context: ReplayContext) -> ICM:
    """ICM on ``encoder`` (``x.icm_lr``, ``x.icm_detach_target``, ``x.icm_feature_norm``)."""
    return ICM(encoder, context.num_actions, context.obs_keys, lr=x.icm_lr, detach_target=x.icm_detach_target,
               feature_norm=x.icm_feature_norm, seed=context.seed + 1)


def re3_bonus(x: Any, encoder: nn.Module, context: ReplayContext) -> RE3:
    """RE3 on ``encoder`` (``x.re3_k``)."""
    return RE3(encoder, context.obs_keys, k=x.re3_k, seed=context.seed + 1)


ONLY = {"exclusive": True}  # refused off its default under a strategy that does not own it


@dataclass
class IntrinsicConfig:
    """The keys ICM and RE3 share: ``r = r_ext + β r_in`` with β's schedule (``constant``; ``linear`` to
    ``beta_end`` over ``anneal_frames``; ``exp``: ``β (1 - beta_decay)^frames``; null: linear when ``beta_end`` is
    given, else constant) and the stable-bonus options of :class:`IntrinsicRewardTransform` (``docs/mdp.md``,
    "Intrinsic-reward options"; the defaults are the method as published)."""

    beta: float = 0.01
    beta_end: float | None = None
    beta_schedule: str | None = field(default=None, metadata=ONLY)
    beta_decay: float | None = field(default=None, metadata=ONLY)
    reward_norm: str = field(default="none", metadata=ONLY)  # none | std (running) | batch (standardised per batch)
    reward_center: bool = field(default=False, metadata=ONLY)  # r_in minus its mean: no net per-step bonus
    reward_clip: float | None = field(default=None, metadata=ONLY)  # clip the normalised r_in to [-c, c]
    obs_norm: bool = field(default=False, metadata=ONLY)  # the bonus's inputs whitened, clipped to ±obs_clip
    obs_clip: float = field(default=5.0, metadata=ONLY)
    terminal_value: bool = field(default=False, metadata=ONLY)  # terminal transitions get β γ^m mean(r_in) / (1 - γ)

    @staticmethod
    def check(x: Any, limits: Any, active: bool) -> None:
        from crowdrl.exploration.normalize import REWARD_SCALES
        from crowdrl.exploration.schedule import SCHEDULES

        if x.beta < 0:
            raise ValueError(f"beta: must be >= 0, got {x.beta}")
        if x.beta_end is not None and x.beta_end < 0:
            raise ValueError(f"beta_end: must be >= 0 or null, got {x.beta_end}")
        if x.beta_schedule is not None and x.beta_schedule not in SCHEDULES:
            raise ValueError(f"beta_schedule: got {x.beta_schedule!r}; allowed: {', '.join(SCHEDULES)} or null")
        schedule = beta_schedule_of(x)
        if schedule == "linear" and x.beta_end is None:
            raise ValueError("beta_end: beta_schedule=linear needs exploration.beta_end (the value reached after "
                             "exploration.anneal_frames)")
        if schedule != "linear" and x.beta_end is not None:
            raise ValueError(f"beta_end: is set ({x.beta_end}) but beta_schedule={schedule} does not use it; use "
                             f"beta_schedule=linear or beta_end=null")
        if schedule == "exp" and x.beta_decay is None:
            raise ValueError("beta_decay: beta_schedule=exp needs exploration.beta_decay (β_t = β (1 - beta_decay)^frames)")
        if schedule != "exp" and x.beta_decay is not None:
            raise ValueError(f"beta_decay: is set ({x.beta_decay}) but beta_schedule={schedule} does not use it; use "
                             f"beta_schedule=exp or beta_decay=null")
        if x.beta_decay is not None and not 0 <= x.beta_decay < 1:
            raise ValueError(f"beta_decay: must lie in [0, 1), got {x.beta_decay}")
        if x.reward_norm not in REWARD_SCALES:
            raise ValueError(f"reward_norm: got {x.reward_norm!r}; allowed: {', '.join(REWARD_SCALES)}")
        if x.reward_clip is not None and x.reward_clip <= 0:
            raise ValueError(f"reward_clip: must be > 0 or null, got {x.reward_clip}")
        if x.obs_clip <= 0:
            raise ValueError(f"obs_clip: must be > 0, got {x.obs_clip}")
        if x.terminal_value and limits.gamma >= 1:
            raise ValueError(f"terminal_value: values the forgone bonus as mean / (1 - gamma): needs train.gamma < 1, "
                             f"got {limits.gamma}")


@dataclass
class ICMConfig(IntrinsicConfig):
    """``exploration=icm``: the shared intrinsic keys, ICM's Adam learning rate and its feature options."""

    icm_lr: float = 1e-4
    icm_feature_norm: str = field(default="none", metadata=ONLY)  # none | layernorm: φ ends with a gain-free LayerNorm
    icm_detach_target: bool = field(default=True, metadata=ONLY)  # false: the forward loss reaches φ(s') too

    @staticmethod
    def check(x: Any, limits: Any, active: bool) -> None:
        IntrinsicConfig.check(x, limits, active)
        if x.icm_lr <= 0:
            raise ValueError(f"icm_lr: must be > 0, got {x.icm_lr}")
        if x.icm_feature_norm not in FEATURE_NORMS:
            raise ValueError(f"icm_feature_norm: got {x.icm_feature_norm!r}; allowed: {', '.join(FEATURE_NORMS)}")


@dataclass
class RE3Config(IntrinsicConfig):
    """``exploration=re3``: the shared intrinsic keys and the k of the k-nearest-neighbour bonus."""

    re3_k: int = 3

    @staticmethod
    def check(x: Any, limits: Any, active: bool) -> None:
        IntrinsicConfig.check(x, limits, active)
        if x.re3_k < 1:
            raise ValueError(f"re3_k: must be >= 1, got {x.re3_k}")
        if active and x.re3_k >= limits.batch_size:
            raise ValueError(f"re3_k: must lie in 1..train.batch_size-1 ({limits.batch_size - 1}), got {x.re3_k}")


#: the stable-bonus options (the keys refused off their default under a non-intrinsic strategy)
INTRINSIC_OPTIONS = tuple(f.name for f in fields(ICMConfig) if f.metadata.get("exclusive"))

register_strategy("icm", lambda config: IntrinsicExploration(config, icm_bonus), ICMConfig)
register_strategy("re3", lambda config: IntrinsicExploration(config, re3_bonus), RE3Config)

__all__ = ["BonusLearner", "ICMConfig", "INTRINSIC_OPTIONS", "IntrinsicConfig", "IntrinsicExploration", "RE3Config",
           "icm_bonus", "re3_bonus"]
