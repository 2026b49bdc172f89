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

**Each strategy owns its config.** ``register_strategy(name, builder, schema)`` brings a dataclass of the
strategy's own keys beyond :class:`CommonConfig` (their defaults are its neutral values) with a
``check(config, limits, active)`` of them. The run's ``exploration`` section (``ExplorationConfig``,
:func:`exploration_config_class`) is :class:`CommonConfig` plus every registered schema's keys, one flat
namespace a Hydra group entry (``conf/exploration/<name>.yaml``) sets; :func:`check_exploration` runs the
checks; :func:`owned_keys` tells the fingerprint which keys the active strategy owns. A key whose field
metadata says ``exclusive`` is refused off its default under another strategy.

Nothing here knows the crowd: the network is any module with a ``head`` (the surgeries' target),
the feature encoder of a bonus comes from :class:`ReplayContext`.
"""

from __future__ import annotations

import contextlib
import dataclasses
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
        ones) without learning or logging from it; ``None`` without such a reward. The batch is shaped
        ``[n, g]``: ``g`` transitions from each of ``n`` sampled states (counterfactual actions)."""
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


@dataclass
class CommonConfig:
    """The keys every strategy reads: its ``name`` and the ε schedule (``eps_start`` -> ``eps_end`` over
    ``anneal_frames`` frames; the variants that explore otherwise set ε to 0)."""

    name: str = "egreedy"
    eps_start: float = 0.5
    eps_end: float = 0.1
    anneal_frames: int = 40_000  # the demo's; the paper's 4000 episodes (200k) in exploration/*.yaml

    @staticmethod
    def check(config: Any, limits: "Limits", active: bool) -> None:
        if not 0 <= config.eps_end <= config.eps_start <= 1:
            raise ValueError(f"eps_start/eps_end: need 0 <= eps_end <= eps_start <= 1, got {config.eps_start} -> "
                             f"{config.eps_end}")
        if config.anneal_frames < 1:
            raise ValueError(f"anneal_frames: must be >= 1, got {config.anneal_frames}")


@dataclass(frozen=True)
class Limits:
    """What a schema's checks may read from the rest of the run: the learner's batch size and discount."""

    batch_size: int
    gamma: float


_BUILDERS: dict[str, Builder] = {}
_SCHEMAS: dict[str, type | None] = {}
_SEALED: list[type] = []  # the ExplorationConfig built (by crowdrl.training's schema): no new key after it


def _fields(schema: type | None) -> list[dataclasses.Field]:
    return list(dataclasses.fields(schema)) if schema is not None else []


def register_strategy(name: str, builder: Builder, schema: type | None = None) -> None:
    """Make ``make_strategy`` build ``builder(config)`` for ``config.name == name``; ``schema``: the dataclass of
    the strategy's own keys (``None``: only :class:`CommonConfig`'s), with an optional
    ``check(config, limits, active)`` raising ``ValueError("<key>: ...")``. A key two schemas share must be
    declared alike (type and default). Register before ``crowdrl.training`` builds the run's config schema."""
    if name in _BUILDERS and _BUILDERS[name] is not builder:
        raise ValueError(f"an exploration strategy named {name!r} is already registered")
    if schema is not None and not dataclasses.is_dataclass(schema):
        raise TypeError(f"register_strategy({name!r}): schema must be a dataclass type, got {schema!r}")
    known = {f.name: f for f in _all_fields()}
    for f in _fields(schema):
        if f.name in known and (known[f.name].type, known[f.name].default) != (f.type, f.default):
            raise ValueError(f"register_strategy({name!r}): key {f.name!r} is declared otherwise by another strategy")
    if _SEALED and any(f.name not in known for f in _fields(schema)):
        raise RuntimeError(f"register_strategy({name!r}): the run's exploration schema is already built; import the "
                           f"module that registers {name!r} before crowdrl.training")
    _BUILDERS[name] = builder
    _SCHEMAS[name] = schema


def _all_fields() -> list[dataclasses.Field]:
    """:class:`CommonConfig`'s fields, then each registered schema's new ones, in registration order."""
    out = {f.name: f for f in dataclasses.fields(CommonConfig)}
    for schema in _SCHEMAS.values():
        for f in _fields(schema):
            out.setdefault(f.name, f)
    return list(out.values())


def exploration_config_class() -> type:
    """The run's ``exploration`` section: a dataclass of :class:`CommonConfig`'s keys and every registered
    schema's (built once; a registration that adds keys afterwards is refused)."""
    if _SEALED:
        return _SEALED[0]

    def copied(f: dataclasses.Field) -> tuple:
        default = (dataclasses.field(default=f.default, metadata=f.metadata) if f.default is not dataclasses.MISSING
                   else dataclasses.field(default_factory=f.default_factory, metadata=f.metadata))
        return f.name, f.type, default

    cls = dataclasses.make_dataclass("ExplorationConfig", [copied(f) for f in _all_fields()])
    cls.__module__ = __name__  # its annotations resolve here
    cls.__doc__ = ("Exploration variant (``docs/mdp.md``, \"Exploration variants\"): :class:`CommonConfig`'s keys and "
                   "those of every registered strategy's schema (" + ", ".join(_SCHEMAS) + ").")
    _SEALED.append(cls)
    return cls


def owned_keys(name: str) -> dict[str, Any]:
    """The keys strategy ``name`` owns beyond :class:`CommonConfig`'s, with their defaults (its neutral values)."""
    return {f.name: f.default for f in _fields(_SCHEMAS.get(name))}


def check_exploration(config: Any, limits: Limits) -> None:
    """Every schema's checks (``active``: the schema is the named strategy's), then the exclusive keys: one set
    off its default while another strategy runs is refused; ``ValueError`` ``"<key>: ..."``."""
    if config.name not in _BUILDERS:
        raise ValueError(f"name: got {config.name!r}; allowed: {', '.join(strategy_names())}")
    CommonConfig.check(config, limits, True)
    done: set[type] = set()
    for name, schema in _SCHEMAS.items():
        if schema is None or schema in done:
            continue
        done.add(schema)
        owners = [n for n, s in _SCHEMAS.items() if s is schema]
        if hasattr(schema, "check"):
            schema.check(config, limits, config.name in owners)
    for f in _all_fields():
        owners = [n for n, s in _SCHEMAS.items() if f.name in owned_keys(n)]
        if f.metadata.get("exclusive") and config.name not in owners and getattr(config, f.name) != f.default:
            raise ValueError(f"{f.name}: applies to {', '.join(owners)} only; exploration.name is {config.name!r}")


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

__all__ = ["CommonConfig", "ExplorationStrategy", "Limits", "ReplayContext", "check_exploration", "exploration_config_class",
           "make_strategy", "owned_keys", "register_strategy", "strategy_names"]
