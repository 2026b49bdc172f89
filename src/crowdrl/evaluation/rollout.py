"""Evaluation of any TorchRL policy on fixed episodes of a ``CrowdNavEnv``: the one rollout path.

Validation during training, the final test, the ORCA baseline and ``experiments/evaluate.py``
all call :func:`evaluate` on an env from the same maker as training (``CrowdNavEnv`` plus its
transforms) with a TorchRL policy, through ``env.rollout``. Episodes are loaded by id
(:meth:`CrowdNavEnv.load_episodes` before the reset), so episode ``i`` of the env's stream is the same
whatever the env's batch size; metrics are computed from what the env emits (see
:func:`evaluate` for an example).
"""

from __future__ import annotations

from typing import Callable

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from crowdrl.envs.crowd_nav import CrowdNavEnv
from crowdrl.envs.mix import ScenarioMixEnv
from crowdrl.evaluation.metrics import EpisodeMetrics, discount_per_step, episode_metrics
from crowdrl.evaluation.trajectory import Trajectory
from crowdrl.sim.config import SCENARIOS
from crowdrl.sim.crowd import EVENT_NAMES

Policy = Callable[[TensorDictBase], TensorDictBase]


def crowd_env_of(env: EnvBase) -> CrowdNavEnv | ScenarioMixEnv:
    """The :class:`CrowdNavEnv` (or :class:`~crowdrl.envs.mix.ScenarioMixEnv`) at the bottom of ``env`` (itself, or
    a ``TransformedEnv``'s base)."""
    base = env
    while not isinstance(base, (CrowdNavEnv, ScenarioMixEnv)):
        nxt = getattr(base, "base_env", None)
        if nxt is None or nxt is base:
            raise TypeError(f"evaluate needs a CrowdNavEnv (optionally transformed), got {type(env).__name__}")
        base = nxt
    return base


def episode_records(rollout: TensorDictBase, max_steps: int) -> dict[str, Tensor]:
    """Per-episode records of a ``[B, T]`` rollout whose envs all started a fresh episode at t = 0.

    Each row's episode ends at its first ``done``; later steps of that row (the env reset it and
    went on) are ignored. Returns ``events``, ``lengths``, ``rewards [B, max_steps]``
    (zero-padded), ``discomfort_steps`` and ``discomfort_separation_sum``; with ``scenario`` the row's scenario
    index (a :class:`~crowdrl.envs.mix.ScenarioMixEnv`'s rollout).
    """
    nxt = rollout.get("next")
    done = nxt.get("done").reshape(rollout.shape)
    if not bool(done.any(-1).all()):
        raise RuntimeError("an episode did not end within the rollout (the env must truncate at max_steps)")
    B, T = done.shape
    first = done.to(torch.int8).argmax(-1)  # [B] index of each row's first done
    inside = torch.arange(T, device=done.device).unsqueeze(0) <= first.unsqueeze(-1)
    rewards = torch.where(inside, nxt.get("reward").reshape(B, T).double(), 0.0)
    in_disc = inside & (nxt.get("discomfort_count").reshape(B, T) > 0)
    min_sep = nxt.get("min_separation").reshape(B, T).double()
    padded = torch.zeros(B, max_steps, dtype=torch.float64, device=done.device)
    padded[:, :T] = rewards[:, :max_steps]
    out = {
        "events": nxt.get("event").reshape(B, T).gather(1, first.unsqueeze(-1)).squeeze(-1),
        "lengths": first + 1,
        "rewards": padded,
        "discomfort_steps": in_disc.sum(-1),
        "discomfort_separation_sum": torch.where(in_disc, min_sep, 0.0).sum(-1),
    }
    if "scenario" in rollout.keys():
        out["scenario"] = rollout.get("scenario").reshape(B, T)[:, 0]
    return out


def kept_bytes(num_episodes: int, max_steps: int) -> int:
    """Peak bytes of the per-episode records :func:`evaluate` keeps for its metrics: each episode's
    rewards (``max_steps`` float32, zero-padded), copied once when joined and twice in float64 when
    the returns are computed, and its five counters."""
    return num_episodes * (max_steps * (4 + 4 + 8 + 8) + 5 * 8)


