"""TorchRL and Gymnasium faces of the crowd simulator."""

from crowdrl.envs.crowd_nav import CrowdNavEnv
from crowdrl.envs.robot_centric import RobotCentric, robot_centric

__all__ = ["CrowdNavEnv", "RobotCentric", "robot_centric"]
