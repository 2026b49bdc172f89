"""SG-D3QN's online planning as a TorchRL policy module (``docs/mdp.md``, "Online planning").

For every environment the planner takes the ``width`` actions with the highest ``Q(s, ·)``,
predicts the state after each of them and scores it:

    score_d(s, a) = ½ · ( r̂(s, a, ŝ′) + γ̄ · (1 − end̂) · V_{d−1}(ŝ′) + Q(s, a) )
    V_0(s) = max_a Q(s, a),        V_k(s) = max over the top-``width`` a of score_k(s, a)

and acts by the best ``score_depth``. ``depth = 1`` is upstream's planner (the top 10 actions,
one step ahead).

* Progress bias (``progress_bias`` κ > 0; off by default): the step's progress term of the reward counts
  (1 + κ) times in r̂, i.e. ``score_d`` gains ½ · κ · ``progress_factor`` · (d_goal before − d_goal after) at
  every level of the look-ahead. It trades some of the learned value's caution for shorter paths, at act time
  and without retraining (``docs/ceiling.md``, "Time over the ceiling"); the reward the agent trains on is
  unchanged.

* ŝ′: the robot's next state from the exact unicycle kinematics (the simulator's one-step model,
  :func:`crowdrl.sim.lookahead.look_ahead`, shared with counterfactual experience); the humans' from a
  predictor (:mod:`crowdrl.models.predictor`), one prediction per state (the humans do not see
  the robot, so it serves every candidate action).
* r̂ and end̂: the simulator's own :func:`crowdrl.sim.crowd.step_reward` on that step, the
  humans moving from their positions to the predicted ones (velocity = displacement / Δt, or
  their current velocity when the simulator judges collisions with it,
  ``collision_velocity="start"``).
* Obstacles: where the observation has them (``"obstacles"``, the edges nearest to the robot),
  the look-ahead's collision check sweeps the robot's disc against those edges as the simulator
  does (they stay the observed ones over the look-ahead); a network trained among obstacles
  (``entities=True``) reads them as entity tokens (:func:`crowdrl.envs.robot_centric.entity_tokens`)
  in every predicted state.
* Lidar: a network that reads the scan (``lidar_key``) reads the observed one at the root and, in every
  predicted state, the scan :func:`crowdrl.sim.lidar.robot_scan` computes from the predicted robot pose
  against the predicted humans' discs and the observed edges (the walls beyond them are not in the
  observation; in open space the predicted scan is exact whenever the prediction is).
* A predicted collision or goal ends the look-ahead (``end̂``): such a step is scored by its
  reward and ``Q(s, a)`` only, as a terminal transition has no successor value in the TD target.
* Safety check (``safety_horizon`` H > 0; off by default): an action is *unsafe* when, taken now and its
  velocity then held for H - 1 more steps, the robot collides with the predicted crowd (the predictor
  chained H steps) or an observed wall in one of the H steps (the simulator's ``step_reward``). The planner
  acts by its best-scored safe candidate; with none, by the safe action of highest Q; with no safe action
  at all, as without the check.

Everything is batched over environments and candidates (``[B·width^k, ...]`` tensors at depth
``k``); the only Python loop is the recursion over depth. Q is the run's network, called as the
plain actor calls it, so noisy or dropout heads act inside the planner as they would outside;
ε-greedy follows it (:class:`torchrl.modules.EGreedyModule` replaces the planner's ``"action"``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn

from crowdrl.envs.robot_centric import entity_tokens, obstacles_centric, robot_centric
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import step_reward
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table
from crowdrl.sim.lidar import robot_scan
from crowdrl.sim.lookahead import look_ahead


class Plan(NamedTuple):
    """What the planner decided for states ``[*]``."""

    action: Tensor  # [*] int64: the best-scored candidate (with the safety check: the best safe one, see above)
    action_value: Tensor  # [*, A]: Q(s, ·)
    candidates: Tensor  # [*, width] int64: the top-width actions by Q, best first
    scores: Tensor  # [*, width]: score_depth(s, candidate)


class OnlinePlanner(TensorDictModuleBase):
    """Depth-``depth``, width-``width`` look-ahead policy on world-frame observations.

    Args:
        net: the Q network, ``net(robot_rc, humans_rc[, humans_mask]) -> [*, A]``.
        predictor: ``predictor(robot, humans, humans_mask) -> next humans [*, N, 5]``.
        config: the simulator's constants (time step, radii, reward); unicycle kinematics only.
        gamma: the discount per step γ̄.
        depth, width: look-ahead depth ``>= 1`` and candidates per state ``1..A``.
        robot_key, humans_key: the world-frame observation keys; ``mask_key``: the crowd mask,
            read when the tensordict has it (``None``: never).
        entities: ``net`` reads entity tokens (humans and obstacle edges,
            ``net(robot_rc, entities_rc, entities_mask)``), as networks trained among obstacles do.
        obstacles_key: the observed obstacle edges ``[*, K, 4]`` (with ``obstacles_key + "_mask"``),
            read when the tensordict has them.
        safety_horizon: steps of the safety check (0: off; see the module docstring).
        progress_bias: κ >= 0, the extra weight of the step's progress in the scores (0: off; see above).
        lidar_key: the lidar scan ``[*, R]`` a network with ``encoder.lidar`` reads last (``None``: it reads none).

    Writes ``"action"`` ``[*]``, ``"action_value"`` ``[*, A]`` (Q(s, ·)) and
    ``"chosen_action_value"`` ``[*, 1]`` (Q of the chosen action), as ``QValueActor`` does.

    Examples:
        One step ahead over the top 4 actions of a (untrained) SARL Q network, the humans
        predicted at constant velocity, on two environments:

        >>> import torch
        >>> from crowdrl.envs import CrowdNavEnv
        >>> from crowdrl.models.predictor import ConstantVelocityPredictor
        >>> from crowdrl.models.qnet import make_q_network
        >>> from crowdrl.policies import OnlinePlanner
        >>> _ = torch.manual_seed(0)
        >>> env = CrowdNavEnv("circle", num_envs=2, num_humans=5)
        >>> planner = OnlinePlanner(make_q_network("sarl"), ConstantVelocityPredictor(env.config.time_step),
        ...                         env.config, gamma=0.97, depth=1, width=4)
        >>> td = planner(env.reset())
        >>> td["action"].shape, td["action"].dtype, td["action_value"].shape, td["chosen_action_value"].shape
        (torch.Size([2]), torch.int64, torch.Size([2, 81]), torch.Size([2, 1]))
        >>> plan = planner.plan(td["robot"], td["humans"])
        >>> plan.candidates.shape, bool((plan.candidates == plan.action.unsqueeze(-1)).any(-1).all())
        (torch.Size([2, 4]), True)
        >>> env.step(td)["next", "reward"].shape
        torch.Size([2, 1])
    """

    def __init__(self, net: nn.Module, predictor: nn.Module, config: CrowdConfig, *, gamma: float,
                 depth: int = 1, width: int = 10, robot_key: str = "robot", humans_key: str = "humans",
                 mask_key: str | None = "humans_mask", entities: bool = False,
                 obstacles_key: str = "obstacles", safety_horizon: int = 0, lidar_key: str | None = None,
                 progress_bias: float = 0.0) -> None:
        super().__init__()
        if config.robot_kinematics != "unicycle":
            raise ValueError(f"planning needs the unicycle's discrete actions, got {config.robot_kinematics!r}")
        if isinstance(depth, bool) or int(depth) != depth or depth < 1:
            raise ValueError(f"depth must be an integer >= 1, got {depth!r}")
        if isinstance(width, bool) or int(width) != width or not 1 <= width <= NUM_ACTIONS:
            raise ValueError(f"width must be an integer in 1..{NUM_ACTIONS}, got {width!r}")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        if isinstance(safety_horizon, bool) or int(safety_horizon) != safety_horizon or not 0 <= safety_horizon <= 20:
            raise ValueError(f"safety_horizon must be an integer in 0..20 (steps; 0: off), got {safety_horizon!r}")
        self.safety_horizon = int(safety_horizon)
        if isinstance(progress_bias, bool) or not math.isfinite(float(progress_bias)) or progress_bias < 0:
            raise ValueError(f"progress_bias must be a finite number >= 0 (0: off), got {progress_bias!r}")
        self.progress_bias = float(progress_bias)
        self.net = net
        self.predictor = predictor
        self.config = config
        self.gamma = float(gamma)
        self.depth, self.width = int(depth), int(width)
        self.robot_key, self.humans_key, self.mask_key = robot_key, humans_key, mask_key
        self.entities, self.obstacles_key = bool(entities), obstacles_key
        self.lidar_key = lidar_key
        if lidar_key is not None and config.lidar_rays < 1:
            raise ValueError("lidar_key: the network reads a scan, but config.lidar_rays is 0 (no scan)")
        self.in_keys = ([robot_key, humans_key] + ([mask_key] if mask_key is not None else [])
                        + ([lidar_key] if lidar_key is not None else []))
        self.out_keys = ["action", "action_value", "chosen_action_value"]
        self.register_buffer("table", action_table(config.robot_v_pref), persistent=False)

    # ------------------------------------------------------------------ the look-ahead
    def q_values(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None,
                 obstacles: Tensor | None = None, obstacles_mask: Tensor | None = None,
                 lidar: Tensor | None = None) -> Tensor:
        """``Q(s, ·)`` ``[M, A]`` of world-frame states ``robot [M, 9]``, ``humans [M, N, 5]`` (and the
        observed obstacle edges ``[M, K, 4]``, read by an ``entities`` network; with ``lidar_key`` the scan
        ``lidar [M, R]``, computed by :meth:`scan` when not given)."""
        robot_rc, humans_rc = robot_centric(robot, humans)
        extra: tuple[Tensor, ...] = ()
        if self.lidar_key is not None:
            extra = (self.scan(robot, humans, humans_mask, obstacles, obstacles_mask) if lidar is None else lidar,)
        if self.entities:
            obstacles_rc = None if obstacles is None else obstacles_centric(robot, obstacles)
            return self.net(robot_rc, *entity_tokens(robot_rc, humans_rc, obstacles_rc, humans_mask, obstacles_mask),
                            *extra)
        if humans_mask is None:
            return self.net(robot_rc, humans_rc, *extra)
        return self.net(robot_rc, humans_rc, humans_mask, *extra)

    def scan(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None, obstacles: Tensor | None = None,
             obstacles_mask: Tensor | None = None) -> Tensor:
        """The lidar scan ``[M, R]`` of a (predicted) state: from the robot's pose against the humans' discs and
        the observed edges (:func:`crowdrl.sim.lidar.robot_scan`, the env's own scan function)."""
        segments = None
        if obstacles is not None:
            valid = (torch.ones(obstacles.shape[:2], dtype=torch.bool, device=obstacles.device)
                     if obstacles_mask is None else obstacles_mask)
            segments = (obstacles[..., 0:2], obstacles[..., 2:4], valid)
        return robot_scan(self.config, robot[:, 0:2], robot[:, 8], humans[..., 0:2], humans_mask, segments)

    def scores(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None, q: Tensor, depth: int,
               obstacles: Tensor | None = None, obstacles_mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(score_depth [M, w], candidates [M, w])`` for states ``[M]`` whose ``Q(s, ·)`` is ``q``."""
        cfg = self.config
        M, N = humans.shape[0], humans.shape[1]
        w = self.width
        q_top, cand = q.topk(w, dim=-1)  # [M, w], best first
        # the crowd after the step: one prediction per state (the humans do not see the robot)
        humans_next = self.predictor(robot, humans, humans_mask)  # [M, N, 5]
        walls, wall_mask = self._walls(obstacles, obstacles_mask)  # the observed edges, for the sweep
        # the robot after each candidate and the step's reward: the simulator's one-step model
        robot_next, judged = look_ahead(cfg, self.table, robot, humans, humans_next, cand, humans_mask, walls, wall_mask)
        mask_w = None if humans_mask is None else humans_mask[:, None].expand(M, w, N)
        # the value after the step: V_0 = max Q, V_k = the best score of the next level
        flat_robot = robot_next.reshape(M * w, -1)
        flat_humans = humans_next[:, None].expand(M, w, N, humans.shape[-1]).reshape(M * w, N, -1)
        flat_mask = None if mask_w is None else mask_w.reshape(M * w, N)
        flat_obstacles = flat_obstacles_mask = None
        if obstacles is not None:
            flat_obstacles = obstacles[:, None].expand(M, w, *obstacles.shape[1:]).reshape(M * w, *obstacles.shape[1:])
            if obstacles_mask is not None:
                flat_obstacles_mask = obstacles_mask[:, None].expand(M, w, -1).reshape(M * w, -1)
        q_next = self.q_values(flat_robot, flat_humans, flat_mask, flat_obstacles, flat_obstacles_mask)
        if depth == 1:
            value = q_next.amax(-1)
        else:
            value = self.scores(flat_robot, flat_humans, flat_mask, q_next, depth - 1, flat_obstacles,
                                flat_obstacles_mask)[0].amax(-1)
        ended = judged.collided | judged.reached
        value = torch.where(ended, 0.0, value.reshape(M, w))
        reward = judged.reward
        if self.progress_bias > 0:  # the step's progress counted (1 + κ) times
            goal = robot[:, None, 5:7]
            progress = (goal - robot[:, None, 0:2]).norm(dim=-1) - (goal - robot_next[..., 0:2]).norm(dim=-1)
            reward = reward + self.progress_bias * cfg.progress_factor * progress
        return 0.5 * (reward + self.gamma * value + q_top), cand

    @staticmethod
    def _walls(obstacles: Tensor | None, obstacles_mask: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
        """The observed edges ``[M, K, 4]`` as 2-vertex wall polygons ``[M, K, 2, 2]`` with their mask."""
        if obstacles is None:
            return None, None
        M, K = obstacles.shape[:2]
        mask = torch.ones(M, K, dtype=torch.bool, device=obstacles.device) if obstacles_mask is None else obstacles_mask
        return obstacles.reshape(M, K, 2, 2), mask[..., None].expand(M, K, 2)

    @torch.no_grad()
    def safe_actions(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None,
                     obstacles: Tensor | None = None, obstacles_mask: Tensor | None = None) -> Tensor:
        """``[M, A]`` bool: the actions that do not collide within ``safety_horizon`` steps when taken now
        and held (their velocity) after, against the crowd chained through the predictor and the observed walls
        (all ``True`` when the check is off)."""
        cfg, M, N = self.config, robot.shape[0], humans.shape[1]
        A = self.table.shape[0]
        if self.safety_horizon == 0:
            return torch.ones(M, A, dtype=torch.bool, device=robot.device)
        walls, wall_mask = self._walls(obstacles, obstacles_mask)
        actions = torch.arange(A, device=robot.device).expand(M, A)
        humans_next = self.predictor(robot, humans, humans_mask)
        robot_next, judged = look_ahead(cfg, self.table, robot, humans, humans_next, actions, humans_mask, walls,
                                        wall_mask)
        hit, ended = judged.collided.clone(), judged.reached.clone()
        position, velocity = robot_next[..., 0:2], robot_next[..., 2:4]
        goal = robot[:, None, 5:7].expand(M, A, 2)
        mask_a = None if humans_mask is None else humans_mask[:, None].expand(M, A, N)
        for _ in range(self.safety_horizon - 1):
            now, humans_next = humans_next, self.predictor(robot, humans_next, humans_mask)
            vel = (now[..., 2:4] if cfg.collision_velocity == "start"
                   else (humans_next[..., 0:2] - now[..., 0:2]) / cfg.time_step)
            step = step_reward(cfg, position, velocity, goal, now[:, None, :, 0:2].expand(M, A, N, 2),
                               vel[:, None].expand(M, A, N, 2), mask_a, walls, wall_mask)
            hit = hit | (step.collided & ~ended)  # out of place: ONNX export has no in-place or
            ended = ended | step.reached
            position = position + velocity * cfg.time_step
        return ~hit

    @torch.no_grad()
    def plan(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None,
             obstacles: Tensor | None = None, obstacles_mask: Tensor | None = None, lidar: Tensor | None = None) -> Plan:
        """The planner's decision for world-frame states ``robot [*, 9]``, ``humans [*, N, 5]`` (and
        the observed obstacle edges ``[*, K, 4]`` with their mask ``[*, K]``, optional; the observed scan
        ``lidar [*, R]`` for a network that reads it)."""
        lead, N = robot.shape[:-1], humans.shape[-2]
        robot, humans = robot.reshape(-1, robot.shape[-1]), humans.reshape(-1, N, humans.shape[-1])
        if humans_mask is not None:
            humans_mask = humans_mask.reshape(-1, N)
        if obstacles is not None:
            obstacles = obstacles.reshape(robot.shape[0], -1, 4)
            if obstacles_mask is not None:
                obstacles_mask = obstacles_mask.reshape(robot.shape[0], -1)
        if lidar is not None:
            lidar = lidar.reshape(robot.shape[0], -1)
        q = self.q_values(robot, humans, humans_mask, obstacles, obstacles_mask, lidar)
        scores, cand = self.scores(robot, humans, humans_mask, q, self.depth, obstacles, obstacles_mask)
        action = cand.gather(-1, scores.argmax(-1, keepdim=True)).squeeze(-1)
        if self.safety_horizon > 0:
            safe = self.safe_actions(robot, humans, humans_mask, obstacles, obstacles_mask)
            safe_cand = safe.gather(-1, cand)
            best_safe = cand.gather(-1, scores.masked_fill(~safe_cand, -torch.inf).argmax(-1, keepdim=True)).squeeze(-1)
            safest = q.masked_fill(~safe, -torch.inf).argmax(-1)
            action = torch.where(safe_cand.any(-1), best_safe, torch.where(safe.any(-1), safest, action))
        return Plan(action.reshape(lead), q.reshape(*lead, -1), cand.reshape(*lead, self.width),
                    scores.reshape(*lead, self.width))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        mask = tensordict.get(self.mask_key, None) if self.mask_key is not None else None
        plan = self.plan(tensordict.get(self.robot_key), tensordict.get(self.humans_key), mask,
                         tensordict.get(self.obstacles_key, None), tensordict.get(self.obstacles_key + "_mask", None),
                         tensordict.get(self.lidar_key) if self.lidar_key is not None else None)
        tensordict.set("action", plan.action)
        tensordict.set("action_value", plan.action_value)
        tensordict.set("chosen_action_value", plan.action_value.gather(-1, plan.action.unsqueeze(-1)))
        return tensordict


__all__ = ["OnlinePlanner", "Plan"]
