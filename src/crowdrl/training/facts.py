"""What a run's factories read, derived once from its validated config: :class:`RunFacts`.

The crowd's constants, whether the networks see obstacles, the observation keys they read and the
action count follow from the ``env`` section; every factory of :mod:`crowdrl.training.factories`
takes its own config section and these facts, so none derives them again. The replay-buffer keys
are collected from the composed parts that read them (:meth:`RunFacts.replay_keys`).

>>> from crowdrl.training import validate
>>> facts = RunFacts.of(validate({"preset": "smoke", "env": {"scenario": "corridor", "num_humans": 4}}))
>>> facts.crowd.scenario, facts.entities, facts.obs_keys, facts.num_actions
('corridor', True, ('robot_rc', 'entities_rc', 'entities_mask'), 81)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from tensordict.utils import NestedKey

from crowdrl.envs import RobotCentric
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.kinematics import NUM_ACTIONS
from crowdrl.training.config import RunConfig, crowd_config, map_extent, sees_obstacles

OBS_KEYS = ("robot_rc", "humans_rc")
MASK_KEY = "humans_mask"  # [B, N] bool, True = present: read by the networks when crowds vary in size
# what a network trained among obstacles reads: the humans and the observed obstacle edges as tokens
ENTITY_OBS_KEYS = ("robot_rc", *RobotCentric.ENTITY_KEYS)
LIDAR_KEY = "lidar"  # the robot's scan [B, R], read last by a network with encoder.lidar on


def obs_keys(cfg: CrowdConfig, obstacles: bool | None = None, lidar: bool = False) -> tuple[str, ...]:
    """What the networks read from an env of ``cfg``: the robot-centric states, and the humans' mask
    when the crowd size varies (a fixed crowd has every human present); with ``obstacles`` (default:
    whether ``cfg`` has them; a run's networks: :func:`~crowdrl.training.config.sees_obstacles`) the
    entity tokens of humans and obstacle edges, with their mask, in place of the humans; with ``lidar``
    (``encoder.lidar`` on) the scan last."""
    if obstacles is None:
        obstacles = cfg.obstacles_shape[0] > 0
    if obstacles:
        keys = ENTITY_OBS_KEYS
    else:
        keys = (*OBS_KEYS, MASK_KEY) if cfg.variable_crowd else OBS_KEYS
    return (*keys, LIDAR_KEY) if lidar else keys


class StoresKeys(Protocol):
    """A composed part that reads replay-buffer keys beyond the transitions' (the planner's predictor,
    counterfactual experience)."""

    def stored_keys(self) -> list[NestedKey]: ...


@dataclass(frozen=True)
class RunFacts:
    """The facts of a run its factories share, made once by :meth:`of` from the validated config.

    Attributes:
        crowd: the simulator constants of the training env (``crowd_config(run)``).
        entities: whether the networks read humans and obstacle edges as entity tokens (trained among obstacles).
        lidar: whether the networks read the lidar scan (``encoder.lidar``).
        obs_keys: the observation keys the networks read.
        num_actions: the robot's discrete action count.
        seed: the run seed (each part derives its own seed from it).
        device: where the networks and the buffer live.
        obstacle_tokens: the obstacle edges a training observation holds (a scenario mix's: the most of its scenarios).
    """

    crowd: CrowdConfig
    entities: bool
    lidar: bool
    obs_keys: tuple[str, ...]
    num_actions: int
    seed: int
    device: str
    obstacle_tokens: int = 0

    @classmethod
    def of(cls, run: RunConfig) -> RunFacts:
        crowd = crowd_config(run)
        entities, lidar = sees_obstacles(run), run.encoder.lidar != "off"
        return cls(crowd=crowd, entities=entities, lidar=lidar, obs_keys=obs_keys(crowd, entities, lidar),
                   num_actions=NUM_ACTIONS, seed=run.seed, device=run.device, obstacle_tokens=map_extent(run)[0])

    def replay_keys(self, *parts: StoresKeys) -> list[NestedKey]:
        """The keys of a collected batch the replay buffer keeps: the transitions of :attr:`obs_keys`
        (the n-step transform adds ``steps_to_next_obs``), then what each of ``parts`` reads, each key once."""
        out: list[NestedKey] = [*self.obs_keys, "action",
                                *[("next", k) for k in (*self.obs_keys, "reward", "done", "terminated")]]
        for part in parts:
            out += [k for k in part.stored_keys() if k not in out]
        return out


__all__ = ["ENTITY_OBS_KEYS", "LIDAR_KEY", "MASK_KEY", "OBS_KEYS", "RunFacts", "StoresKeys", "obs_keys"]