@torch.no_grad()
def evaluate(
    env: EnvBase,
    policy: Policy,
    *,
    num_episodes: int = 1000,
    first_episode: int = 0,
    record_episode: int | None = None,
    progress: Callable[[int], None] | None = None,
    per_scenario: dict[str, EpisodeMetrics] | None = None,
) -> tuple[EpisodeMetrics, Trajectory | None]:
    """Run episodes ``first_episode .. first_episode + num_episodes - 1`` of ``env``'s stream.

    ``env`` is a :class:`CrowdNavEnv` (its ``split`` and ``seed`` name the stream: ``test`` for
    test cases, ``val`` for validation), optionally inside a ``TransformedEnv``; ``policy`` is any
    TorchRL policy (a ``TensorDictModule`` or a callable on tensordicts) for that env. Episodes
    run ``env.num_envs`` at a time through ``env.rollout`` under the deterministic exploration
    type (greedy ε, dropout off); turn noisy layers off around the call. When
    ``record_episode`` is given, that episode's :class:`Trajectory` is returned too. On a
    :class:`~crowdrl.envs.mix.ScenarioMixEnv` (each row its scenario's case), ``per_scenario`` (a dict, when
    given) is filled with each scenario's own metrics, keyed by name.

    Examples:
        The ORCA baseline (holonomic robot) on the first four test episodes, two at a time:

        >>> from crowdrl.envs import CrowdNavEnv
        >>> from crowdrl.evaluation import evaluate
        >>> from crowdrl.policies import OrcaRobotPolicy
        >>> env = CrowdNavEnv("circle", num_envs=2, num_humans=5, split="test", robot_kinematics="holonomic")
        >>> metrics, trajectory = evaluate(env, OrcaRobotPolicy(env.config), num_episodes=4, record_episode=0)
        >>> metrics.episodes
        4
        >>> sorted(metrics.as_dict())  # doctest: +NORMALIZE_WHITESPACE
        ['average_return', 'collision_rate', 'discomfort_frequency', 'discomfort_min_separation',
         'episodes', 'navigation_time', 'success_rate', 'timeout_rate']
        >>> round(metrics.success_rate + metrics.collision_rate + metrics.timeout_rate, 6)
        1.0
        >>> trajectory.outcome in ("success", "collision", "timeout"), trajectory.robot_positions.shape[1]
        (True, 2)
    """
    if isinstance(num_episodes, bool) or int(num_episodes) != num_episodes or num_episodes < 1:
        raise ValueError(f"num_episodes must be an integer >= 1, got {num_episodes!r}")
    if first_episode < 0:
        raise ValueError(f"first_episode must be >= 0, got {first_episode}")
    if record_episode is not None and not first_episode <= record_episode < first_episode + num_episodes:
        raise ValueError(f"record_episode must lie in {first_episode}..{first_episode + num_episodes - 1}, "
                         f"got {record_episode}")
    crowd = crowd_env_of(env)
    cfg, B, device = crowd.config, crowd.num_envs, crowd.device
    records: dict[str, list[Tensor]] = {}
    trajectory = None
    stop = first_episode + num_episodes
    for first in range(first_episode, stop, B):
        n = min(B, stop - first)
        # a last partial chunk fills its spare sub-envs with copies of its last episode (ignored)
        ids = torch.arange(first, first + B, device=device).clamp_max(stop - 1)
        crowd.load_episodes(ids)
        start = env.reset()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            rollout = env.rollout(cfg.max_steps, policy, auto_reset=False, tensordict=start,
                                  break_when_any_done=False, break_when_all_done=True)
        chunk = episode_records(rollout, cfg.max_steps)
        for key, value in chunk.items():
            records.setdefault(key, []).append(value[:n])
        if record_episode is not None and first <= record_episode < first + n:
            row = record_episode - first
            trajectory = recorded_trajectory(cfg, start[row], rollout[row], int(chunk["lengths"][row]),
                                             EVENT_NAMES[int(chunk["events"][row])],
                                             crowd.state.obstacle_polygons(row) or None)
        if progress is not None:
            progress(n)
    keys = ("events", "lengths", "rewards", "discomfort_steps", "discomfort_separation_sum")
    joined = {k: torch.cat(v) for k, v in records.items()}

    def metrics_of(rows: Tensor | slice) -> EpisodeMetrics:
        return episode_metrics(*(joined[k][rows] for k in keys), time_step=cfg.time_step,
                               discount=discount_per_step(cfg.time_step, cfg.robot_v_pref))

    if per_scenario is not None and "scenario" in joined:
        for index in joined["scenario"].unique().tolist():
            per_scenario[SCENARIOS[index]] = metrics_of(joined["scenario"] == index)
    return metrics_of(slice(None)), trajectory


def recorded_trajectory(cfg, start: TensorDictBase, steps: TensorDictBase, length: int, outcome: str,
                        obstacles: tuple | None = None) -> Trajectory:
    """The :class:`Trajectory` of one env row: its reset observation and its first ``length`` steps
    (the humans present in it), with the episode's ``obstacles`` polygons if any."""
    def series(key: str) -> Tensor:
        first = start.get(key).unsqueeze(0)
        return torch.cat((first, steps.get(("next", key))[:length]), 0).double().cpu()

    robot, humans, goals = series("robot"), series("humans"), series("human_goals")
    present = start.get("humans_mask", None)
    if present is not None:  # a crowd smaller than its maximum: only the humans that take part
        present = present.cpu()
        humans, goals = humans[:, present], goals[:, present]
    return Trajectory(
        robot_positions=robot[:, 0:2].numpy(),
        robot_goal=robot[0, 5:7].numpy(),
        robot_radius=cfg.robot_radius,
        human_positions=humans[..., 0:2].numpy(),
        human_goals=goals.numpy(),
        human_radius=cfg.human_radius,
        time_step=cfg.time_step,
        outcome=outcome,
        robot_headings=robot[:, 8].numpy(),
        obstacles=obstacles,
    )
