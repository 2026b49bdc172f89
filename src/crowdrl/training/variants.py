"""The exploration variant of a run (``exploration.name``) on the crowd's networks: the Q network
its strategy modifies (:func:`make_network`) and what its replay transform reads from the run
(:func:`replay_context`). The variants themselves are
:class:`~crowdrl.exploration.strategy.ExplorationStrategy` instances (``docs/mdp.md``,
"Exploration variants"):

* ``egreedy``: the plain dueling network, ε-greedy acting.
* ``noisy``: every head layer a factorised NoisyLinear (σ0), ε = 0.
* ``dropout``: dropout after each hidden ReLU of the head while acting, p scheduled, ε = 0.
* ``icm`` / ``re3``: the plain network plus an intrinsic bonus computed at sample time by an
  :class:`~crowdrl.exploration.IntrinsicRewardTransform` in the replay buffer, ε = 0. With
  n-step returns (n > 1) the bonus is that of the window's first transition
  ``(s_t, a_t, s_{t+1})`` added to the n-step extrinsic return: the later steps' bonuses would
  need their own states at sample time. The paper's setting is n = 1, where this is exact.

Shared by the trainer and by the evaluation of saved checkpoints (a noisy network's parameters
have their own names, so the test network must be built the same way).
"""

from __future__ import annotations

from typing import Callable

from crowdrl.envs.robot_centric import ENTITY_DIM
from crowdrl.exploration import ExplorationStrategy, ReplayContext
from crowdrl.models import make_encoder, make_q_network
from crowdrl.models.qnet import CrowdQNetwork
from crowdrl.training.config import RunConfig, sees_obstacles
from crowdrl.training.facts import LIDAR_KEY

ONE_STEP_KEY = "one_step_next"  # where the n-step transform keeps s_{t+1} for the intrinsic bonus


def encoder_kwargs(run: RunConfig) -> dict:
    """The encoder's arguments for ``run``: entity tokens (humans and obstacle edges) in place of
    humans for a run trained among obstacles (:func:`~crowdrl.training.config.sees_obstacles`)."""
    return {"human_dim": ENTITY_DIM} if sees_obstacles(run) else {}


def make_network(run: RunConfig, num_actions: int = 81, *, strategy: ExplorationStrategy) -> CrowdQNetwork:
    """The Q network of the run's encoder (fresh parameters), modified by its exploration ``strategy``
    (``make_strategy(run.exploration)``): required, so that the policy acting on the network and the
    strategy that modified it (a noisy network's noise, a dropout head's p) are the same object."""
    net = make_q_network(run.encoder.name, num_actions=num_actions, head_layer_norm=run.train.q_layer_norm,
                         lidar=run.encoder.lidar, lidar_rays=run.env.lidar_rays, lidar_range=run.env.lidar_range,
                         **encoder_kwargs(run))
    return strategy.modify_network(net)


def successor_key(run: RunConfig, strategy: ExplorationStrategy) -> str | None:
    """Where a sampled transition keeps ``s_{t+1}`` for the strategy's bonus, decided here only: ``ONE_STEP_KEY``
    when the strategy reads the successor and n-step returns (n > 1) move ``("next", ·)`` to ``s_{t+n}``;
    ``None`` when nothing reads it or ``("next", ·)`` is ``s_{t+1}`` itself (the buffer then keeps no copy)."""
    return ONE_STEP_KEY if strategy.reads_successor and run.train.n_step > 1 else None


def replay_context(run: RunConfig, obs_keys: list, num_actions: int, frames: Callable[[], int],
                   successor: str | None = None) -> ReplayContext:
    """What an exploration strategy's replay transform reads from ``run``: the one-step successor's
    keys (under ``successor``, :func:`successor_key`; ``None``: ``("next", ·)``), a fresh encoder of the run's
    architecture, a seed derived from the run seed, and ``frames()``, the frame count a scheduled β reads.
    The intrinsic models read the robot and the crowd (or entity) tokens, not the lidar scan."""
    obs_keys = [k for k in obs_keys if k != LIDAR_KEY]
    next_keys = [(successor or "next", k) for k in obs_keys]
    return ReplayContext(obs_keys=list(obs_keys), next_obs_keys=next_keys, num_actions=num_actions,
                         gamma=run.train.gamma, frames=frames,
                         make_encoder=lambda: make_encoder(run.encoder.name, **encoder_kwargs(run)),
                         seed=1_000_003 * (run.seed + 1), device=run.device)


__all__ = ["encoder_kwargs", "make_network", "replay_context", "successor_key", "ONE_STEP_KEY"]
