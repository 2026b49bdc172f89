"""Factories of a run, in the TorchRL ``sota-implementations`` style: ``make_env``,
``make_actor``, ``make_exploration``, ``make_loss``, ``make_buffer``, ``make_update_part``,
``make_learner``, ``make_collector``. Each takes its config section and the run's
:class:`~crowdrl.training.facts.RunFacts` (derived once); ``make_env`` and ``make_actor`` take the
run, as every evaluation calls them.

Training, validation, the final test and ``experiments/evaluate.py`` build their envs with the
same :func:`make_env` and act with the same actor, so there is one rollout path
(:func:`crowdrl.evaluation.evaluate`).
"""

from __future__ import annotations

from typing import Any, Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.envs import CrowdNavEnv, RobotCentric
from crowdrl.envs.mix import ScenarioMixEnv, mix_rows
from crowdrl.exploration import ExplorationStrategy, ReplayContext
from crowdrl.training.acting import GreedyActing, make_acting
from crowdrl.training.config import RunConfig, TrainConfig, crowd_config, sees_obstacles, trained_scenarios
from crowdrl.training.counterfactual import CounterfactualExperience
from crowdrl.training.facts import RunFacts
from crowdrl.training.learner import D3QNLearner
from crowdrl.training.loss import D3QNLoss
from crowdrl.training.nstep import NStepReturn
from crowdrl.training.parts import ReplayOnly, UpdatePart


def make_env(run: RunConfig, *, split: str = "train", num_envs: int | None = None, seed: int | None = None,
             scenario: str | None = None, num_humans: int | None = None,
             robot_kinematics: str = "unicycle") -> TransformedEnv:
    """``CrowdNavEnv`` + the robot-centric state (the env itself counts steps and sums the return, so
    that its snapshot holds them: a resumed run continues its in-flight episodes exactly).

    Training uses the ``train`` stream of the run seed; validation the ``val`` stream of the run
    seed; tests the ``test`` stream of the evaluation seed (``seed``), possibly on another
    ``scenario`` or crowd size than training. A run with ``env.mix`` trains and validates on a
    :class:`~crowdrl.envs.mix.ScenarioMixEnv` of its scenarios (``scenario`` not given); tests, and any
    ``scenario`` given, play one scenario alone (``env.scenario`` by default).
    """
    n, seed = num_envs or run.train.num_envs, run.seed if seed is None else seed
    if run.env.mix and scenario is None and split != "test":  # one agent for several scenarios, each on its stream
        names = trained_scenarios(run)
        configs = {name: crowd_config(run, scenario=name, num_humans=num_humans, robot_kinematics=robot_kinematics)
                   for name in names}
        rows = mix_rows({name: run.env.mix[name] for name in names}, n)
        base: EnvBase = ScenarioMixEnv(configs, rows, seed=seed, split=split, device=run.device)
    else:
        cfg = crowd_config(run, scenario=scenario, num_humans=num_humans, robot_kinematics=robot_kinematics)
        base = CrowdNavEnv(cfg.scenario, num_envs=n, num_humans=cfg.num_humans, config=cfg, seed=seed, split=split,
                           device=run.device)
    return TransformedEnv(base, Compose(RobotCentric(entities=sees_obstacles(run))))


def make_actor(run: RunConfig, env: EnvBase, net: torch.nn.Module,
               predictor: torch.nn.Module | None = None) -> TensorDictModuleBase:
    """The actor of a trained ``net`` for ``env``, as training acts (:func:`~crowdrl.training.acting.make_acting`):
    the greedy Q actor (``QValueActor``, reading the humans' mask when ``env``'s crowd size varies: one network
    serves any crowd), or, with ``planning.enabled``, the :class:`~crowdrl.policies.OnlinePlanner` of ``net`` and
    its crowd ``predictor`` (required then). With ``train.compile_acting`` the actor calls ``net`` (and the
    predictor) through ``torch.compile``."""
    if run.planning.enabled and predictor is None:
        raise ValueError("planning.enabled: the planner needs its crowd predictor (make_predictor_of)")
    return make_acting(run.planning, RunFacts.of(run), train=run.train, encoder=run.encoder.name,
                       predictor=predictor).actor(net, env)


def make_exploration(env: EnvBase, actor: TensorDictModuleBase, strategy: ExplorationStrategy) -> TensorDictSequential:
    """The acting policy of ``strategy`` (the one that modified the actor's network): ``actor`` then
    ε-greedy (ε = 0 for the variants that explore otherwise).

    Under ``ExplorationType.DETERMINISTIC`` (evaluation) the ε-greedy step passes the greedy
    action through, so the same policy serves collection and evaluation. ε is set by
    ``strategy.schedule(frames)``.
    """
    return strategy.policy(actor, env.action_spec)


def make_loss(train: TrainConfig, net: torch.nn.Module, facts: RunFacts) -> D3QNLoss:
    """Double dueling DQN loss on n-step transitions of the networks' observation keys, with its target network."""
    return D3QNLoss(net, facts.obs_keys, gamma=train.gamma, double=True, compile=train.compile_loss,
                    huber_delta=train.huber_delta)


