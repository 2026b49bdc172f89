"""Robot policies that act on the world-frame observation: the ORCA baseline and SG-D3QN's
online planner."""

from crowdrl.policies.orca_baseline import OrcaRobotPolicy
from crowdrl.policies.planning import OnlinePlanner, Plan

__all__ = ["OnlinePlanner", "OrcaRobotPolicy", "Plan"]
