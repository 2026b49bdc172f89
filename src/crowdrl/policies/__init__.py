"""Robot policies that act on the simulator state directly (baselines)."""

from crowdrl.policies.orca_baseline import OrcaRobotPolicy

__all__ = ["OrcaRobotPolicy"]