def make_buffer(train: TrainConfig, facts: RunFacts, strategy: ExplorationStrategy | None = None,
                context: ReplayContext | None = None, one_step_key: str | None = None) -> TensorDictReplayBuffer:
    """The replay buffer of the networks' observations: n-step returns when a batch is written (keeping
    ``s_{t+1}`` under ``one_step_key`` too, :func:`~crowdrl.training.variants.successor_key`), then what the
    exploration ``strategy`` does to a sampled batch (ICM/RE3: the intrinsic bonus), its transform built from
    ``context`` (:func:`~crowdrl.training.variants.replay_context`)."""
    transform: Transform = NStepReturn(train.n_step, train.gamma, facts.obs_keys, one_step_key=one_step_key)
    extra = strategy.replay_transform(context) if strategy is not None else None
    if extra is not None:
        transform = Compose(transform, extra)
    return TensorDictReplayBuffer(storage=LazyTensorStorage(train.buffer_size, device=facts.device),
                                  batch_size=train.batch_size, transform=transform)


def make_update_part(train: TrainConfig, net: torch.nn.Module, facts: RunFacts,
                     reward_bonus: Callable[[TensorDictBase], TensorDictBase] | None = None,
                     one_step_key: str | None = None) -> UpdatePart:
    """The gradient steps of one update (:mod:`crowdrl.training.parts`): the sampled batch alone, or with
    ``train.counterfactual.mode`` its counterfactual transitions too (``reward_bonus``, the exploration
    strategy's, added to them; it reads their successor under ``one_step_key`` where :func:`make_buffer` stores
    it, :func:`~crowdrl.training.variants.successor_key`)."""
    c = train.counterfactual
    if c.mode == "off":
        return ReplayOnly()
    return CounterfactualExperience(facts.crowd, net, facts.obs_keys, mode=c.mode, actions=c.actions, k=c.k,
                                    weight=c.weight, entities=facts.entities, seed=3_000_017 * (facts.seed + 1),
                                    reward_bonus=reward_bonus, one_step_key=one_step_key,
                                    obstacle_tokens=facts.obstacle_tokens, compile=train.compile_acting)


def make_learner(train: TrainConfig, net: torch.nn.Module, facts: RunFacts, strategy: ExplorationStrategy,
                 acting: GreedyActing, one_step_key: str | None = None) -> D3QNLearner:
    """The Q network's learner (:class:`~crowdrl.training.learner.D3QNLearner`): the loss, Adam (fused: one
    kernel for all parameters, cheaper than the per-tensor loop on CPU; docs/benchmarks.md), the update part,
    the auxiliary learners in the order they step (the ``strategy``'s, then the ``acting`` part's: the
    planner's crowd predictor), the strategy's hook before each update, the gradient clip, the target rule
    (Polyak ``train.target_tau`` < 1, else a hard copy every ``train.target_update_frames`` frames of updates)
    and the learning-rate schedule. ``one_step_key``: where the buffer keeps ``s_{t+1}`` for the bonus."""
    loss = make_loss(train, net, facts)
    optimizer = torch.optim.Adam(net.parameters(), lr=train.lr, fused=True)
    learners: list[AuxiliaryLearner] = [*strategy.learners(), *acting.learners()]
    part = make_update_part(train, net, facts, strategy.reward_bonus(), one_step_key)
    return D3QNLearner(loss, optimizer, part, learners, before_update=strategy.before_update,
                       grad_clip_norm=train.grad_clip_norm, target_tau=train.target_tau,
                       updates_per_copy=max(1, round(train.target_update_frames * max(train.updates_per_frame, 1e-9))),
                       lr=None if train.lr_end is None else (train.lr, train.lr_end, train.total_frames))


def buffer_state_dict(buffer: TensorDictReplayBuffer) -> dict[str, Any]:
    """``buffer.state_dict()`` with the storage's slots never written set to zero: the storage is
    allocated uninitialised (``torch.empty``), so those bytes would differ between identical runs
    and make their ``last.pt`` differ. The slots are zeroed in place (no copy of the buffer): nothing
    reads a slot before it is written."""
    state = buffer.state_dict()
    storage = state.get("_storage", {})
    written = storage.get("_len")

    def zero_tail(node: Any) -> None:  # the storage: a (nested) dict of [capacity, ...] tensors
        if isinstance(node, torch.Tensor):
            node[written:].zero_()
        elif isinstance(node, dict):
            for value in node.values():
                zero_tail(value)

    if isinstance(written, int):
        zero_tail(storage.get("_storage"))
    return state


def make_collector(train: TrainConfig, env: EnvBase, policy: TensorDictModule, device: str) -> Collector:
    """A single-process collector of ``num_envs x steps_per_batch`` frames per batch."""
    return Collector(env, policy, frames_per_batch=train.num_envs * train.steps_per_batch, total_frames=-1,
                     device=device, auto_register_policy_transforms=False)


__all__ = ["buffer_state_dict", "make_actor", "make_buffer", "make_collector", "make_env", "make_exploration",
           "make_learner", "make_loss", "make_update_part"]
