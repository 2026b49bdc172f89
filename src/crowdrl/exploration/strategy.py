"""What an exploration variant adds to a DQN learner, as one interface, and the registry of variants.

A strategy may change the Q network when it is built (:meth:`ExplorationStrategy.modify_network`:
a noisy head, action dropout), wraps the greedy actor into the acting policy
(:meth:`~ExplorationStrategy.policy`: ε-greedy for every variant, ε = 0 for those that explore
otherwise), may add a transform to the replay buffer's sampling (:meth:`~ExplorationStrategy.replay_transform`:
an intrinsic bonus) and auxiliary learners trained on the sampled batches
(:meth:`~ExplorationStrategy.learners`), and acts at fixed points of the training loop::

    strategy.schedule(frames)                 # start of training: ε, dropout p at this frame count
    for batch in collector:
        ...; strategy.before_update(loss)     # each update (noisy: fresh online and target noise)
        strategy.before_collection(frames)    # after the batch's updates (schedules; noisy: fresh noise)
    with strategy.evaluating(): ...           # greedy evaluation (noisy: the mean weights)

It logs :meth:`~ExplorationStrategy.scalars` and saves :meth:`~ExplorationStrategy.state_dict` (top-level
keys of the checkpoint). ``make_strategy(config)`` builds the strategy named ``config.name`` from
the builders registered with :func:`register_strategy` (each variant's module registers its own).

Nothing here knows the crowd: the network is any module with a ``head`` (the surgeries' target),
the feature encoder of a bonus comes from :class:`ReplayContext`.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, Callable, ContextManager

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs import Transform
from torchrl.modules import EGreedyModule

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.exploration.schedule import linear_schedule


@dataclass
class ReplayContext:
    """What a strategy's replay transform may need from the run.

    ``next_obs_keys``: where the one-step successor ``s_{t+1}`` of each of ``obs_keys`` lies in a
    sampled batch; ``frames()``: the frame count (the clock of scheduled coefficients);
    ``make_encoder()``: a fresh feature encoder of the agent's architecture; ``seed``: the seed of
    the strategy's own parameters (built without touching the global RNG).
    """

    obs_keys: list[NestedKey]
    next_obs_keys: list[NestedKey]
    num_actions: int
    gamma: float
    frames: Callable[[], int]
    make_encoder: Callable[[], nn.Module]
    seed: int
    device: torch.device | str = "cpu"


class ExplorationStrategy:
    """ε-greedy exploration, and the interface of every strategy (see the module docstring).

    ``config`` holds ``eps_start``, ``eps_end`` and ``anneal_frames`` (ε decays linearly from start
    to end over ``anneal_frames`` frames), and whatever its subclass reads.
    """

    #: whether :meth:`replay_transform` reads ``s_{t+1}`` (an n-step buffer must then keep it)
    reads_successor: bool = False

    def __init__(self, config: Any) -> None:
        self.config = config
        self.egreedy: EGreedyModule | None = None

    def modify_network(self, net: nn.Module) -> nn.Module:
        """Change the freshly built Q network in place (plain ε-greedy: nothing); returns it."""
        return net

    def policy(self, actor: TensorDictModuleBase, action_spec: TensorSpec) -> TensorDictSequential:
        """The acting policy: ``actor`` then ε-greedy. Under ``ExplorationType.DETERMINISTIC``
        (evaluation) the ε-greedy step passes the greedy action through. ε is set by
        :meth:`schedule`, never by the module's own annealing."""
        x = self.config
        self.egreedy = EGreedyModule(action_spec, eps_init=x.eps_start, eps_end=x.eps_start)
        return TensorDictSequential(actor, self.egreedy)

    def replay_transform(self, context: ReplayContext) -> Transform | None:
        """The transform applied to each sampled batch (none), built once."""
        return None

    def reward_bonus(self) -> Callable[[TensorDictBase], TensorDictBase] | None:
        """Adds the exploration reward to a batch of transitions built from a sample (e.g. simulated
        ones) without learning or logging from it; ``None`` without such a reward."""
        return None

    def learners(self) -> list[AuxiliaryLearner]:
        """Models trained beside the Q network on each sampled batch (none)."""
        return []

    def schedule(self, frames: int) -> None:
        """Set the scheduled coefficients (ε) to their value at ``frames``."""
        x = self.config
        self._egreedy().eps.fill_(linear_schedule(x.eps_start, x.eps_end, x.anneal_frames, frames))

    def before_collection(self, frames: int) -> None:
        """After a collected batch's updates, before the next collection: :meth:`schedule`."""
        self.schedule(frames)

    def before_update(self, loss: nn.Module) -> None:
        """Before each update of ``loss`` (its online and target networks): nothing."""

    def evaluating(self) -> ContextManager:
        """Context for greedy evaluation (nothing to change)."""
        return contextlib.nullcontext()

    def scalars(self) -> dict[str, float]:
        """Scalars to log (``train/<name>``)."""
        return {"epsilon": float(self._egreedy().eps)}

    def progress(self) -> dict[str, str]:
        """What the progress bar shows."""
        return {"eps": f"{float(self._egreedy().eps):.3f}"}

    def state_dict(self) -> dict[str, Any]:
        """Top-level checkpoint keys this strategy writes (ε is a function of the frame count: none)."""
        return {}

    def load_state_dict(self, payload: dict[str, Any]) -> None:
        """Restore from a checkpoint ``payload`` the keys :meth:`state_dict` wrote."""

    def _egreedy(self) -> EGreedyModule:
        if self.egreedy is None:
            raise RuntimeError(f"{type(self).__name__}: build the acting policy (policy()) first")
        return self.egreedy


Builder = Callable[[Any], ExplorationStrategy]
_BUILDERS: dict[str, Builder] = {}


def register_strategy(name: str, builder: Builder) -> None:
    """Make ``make_strategy`` build ``builder(config)`` for ``config.name == name``."""
    if name in _BUILDERS and _BUILDERS[name] is not builder:
        raise ValueError(f"an exploration strategy named {name!r} is already registered")
    _BUILDERS[name] = builder


def strategy_names() -> tuple[str, ...]:
    """The registered strategy names."""
    return tuple(_BUILDERS)


def make_strategy(config: Any) -> ExplorationStrategy:
    """The strategy of an exploration config (its ``name`` picks the registered builder)."""
    try:
        builder = _BUILDERS[config.name]
    except KeyError:
        raise ValueError(f"exploration: unknown strategy {config.name!r}; registered: "
                         f"{', '.join(strategy_names())}") from None
    return builder(config)


register_strategy("egreedy", ExplorationStrategy)

__all__ = ["ExplorationStrategy", "ReplayContext", "make_strategy", "register_strategy", "strategy_names"]
