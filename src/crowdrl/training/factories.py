"""Factories of a run, in the TorchRL ``sota-implementations`` style: ``make_env``,
``make_actor``, ``make_exploration``, ``make_loss``, ``make_learner``, ``make_buffer``,
``make_learners``, ``make_collector``.

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

from crowdrl.envs import CrowdNavEnv, RobotCentric
from crowdrl.evaluation.rollout import crowd_env_of
from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.exploration import ExplorationStrategy, ReplayContext
from crowdrl.exploration.intrinsic import seeded_init
from crowdrl.models import make_q_actor
from crowdrl.compile import CompiledModule
from crowdrl.models.predictor import make_predictor
from crowdrl.policies import OnlinePlanner
from crowdrl.sim.config import CrowdConfig
from crowdrl.training.config import RunConfig, crowd_config, sees_obstacles
from crowdrl.training.learner import D3QNLearner
from crowdrl.training.loss import D3QNLoss
from crowdrl.training.counterfactual import CounterfactualExperience
from crowdrl.training.nstep import NStepReturn
from crowdrl.training.parts import ReplayOnly, UpdatePart
from crowdrl.training.predictor_learner import PredictorLearner
from crowdrl.training.variants import successor_key

OBS_KEYS = ("robot_rc", "humans_rc")
MASK_KEY = "humans_mask"  # [B, N] bool, True = present: read by the networks when crowds vary in size
# what a network trained among obstacles reads: the humans and the observed obstacle edges as tokens
ENTITY_OBS_KEYS = ("robot_rc", *RobotCentric.ENTITY_KEYS)
# what the learned crowd predictor trains on: world-frame states and the real next human states (one
# step later: the n-step transform moves only the observation keys), plus the humans' mask where the
# crowd size varies (``obs_keys``), as the planner reads it when acting
PREDICTOR_KEYS = ["robot", "humans", ("next", "humans")]


def obs_keys(cfg: CrowdConfig, obstacles: bool | None = None) -> tuple[str, ...]:
    """What the networks read from an env of ``cfg``: the robot-centric states, and the humans' mask
    when the crowd size varies (a fixed crowd has every human present); with ``obstacles`` (default:
    whether ``cfg`` has them; a run's networks: :func:`~crowdrl.training.config.sees_obstacles`) the
    entity tokens of humans and obstacle edges, with their mask, in place of the humans."""
    if obstacles is None:
        obstacles = cfg.obstacles_shape[0] > 0
    if obstacles:
        return ENTITY_OBS_KEYS
    return (*OBS_KEYS, MASK_KEY) if cfg.variable_crowd else OBS_KEYS


def stored_keys(run: RunConfig, keys: tuple[str, ...] = OBS_KEYS) -> list:
    """The keys of a collected batch that the replay buffer keeps for ``run`` whose networks read
    ``keys`` (the n-step transform adds steps_to_next_obs; the learned predictor adds its own)."""
    out = [*keys, "action", *[("next", k) for k in (*keys, "reward", "done", "terminated")]]
    if run.planning.enabled and run.planning.predictor == "learned":
        out += [k for k in PREDICTOR_KEYS if k not in out]
    return out


def make_env(run: RunConfig, *, split: str = "train", num_envs: int | None = None, seed: int | None = None,
             scenario: str | None = None, num_humans: int | None = None,
             robot_kinematics: str = "unicycle") -> TransformedEnv:
    """``CrowdNavEnv`` + the robot-centric state (the env itself counts steps and sums the return, so
    that its snapshot holds them: a resumed run continues its in-flight episodes exactly).

    Training uses the ``train`` stream of the run seed; validation the ``val`` stream of the run
    seed; tests the ``test`` stream of the evaluation seed (``seed``), possibly on another
    ``scenario`` or crowd size than training.
    """
    cfg = crowd_config(run, scenario=scenario, num_humans=num_humans, robot_kinematics=robot_kinematics)
    base = CrowdNavEnv(cfg.scenario, num_envs=num_envs or run.train.num_envs, num_humans=cfg.num_humans,
                       config=cfg, seed=run.seed if seed is None else seed, split=split, device=run.device)
    return TransformedEnv(base, Compose(RobotCentric(entities=sees_obstacles(run))))


def make_actor(run: RunConfig, env: EnvBase, net: torch.nn.Module,
               predictor: torch.nn.Module | None = None) -> TensorDictModuleBase:
    """The greedy Q actor (``QValueActor``) of ``net`` for ``env``'s action spec (reading the
    humans' mask when ``env``'s crowd size varies: one network serves any crowd), or, with
    ``planning.enabled``, the :class:`~crowdrl.policies.OnlinePlanner` of ``net`` and ``predictor``
    (which reads the mask in the same case). With ``train.compile_acting`` the actor calls ``net`` (and the predictor)
    through ``torch.compile`` (:class:`~crowdrl.compile.CompiledModule`, same
    parameters)."""
    crowd = crowd_env_of(env).config
    if run.train.compile_acting:
        net = CompiledModule(net, what="the acting Q network")
        if predictor is not None:
            predictor = CompiledModule(predictor, what="the planner's crowd predictor")
    if not run.planning.enabled:
        return make_q_actor(run.encoder.name, env.action_spec, in_keys=obs_keys(crowd, sees_obstacles(run)), net=net)
    if predictor is None:
        raise ValueError("planning.enabled: the planner needs its crowd predictor (make_predictor_of)")
    p = run.planning
    return OnlinePlanner(net, predictor, crowd, gamma=run.train.gamma, depth=p.depth, width=p.width,
                         mask_key=MASK_KEY if crowd.variable_crowd else None, entities=sees_obstacles(run),
                         safety_horizon=p.safety_horizon)


def make_predictor_of(run: RunConfig, time_step: float) -> torch.nn.Module | None:
    """The planner's crowd predictor (``None`` without planning), initialised from a seed derived
    from the run seed: the global RNG, hence the Q network and everything after, is untouched."""
    if not run.planning.enabled:
        return None
    with seeded_init(2_000_003 * (run.seed + 1)):
        return make_predictor(run.planning.predictor, time_step).to(run.device)


def make_exploration(env: EnvBase, actor: TensorDictModuleBase, strategy: ExplorationStrategy) -> TensorDictSequential:
    """The acting policy of ``strategy`` (the one that modified the actor's network): ``actor`` then
    ε-greedy (ε = 0 for the variants that explore otherwise).

    Under ``ExplorationType.DETERMINISTIC`` (evaluation) the ε-greedy step passes the greedy
    action through, so the same policy serves collection and evaluation. ε is set by
    ``strategy.schedule(frames)``.
    """
    return strategy.policy(actor, env.action_spec)


def make_loss(run: RunConfig, net: torch.nn.Module, keys: tuple[str, ...] = OBS_KEYS) -> D3QNLoss:
    """Double dueling DQN loss on n-step transitions of ``keys``, with its target network."""
    t = run.train
    return D3QNLoss(net, keys, gamma=t.gamma, double=True, compile=t.compile_loss, huber_delta=t.huber_delta)


def make_optimizer(run: RunConfig, net: torch.nn.Module, lr: float | None = None) -> torch.optim.Optimizer:
    """Adam at ``lr`` (default ``train.lr``); fused (one kernel for all parameters, cheaper than
    the per-tensor loop on CPU; docs/benchmarks.md): the Q network's and the crowd predictor's."""
    return torch.optim.Adam(net.parameters(), lr=run.train.lr if lr is None else lr, fused=True)


def make_buffer(run: RunConfig, keys: tuple[str, ...] = OBS_KEYS, strategy: ExplorationStrategy | None = None,
                context: ReplayContext | None = None) -> TensorDictReplayBuffer:
    """The replay buffer of observations ``keys``: n-step returns when a batch is written, then
    what the exploration ``strategy`` does to a sampled batch (ICM/RE3: the intrinsic bonus), its
    transform built from ``context`` (:func:`~crowdrl.training.variants.replay_context`)."""
    t = run.train
    transform: Transform = NStepReturn(t.n_step, t.gamma, keys,
                                       one_step_key=successor_key(run, strategy) if strategy is not None else None)
    extra = strategy.replay_transform(context) if strategy is not None else None
    if extra is not None:
        transform = Compose(transform, extra)
    return TensorDictReplayBuffer(storage=LazyTensorStorage(t.buffer_size, device=run.device),
                                  batch_size=t.batch_size, transform=transform)


def make_learners(run: RunConfig, predictor: torch.nn.Module | None, keys: tuple[str, ...],
                  strategy: ExplorationStrategy | None = None) -> list[AuxiliaryLearner]:
    """The models trained beside the Q network on each sampled batch, in the order they step: the
    exploration ``strategy``'s (ICM's forward and inverse models), then the planner's crowd
    ``predictor`` when it has weights (its own Adam at ``planning.lr``; ``keys``: whether it reads
    the humans' mask)."""
    learners = list(strategy.learners()) if strategy is not None else []
    if predictor is not None and any(True for _ in predictor.parameters()):
        learners.append(PredictorLearner(predictor, make_optimizer(run, predictor, lr=run.planning.lr),
                                         compile=run.train.compile_loss, mask_key=MASK_KEY if MASK_KEY in keys else None))
    return learners


def make_update_part(run: RunConfig, net: torch.nn.Module, keys: tuple[str, ...], crowd: CrowdConfig,
                     reward_bonus: Callable[[TensorDictBase], TensorDictBase] | None = None,
                     one_step_key: str | None = None) -> UpdatePart:
    """The gradient steps of one update (:mod:`crowdrl.training.parts`): the sampled batch alone, or with
    ``train.counterfactual.mode`` its counterfactual transitions too (``reward_bonus``, the exploration
    strategy's, added to them; it reads their successor under ``one_step_key`` where :func:`make_buffer` stores
    it, :func:`~crowdrl.training.variants.successor_key`)."""
    c = run.train.counterfactual
    if c.mode == "off":
        return ReplayOnly()
    return CounterfactualExperience(crowd, net, keys, mode=c.mode, actions=c.actions, k=c.k, weight=c.weight,
                                    entities=sees_obstacles(run), seed=3_000_017 * (run.seed + 1),
                                    reward_bonus=reward_bonus, one_step_key=one_step_key)


def make_learner(run: RunConfig, net: torch.nn.Module, keys: tuple[str, ...], crowd: CrowdConfig,
                 strategy: ExplorationStrategy, predictor: torch.nn.Module | None) -> D3QNLearner:
    """The Q network's learner (:class:`~crowdrl.training.learner.D3QNLearner`): the loss on ``keys``, Adam,
    the update part, the auxiliary learners (the ``strategy``'s, the planner's ``predictor``), the
    strategy's hook before each update, the gradient clip, the target rule (Polyak ``train.target_tau`` < 1,
    else a hard copy every ``train.target_update_frames`` frames of updates) and the learning-rate schedule."""
    t = run.train
    loss = make_loss(run, net, keys)
    optimizer = make_optimizer(run, net)
    learners = make_learners(run, predictor, keys, strategy)
    part = make_update_part(run, net, keys, crowd, strategy.reward_bonus(), successor_key(run, strategy))
    return D3QNLearner(loss, optimizer, part, learners, before_update=strategy.before_update,
                       grad_clip_norm=t.grad_clip_norm, target_tau=t.target_tau,
                       updates_per_copy=max(1, round(t.target_update_frames * max(t.updates_per_frame, 1e-9))),
                       lr=None if t.lr_end is None else (t.lr, t.lr_end, t.total_frames))


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


def make_collector(run: RunConfig, env: EnvBase, policy: TensorDictModule) -> Collector:
    """A single-process collector of ``num_envs x steps_per_batch`` frames per batch."""
    t = run.train
    return Collector(env, policy, frames_per_batch=t.num_envs * t.steps_per_batch, total_frames=-1,
                     device=run.device, auto_register_policy_transforms=False)


__all__ = ["ENTITY_OBS_KEYS", "MASK_KEY", "OBS_KEYS", "PREDICTOR_KEYS", "buffer_state_dict",
           "make_actor", "make_buffer", "make_collector", "make_env", "make_exploration", "make_learner", "make_learners",
           "make_loss", "make_optimizer", "make_predictor_of", "make_update_part", "obs_keys", "stored_keys"]
