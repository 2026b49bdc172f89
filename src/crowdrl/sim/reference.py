"""A deliberately plain, single-episode reference simulator (CrowdNav style).

:class:`ReferenceCrowdSim` re-implements one episode of the MDP of ``docs/mdp.md`` the way the
reference implementations (CrowdNav, SG-D3QN) do it: python floats for the robot, small numpy
float64 arrays for the humans, one loop iteration per agent, and the RVO2 C++ library
(``pyrvo``, RVO2 2.0.3) for the humans' ORCA velocities. It shares no step code with the
batched torch simulator (:mod:`crowdrl.sim.crowd`); it exists to check that simulator against
an independent implementation (``tests/test_reference_agreement.py``) and to time the
one-episode-at-a-time baseline (``experiments/bench_env.py``). No torch is used in
:meth:`ReferenceCrowdSim.step`; :meth:`ReferenceCrowdSim.from_state` only reads a
:class:`~crowdrl.sim.state.CrowdState` (any object with the same tensor fields).

Per step, in this order (``crowd.step`` order):

1. humans: every human's position, velocity and preferred velocity (vector to goal, scaled to
   unit length if longer than 1) is written into the episode's ``RVOSimulator`` (radius
   ``human_radius + 0.01``, max speed ``human_v_pref``, the ORCA parameters of
   :class:`~crowdrl.sim.config.CrowdConfig`, ``time_horizon_obst`` 5, no obstacles), one
   ``do_step`` computes all new velocities from the state at the start of the step, and they
   are read back. RVO2 works in float32; positions are kept here in float64 and RVO2's own
   position update is discarded (overwritten at the next step).
2. robot: unicycle, ``theta <- wrap(theta + rot)``, ``v = speed * (cos theta, sin theta)``.
3. continuous collision check: the closest distance of each human's relative linear motion
   within the step to the robot, minus both radii (CrowdNav's ``point_to_segment_dist``).
4. move everybody by ``v * dt``; goal reached iff ``|p_robot - g| < robot_radius``.
5. reward: ``0.2 * (d_before - d_after) + sum_i min(0, dmin_i - 0.2)`` plus ``+0.25`` (goal) or
   ``-0.25`` (collision; collision has priority); terminated on collision or goal, truncated
   when the step count reaches ``max_steps`` without termination.
6. non-stop humans: a human whose new position is within ``human_radius`` of its goal counts
   one more step; at ``goal_steps_before_new_goal`` steps it gets a new goal, its velocity is
   set to 0 and its counter to 0.

New goals of non-stop humans. The batched simulator draws them from counter-based random
numbers (:mod:`crowdrl.sim.rng`); reproducing that here would mean re-implementing the hash.
Instead, a ``new_goal_fn(sim, human_index) -> (gx, gy)`` callback can be passed (the agreement
test passes one that reads the goal the batched simulator chose for the same step). Without a
callback, a fresh goal is drawn CrowdNav-style from this object's own ``numpy`` generator (circle
or square point with the spawn clearance, at most 16 tries, the last one kept): statistically the
same rule, not the same numbers, so trajectories only match the batched simulator up to the
first new goal.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from crowdrl.sim.config import CrowdConfig

# Event codes, equal to ``crowdrl.sim.crowd``'s (checked by the agreement test).
RUNNING, SUCCESS, COLLISION, TIMEOUT = 0, 1, 2, 3
EVENT_NAMES = ("running", "success", "collision", "timeout")

TIME_HORIZON_OBST = 5.0
NEW_GOAL_TRIES = 16

_PYRVO_HINT = (
    "ReferenceCrowdSim needs the RVO2 bindings `pyrvo`; install them with "
    "`pip install --no-deps pyrvo==0.4.3`"
)


def _import_pyrvo():
    try:
        import pyrvo  # noqa: PLC0415 - optional dependency, imported lazily
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(_PYRVO_HINT) from exc
    return pyrvo


def action_speed_rotation(action: int, v_pref: float) -> tuple[float, float]:
    """(speed, rotation) of action ``action`` in ``0..80`` (5 speeds x 16 rotations, ``docs/mdp.md``,
    "The robot").

    Index 0 stops; ``1 + 5*i_rot + j_speed`` moves at ``(j+1)/5 * v_pref`` after rotating by
    ``-pi/6 + i_rot * (pi/3)/15``.
    """
    action = int(action)
    if not 0 <= action <= 80:
        raise ValueError(f"action must lie in 0..80, got {action}")
    if action == 0:
        return 0.0, 0.0
    i_rot, j_speed = divmod(action - 1, 5)
    speed = (j_speed + 1) / 5 * v_pref
    rotation = -math.pi / 6 + i_rot * (math.pi / 3) / 15
    return speed, rotation


def point_to_segment_dist(x1: float, y1: float, x2: float, y2: float, x3: float, y3: float) -> float:
    """Distance from point (x3, y3) to the segment (x1, y1)-(x2, y2) (CrowdNav's helper)."""
    px, py = x2 - x1, y2 - y1
    if px == 0 and py == 0:
        return math.hypot(x3 - x1, y3 - y1)
    u = ((x3 - x1) * px + (y3 - y1) * py) / (px * px + py * py)
    u = min(max(u, 0.0), 1.0)
    return math.hypot(x1 + u * px - x3, y1 + u * py - y3)


def _wrap(angle: float) -> float:
    """Angle in ``[-pi, pi)``."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


class ReferenceCrowdSim:
    """One crowd-navigation episode, stepped one agent at a time with RVO2 for the humans."""

    def __init__(
        self,
        cfg: CrowdConfig,
        *,
        robot_position,
        robot_heading: float,
        human_position,
        human_goal,
        robot_goal=None,
        robot_velocity=(0.0, 0.0),
        human_velocity=None,
        human_goal_steps=None,
        step_count: int = 0,
        new_goal_fn: Callable[["ReferenceCrowdSim", int], tuple[float, float]] | None = None,
        seed: int | None = None,
    ) -> None:
        pyrvo = _import_pyrvo()
        self.cfg = cfg
        self.new_goal_fn = new_goal_fn
        self._rng = np.random.default_rng(seed)
        n = len(human_position)
        self.num_humans = n
        self._set(robot_position, robot_velocity, robot_heading,
                  robot_goal if robot_goal is not None else (0.0, cfg.circle_radius),
                  human_position, human_velocity if human_velocity is not None else np.zeros((n, 2)),
                  human_goal, human_goal_steps if human_goal_steps is not None else np.zeros(n, np.int64),
                  step_count)
        radius = cfg.human_radius + cfg.orca_radius_margin
        self._rvo = pyrvo.RVOSimulator(
            cfg.time_step, cfg.orca_neighbor_dist, cfg.orca_max_neighbors, cfg.orca_time_horizon,
            TIME_HORIZON_OBST, radius, cfg.human_v_pref,
        )
        for i in range(n):
            self._rvo.add_agent(
                (float(self.human_position[i, 0]), float(self.human_position[i, 1])),
                cfg.orca_neighbor_dist, cfg.orca_max_neighbors, cfg.orca_time_horizon, TIME_HORIZON_OBST,
                radius, cfg.human_v_pref,
                (float(self.human_velocity[i, 0]), float(self.human_velocity[i, 1])),
            )

    # ------------------------------------------------------------------ state
    def _set(self, robot_position, robot_velocity, robot_heading, robot_goal, human_position, human_velocity,
             human_goal, human_goal_steps, step_count) -> None:
        self.robot_position = np.array(robot_position, dtype=np.float64).reshape(2)
        self.robot_velocity = np.array(robot_velocity, dtype=np.float64).reshape(2)
        self.robot_heading = float(robot_heading)
        self.robot_goal = np.array(robot_goal, dtype=np.float64).reshape(2)
        self.human_position = np.array(human_position, dtype=np.float64).reshape(self.num_humans, 2)
        self.human_velocity = np.array(human_velocity, dtype=np.float64).reshape(self.num_humans, 2)
        self.human_goal = np.array(human_goal, dtype=np.float64).reshape(self.num_humans, 2)
        self.human_goal_steps = np.array(human_goal_steps, dtype=np.int64).reshape(self.num_humans)
        self.step_count = int(step_count)

    @staticmethod
    def _episode_fields(state: Any, index: int) -> dict[str, Any]:
        def get(name):
            return np.asarray(getattr(state, name)[index].detach().cpu().double().numpy())

        return dict(
            robot_position=get("robot_position"),
            robot_velocity=get("robot_velocity"),
            robot_heading=float(get("robot_heading")),
            robot_goal=get("robot_goal"),
            human_position=get("human_position"),
            human_velocity=get("human_velocity"),
            human_goal=get("human_goal"),
            human_goal_steps=np.asarray(state.human_goal_steps[index].cpu().numpy()),
            step_count=int(state.step_count[index]),
        )

    @classmethod
    def from_state(cls, cfg: CrowdConfig, state: Any, index: int = 0, **kwargs) -> "ReferenceCrowdSim":
        """The episode ``index`` of a batched :class:`~crowdrl.sim.state.CrowdState`."""
        fields = cls._episode_fields(state, index)
        if fields["human_position"].shape[0] != cfg.num_humans:
            raise ValueError(f"state has {fields['human_position'].shape[0]} humans, cfg {cfg.num_humans}")
        return cls(cfg, **fields, **kwargs)

    def load_state(self, state: Any, index: int = 0) -> None:
        """Overwrite this episode's state with episode ``index`` of a batched state (re-sync)."""
        f = self._episode_fields(state, index)
        self._set(f["robot_position"], f["robot_velocity"], f["robot_heading"], f["robot_goal"],
                  f["human_position"], f["human_velocity"], f["human_goal"], f["human_goal_steps"],
                  f["step_count"])

    def positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Robot ``[2]`` and human ``[N, 2]`` positions (copies)."""
        return self.robot_position.copy(), self.human_position.copy()

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """Robot ``[2]`` and human ``[N, 2]`` velocities (copies)."""
        return self.robot_velocity.copy(), self.human_velocity.copy()

    # ------------------------------------------------------------------- step
    def _human_velocities(self) -> np.ndarray:
        sim = self._rvo
        for i in range(self.num_humans):
            px, py = float(self.human_position[i, 0]), float(self.human_position[i, 1])
            gx, gy = float(self.human_goal[i, 0]), float(self.human_goal[i, 1])
            dx, dy = gx - px, gy - py
            dist = math.hypot(dx, dy)
            if dist > 1:
                dx, dy = dx / dist, dy / dist
            sim.set_agent_position(i, (px, py))
            sim.set_agent_velocity(i, (float(self.human_velocity[i, 0]), float(self.human_velocity[i, 1])))
            sim.set_agent_pref_velocity(i, (dx, dy))
        sim.do_step()
        out = np.empty((self.num_humans, 2))
        for i in range(self.num_humans):
            out[i] = sim.get_agent_velocity(i).to_tuple()
        return out

    def step(self, action: int) -> tuple[float, bool, bool, dict[str, Any]]:
        """Advance by one step with unicycle action ``action``: ``(reward, terminated, truncated, info)``."""
        speed, rotation = action_speed_rotation(action, self.cfg.robot_v_pref)
        theta = self.robot_heading + rotation
        return self.step_velocity((speed * math.cos(theta), speed * math.sin(theta)), heading=theta)

    def step_velocity(self, velocity, heading: float | None = None) -> tuple[float, bool, bool, dict[str, Any]]:
        """One step with the robot's velocity given directly (heading defaults to its direction)."""
        cfg, dt = self.cfg, self.cfg.time_step
        vx, vy = float(velocity[0]), float(velocity[1])
        if heading is None:
            heading = math.atan2(vy, vx) if (vx != 0 or vy != 0) else self.robot_heading
        rx, ry = float(self.robot_position[0]), float(self.robot_position[1])
        gx, gy = float(self.robot_goal[0]), float(self.robot_goal[1])

        # 1. humans' ORCA velocities from the state at the start of the step
        new_hv = self._human_velocities()

        # 2. continuous collision check, human by human
        radii = cfg.human_radius + cfg.robot_radius
        dmin = np.empty(self.num_humans)
        for i in range(self.num_humans):
            px = float(self.human_position[i, 0]) - rx
            py = float(self.human_position[i, 1]) - ry
            rvx = float(new_hv[i, 0]) - vx
            rvy = float(new_hv[i, 1]) - vy
            ex, ey = px + rvx * dt, py + rvy * dt
            dmin[i] = point_to_segment_dist(px, py, ex, ey, 0.0, 0.0) - radii
        min_separation = float(dmin.min())
        collided = min_separation < 0
        discomfort_count = int(sum(1 for d in dmin if d < cfg.discomfort_dist))

        # 3. move
        new_rx, new_ry = rx + vx * dt, ry + vy * dt
        self.human_position = self.human_position + new_hv * dt
        d_before = math.hypot(rx - gx, ry - gy)
        d_after = math.hypot(new_rx - gx, new_ry - gy)
        reached = d_after < cfg.robot_radius

        # 4. reward
        reward = cfg.progress_factor * (d_before - d_after)
        for d in dmin:
            reward += min(0.0, float(d) - cfg.discomfort_dist)
        if collided:
            reward += cfg.collision_penalty
        elif reached:
            reward += cfg.goal_reward

        self.step_count += 1
        terminated = collided or reached
        truncated = (not terminated) and self.step_count >= cfg.max_steps
        if collided:
            event = COLLISION
        elif reached:
            event = SUCCESS
        elif truncated:
            event = TIMEOUT
        else:
            event = RUNNING

        self.robot_position = np.array([new_rx, new_ry])
        self.robot_velocity = np.array([vx, vy])
        self.robot_heading = _wrap(float(heading))
        self.human_velocity = new_hv

        # 5. non-stop humans
        new_goal_humans = []
        for i in range(self.num_humans):
            if math.hypot(*(self.human_position[i] - self.human_goal[i])) < cfg.human_radius:
                self.human_goal_steps[i] += 1
        for i in range(self.num_humans):  # all counted first: a new goal sees the others' old goals
            if self.human_goal_steps[i] >= cfg.goal_steps_before_new_goal:
                new_goal_humans.append(i)
        new_goals = {i: self._new_goal(i) for i in new_goal_humans}
        for i, goal in new_goals.items():
            self.human_goal[i] = goal
            self.human_velocity[i] = 0.0
            self.human_goal_steps[i] = 0

        info = {
            "event": event,
            "event_name": EVENT_NAMES[event],
            "reached": reached,
            "collided": collided,
            "timed_out": truncated,
            "min_separation": min_separation,
            "discomfort_count": discomfort_count,
            "human_distances": dmin,  # [N] closest surface distance of each human during the step
            "new_goal_humans": new_goal_humans,
        }
        return float(reward), terminated, truncated, info

    # -------------------------------------------------------------- new goals
    def _new_goal(self, human: int) -> tuple[float, float]:
        if self.new_goal_fn is not None:
            gx, gy = self.new_goal_fn(self, human)
            return float(gx), float(gy)
        cfg = self.cfg
        clearance = cfg.spawn_clearance
        others = [(self.robot_position, self.robot_goal)] + [
            (self.human_position[j], self.human_goal[j]) for j in range(self.num_humans) if j != human
        ]
        goal = (0.0, 0.0)
        for _ in range(NEW_GOAL_TRIES):
            if cfg.scenario == "circle":
                angle = self._rng.random() * 2 * math.pi
                goal = (cfg.circle_radius * math.cos(angle) + (self._rng.random() - 0.5) * cfg.human_v_pref,
                        cfg.circle_radius * math.sin(angle) + (self._rng.random() - 0.5) * cfg.human_v_pref)
            else:
                side = -1.0 if self._rng.random() > 0.5 else 1.0
                goal = (self._rng.random() * cfg.square_width * 0.5 * side,
                        (self._rng.random() - 0.5) * cfg.square_width)
            if all(math.hypot(goal[0] - p[0], goal[1] - p[1]) >= clearance
                   and math.hypot(goal[0] - g[0], goal[1] - g[1]) >= clearance for p, g in others):
                break
        return goal
