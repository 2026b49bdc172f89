"""The batched state of B crowd-navigation episodes: plain tensors, no per-agent objects."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


@dataclass
class CrowdState:
    """State of ``B`` episodes with ``N`` humans each (world frame, metres, seconds)."""

    robot_position: Tensor  # [B, 2]
    robot_velocity: Tensor  # [B, 2]
    robot_heading: Tensor  # [B]
    robot_goal: Tensor  # [B, 2]
    human_position: Tensor  # [B, N, 2]
    human_velocity: Tensor  # [B, N, 2]
    human_goal: Tensor  # [B, N, 2]
    human_goal_steps: Tensor  # [B, N] int64, steps spent within a radius of the current goal
    step_count: Tensor  # [B] int64
    episode_key: Tensor  # [B] int64, key of the episode's counter-based random numbers
    human_mask: Tensor  # [B, N] bool, True where a human is present (a crowd of n < N: the first n)
    # Static obstacles of each episode, RVO2 polygons padded to the config's P x V
    # (:mod:`crowdrl.sim.obstacles`: 2 vertices a wall segment, 3+ a counter-clockwise solid polygon):
    # [B, P, V, 2] and the vertex mask [B, P, V]. P = 0 (the open scenarios) or None: no obstacles.
    obstacles: Tensor | None = None
    obstacle_mask: Tensor | None = None
    # [B, N] int8: the model each human follows for the whole episode, its index in
    # crowdrl.sim.config.HUMAN_MODELS (0 orca, 1 social_force, 2 linear): drawn per episode for
    # human_model="mixed" (crowdrl.sim.scenarios.assign_human_models), the config's model for every human
    # otherwise (which the step then does not read). None (a state built by hand): every human follows the
    # config's model; a mixed crowd's step refuses it.
    human_model: Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.robot_position.shape[0]

    @property
    def num_humans(self) -> int:
        return self.human_position.shape[1]

    @property
    def has_obstacles(self) -> bool:
        """Whether the episodes have obstacle polygons (a tensor with ``P > 0``)."""
        return self.obstacles is not None and self.obstacles.shape[1] > 0

    def obstacle_polygons(self, row: int) -> tuple[np.ndarray, ...]:
        """Episode ``row``'s obstacle polygons as ``[n_i, 2]`` float64 arrays (valid vertices only; a
        wall has 2), as the figures draw them; empty without obstacles."""
        if not self.has_obstacles:
            return ()
        obs, mask = self.obstacles[row].double().cpu(), self.obstacle_mask[row].cpu()
        return tuple(obs[p, mask[p]].numpy() for p in range(obs.shape[0]) if int(mask[p].sum()) >= 2)

    @property
    def device(self) -> torch.device:
        return self.robot_position.device

    def replace(self, **changes: Tensor) -> "CrowdState":
        return dataclasses.replace(self, **changes)

    def where(self, mask: Tensor, other: "CrowdState") -> "CrowdState":
        """Per episode: ``other`` where ``mask`` ([B] bool) is set, ``self`` elsewhere."""
        out = {}
        for f in dataclasses.fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if mine is None or theirs is None:
                if (mine is None) != (theirs is None):
                    raise ValueError(f"where: {f.name} is None in one state only")
                out[f.name] = None
                continue
            m = mask.reshape(mask.shape + (1,) * (mine.dim() - 1))
            out[f.name] = torch.where(m, theirs, mine)
        return CrowdState(**out)

    def to(self, device: torch.device | str) -> "CrowdState":
        return CrowdState(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name).to(device)
                             for f in dataclasses.fields(self)})

    def index(self, idx: Tensor | slice | int) -> "CrowdState":
        """The episodes selected by ``idx`` along the batch dimension."""
        out = {}
        for f in dataclasses.fields(self):
            t = getattr(self, f.name)
            out[f.name] = None if t is None else t[idx]
        return CrowdState(**out)
