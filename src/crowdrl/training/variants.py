"""The exploration variant of a run (``exploration.name``), built from its config.

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

from crowdrl.exploration import ICM, RE3, IntrinsicBonus, IntrinsicRewardTransform
from crowdrl.exploration.normalize import ObservationNormalizer, RewardNormalizer
from crowdrl.exploration.schedule import make_schedule
from crowdrl.exploration.dropout import add_action_dropout
from crowdrl.exploration.intrinsic import seeded_init
from crowdrl.exploration.noisy import noisify_head
from crowdrl.models import make_encoder, make_q_network
from crowdrl.models.qnet import CrowdQNetwork
from crowdrl.envs.robot_centric import ENTITY_DIM
from crowdrl.training.config import INTRINSIC, RunConfig, beta_schedule_of, sees_obstacles

ONE_STEP_KEY = "one_step_next"  # where the n-step transform keeps s_{t+1} for the intrinsic bonus


def encoder_kwargs(run: RunConfig) -> dict:
    """The encoder's arguments for ``run``: entity tokens (humans and obstacle edges) in place of
    humans for a run trained among obstacles (:func:`~crowdrl.training.config.sees_obstacles`)."""
    return {"human_dim": ENTITY_DIM} if sees_obstacles(run) else {}


def make_network(run: RunConfig, num_actions: int = 81) -> CrowdQNetwork:
    """The Q network of the run's encoder and exploration variant (fresh parameters)."""
    net = make_q_network(run.encoder.name, num_actions=num_actions, **encoder_kwargs(run))
    x = run.exploration
    if x.name == "noisy":
        noisify_head(net.head, x.sigma0)
    elif x.name == "dropout":
        add_action_dropout(net.head, x.dropout_start)
    return net


def make_bonus(run: RunConfig, obs_keys: list[str], num_actions: int = 81) -> IntrinsicBonus | None:
    """ICM or RE3 on its own encoder of the run's architecture (``None`` for other variants).

    Initialised from a seed derived from the run seed without touching the global RNG, so a
    ``beta = 0`` run follows the extrinsic-only run bit for bit.
    """
    x = run.exploration
    if x.name not in INTRINSIC:
        return None
    seed = 1_000_003 * (run.seed + 1)
    with seeded_init(seed):
        encoder = make_encoder(run.encoder.name, **encoder_kwargs(run))
    if x.name == "icm":
        return ICM(encoder, num_actions, obs_keys, lr=x.icm_lr, detach_target=x.icm_detach_target,
                   feature_norm=x.icm_feature_norm, seed=seed + 1)
    return RE3(encoder, obs_keys, k=x.re3_k, seed=seed + 1)


def make_intrinsic_transform(run: RunConfig, bonus: IntrinsicBonus, obs_keys: list[str],
                             frames: Callable[[], int]) -> IntrinsicRewardTransform:
    """The sample-time reward transform with the run's β schedule and stable-bonus options;
    ``frames()`` gives the frame count a scheduled β reads."""
    x = run.exploration
    beta = make_schedule(beta_schedule_of(x), x.beta, end=x.beta_end, duration=x.anneal_frames, decay=x.beta_decay,
                         clock=frames)
    next_keys = [("next", k) for k in obs_keys] if run.train.n_step == 1 else [(ONE_STEP_KEY, k) for k in obs_keys]
    reward_norm = RewardNormalizer(x.reward_norm, center=x.reward_center, clip=x.reward_clip)
    return IntrinsicRewardTransform(
        bonus, beta, obs_keys=obs_keys, next_obs_keys=next_keys,
        obs_norm=ObservationNormalizer(clip=x.obs_clip) if x.obs_norm else None,
        reward_norm=None if reward_norm.is_identity else reward_norm,
        terminal_value_gamma=run.train.gamma if x.terminal_value else None)


def uses_one_step_successor(run: RunConfig) -> bool:
    """Whether the buffer must keep ``s_{t+1}`` next to the n-step successor."""
    return run.exploration.name in INTRINSIC and run.train.n_step > 1


__all__ = ["encoder_kwargs", "make_network", "make_bonus", "make_intrinsic_transform", "uses_one_step_successor", "ONE_STEP_KEY"]
