"""TorchRL and Gymnasium faces of the crowd simulator."""

from crowdrl.envs.crowd_nav import CrowdNavEnv
from crowdrl.envs.mix import ScenarioMixEnv, mix_rows
from crowdrl.envs.robot_centric import ENTITY_DIM, RobotCentric, entity_tokens, obstacles_centric, robot_centric

__all__ = ["ENTITY_DIM", "CrowdNavEnv", "RobotCentric", "ScenarioMixEnv", "entity_tokens", "mix_rows", "obstacles_centric",
           "robot_centric"]
