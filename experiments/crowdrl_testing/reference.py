"""A deliberately plain, single-episode reference simulator (CrowdNav style).

:class:`ReferenceCrowdSim` re-implements one episode of the MDP of ``docs/mdp.md`` the way the
reference implementations (CrowdNav, SG-D3QN) do it: python floats for the robot, small numpy
float64 arrays for the humans, one loop iteration per agent, and the RVO2 C++ library
(``pyrvo``, RVO2 2.0.3) for the humans' ORCA velocities, static obstacles included. It shares no
step code with the batched torch simulator (:mod:`crowdrl.sim.crowd`) but one pure function, the
humans' preferred velocities in ``doorway`` (below); it exists to check that simulator against
an independent implementation (``tests/test_reference_agreement.py``) and to time the
one-episode-at-a-time baseline (``experiments/bench_env.py``). :meth:`ReferenceCrowdSim.from_state`
only reads a :class:`~crowdrl.sim.state.CrowdState` (any object with the same tensor fields).

Obstacles (the scenarios corridor, doorway and room): the episode's polygons (``state.obstacles``,
only the vertices ``state.obstacle_mask`` marks valid; 2 vertices are a wall segment) are given to
RVO2 once, at construction (``add_obstacle`` in the state's polygon order, then
``process_obstacles``); they are static, so :meth:`ReferenceCrowdSim.load_state` refuses a state
with other obstacles.

Per step, in this order (``crowd.step`` order):

1. humans: every human's position, velocity and preferred velocity (vector to goal, scaled to
   unit length if longer than 1) is written into the episode's ``RVOSimulator`` (radius
   ``human_radius + 0.01``, max speed ``human_v_pref``, the ORCA parameters of
   :class:`~crowdrl.sim.config.CrowdConfig`, ``time_horizon_obst = orca_time_horizon_obst``), one
   ``do_step`` computes all new velocities from the state at the start of the step, and they
   are read back. RVO2 works in float32; positions are kept here in float64 and RVO2's own
   position update is discarded (overwritten at the next step). In ``doorway`` the preferred
   velocities head for the gap while the wall is between a human and its goal: they come from
   :func:`crowdrl.sim.crowd.preferred_velocities`, called on the episode's ``[N, 2]`` float64
   arrays (the only torch in :meth:`ReferenceCrowdSim.step`; one implementation of that rule).
2. robot: unicycle, ``theta <- wrap(theta + rot)``, ``v = speed * (cos theta, sin theta)``.
3. continuous collision check: the closest distance of each human's relative linear motion
   within the step to the robot, minus both radii (CrowdNav's ``point_to_segment_dist``); with
   obstacles, the robot's straight path over the step against every obstacle edge: closer than
   ``robot_radius`` (or crossing the edge) is a collision too (``info["obstacle_collision"]``).
4. move everybody by ``v * dt``; goal reached iff ``|p_robot - g| < robot_radius``.
5. reward: ``0.2 * (d_before - d_after) + sum_i min(0, dmin_i - 0.2)`` plus ``+0.25`` (goal) or
   ``-0.25`` (collision, with a human or an obstacle; collision has priority); terminated on
   collision or goal, truncated when the step count reaches ``max_steps`` without termination.
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
first new goal. In the obstacle scenarios the rule is :func:`crowdrl.sim.scenarios.new_human_goals`'
for them: up to 64 candidates on the other side (corridor: the other end; doorway: the other side
of the wall; room: a random side of the square), the first that keeps ``human_radius + margin``
from the obstacles with a straight path from where the human stands that keeps it too, preferably
also the spawn clearance from every agent's position and goal; none reachable: the goal stays.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from crowdrl.sim.config import CrowdConfig

# Event codes, equal to ``crowdrl.sim.crowd``'s (checked by the agreement test).
RUNNING, SUCCESS, COLLISION, TIMEOUT = 0, 1, 2, 3
EVENT_NAMES = ("running", "success", "collision", "timeout")

NEW_GOAL_TRIES = 16
OBSTACLE_GOAL_TRIES = 64  # crowdrl.sim.scenarios.OBSTACLE_GOAL_ROUNDS

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


def segment_distance(x1: float, y1: float, x2: float, y2: float,
                     x3: float, y3: float, x4: float, y4: float) -> float:
    """Distance between the segments (x1, y1)-(x2, y2) and (x3, y3)-(x4, y4): 0 when they cross,
    else the smallest distance of an endpoint to the other segment."""
    d1 = (x4 - x3) * (y1 - y3) - (y4 - y3) * (x1 - x3)
    d2 = (x4 - x3) * (y2 - y3) - (y4 - y3) * (x2 - x3)
    d3 = (x2 - x1) * (y3 - y1) - (y2 - y1) * (x3 - x1)
    d4 = (x2 - x1) * (y4 - y1) - (y2 - y1) * (x4 - x1)
    if d1 * d2 < 0 and d3 * d4 < 0:
        return 0.0
    return min(point_to_segment_dist(x3, y3, x4, y4, x1, y1), point_to_segment_dist(x3, y3, x4, y4, x2, y2),
               point_to_segment_dist(x1, y1, x2, y2, x3, y3), point_to_segment_dist(x1, y1, x2, y2, x4, y4))


def polygon_edges(polygons) -> list[tuple[float, float, float, float]]:
    """The edges ``(ax, ay, bx, by)`` of obstacle polygons: a wall (2 vertices) is one edge, a solid
    polygon of ``n`` vertices has ``n`` (the last closing it)."""
    edges = []
    for poly in polygons:
        n = len(poly)
        for k in range(1 if n == 2 else n):
            (ax, ay), (bx, by) = poly[k], poly[(k + 1) % n]
            edges.append((float(ax), float(ay), float(bx), float(by)))
    return edges


def _inside_solid(x: float, y: float, polygons) -> bool:
    """Whether the point lies inside (or on) a convex solid polygon (3+ counter-clockwise vertices)."""
    for poly in polygons:
        n = len(poly)
        if n >= 3 and all((poly[(k + 1) % n][0] - poly[k][0]) * (y - poly[k][1])
                          - (poly[(k + 1) % n][1] - poly[k][1]) * (x - poly[k][0]) >= 0 for k in range(n)):
            return True
    return False


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
        obstacles=(),
    ) -> None:
        """``obstacles``: the episode's static obstacle polygons, each ``[n, 2]`` (RVO2's convention:
        2 vertices a wall segment, 3 or more a counter-clockwise solid polygon); none by default."""
        if cfg.human_model != "orca" or cfg.robot_visible:
            raise ValueError("ReferenceCrowdSim simulates ORCA humans that do not see the robot only; got "
                             f"human_model={cfg.human_model!r}, robot_visible={cfg.robot_visible}")
        pyrvo = _import_pyrvo()
        self.cfg = cfg
        self.obstacles = tuple(tuple((float(x), float(y)) for x, y in np.asarray(poly, dtype=np.float64).reshape(-1, 2))
                               for poly in obstacles)
        if any(len(poly) < 2 for poly in self.obstacles):
            raise ValueError("an obstacle polygon needs at least 2 vertices (2: a wall segment)")
        self._edges = polygon_edges(self.obstacles)
        self._waypoints = cfg.scenario == "doorway"
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
        tho = cfg.orca_time_horizon_obst  # unused by RVO2 without obstacles
        self._rvo = pyrvo.RVOSimulator(
            cfg.time_step, cfg.orca_neighbor_dist, cfg.orca_max_neighbors, cfg.orca_time_horizon,
            tho, radius, cfg.human_v_pref,
        )
        for poly in self.obstacles:
            self._rvo.add_obstacle(list(poly))
        if self.obstacles:
            self._rvo.process_obstacles()
        for i in range(n):
            self._rvo.add_agent(
                (float(self.human_position[i, 0]), float(self.human_position[i, 1])),
                cfg.orca_neighbor_dist, cfg.orca_max_neighbors, cfg.orca_time_horizon, tho,
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

        polygons = ()
        obs, mask = getattr(state, "obstacles", None), getattr(state, "obstacle_mask", None)
        if obs is not None and obs.shape[1] > 0:  # [B, P, V, 2] and [B, P, V]: the valid vertices only
            verts, valid = get("obstacles"), np.asarray(mask[index].cpu().numpy(), dtype=bool)
            polygons = tuple(verts[p][valid[p]] for p in range(verts.shape[0]) if valid[p].sum() >= 2)
        return dict(
            obstacles=polygons,
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
        """Overwrite this episode's state with episode ``index`` of a batched state (re-sync); its
        obstacles must be this episode's (RVO2's are fixed at construction)."""
        f = self._episode_fields(state, index)
        obstacles = tuple(tuple((float(x), float(y)) for x, y in poly) for poly in f["obstacles"])
        if obstacles != self.obstacles:
            raise ValueError(f"episode {index} of the state has other obstacles than this simulator; "
                             "build a new one (ReferenceCrowdSim.from_state)")
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
    def preferred_velocities(self) -> np.ndarray:
        """``doorway``: the humans' preferred velocities ``[N, 2]`` (through the gap), by the batched
        simulator's pure function on this episode's arrays."""
        import torch  # noqa: PLC0415 - only the doorway needs it

        from crowdrl.sim.humans import preferred_velocities  # noqa: PLC0415

        return preferred_velocities(self.cfg, torch.from_numpy(self.human_position),
                                    torch.from_numpy(self.human_goal)).numpy()

    def _human_velocities(self) -> np.ndarray:
        sim = self._rvo
        pref = self.preferred_velocities() if self._waypoints else None
        for i in range(self.num_humans):
            px, py = float(self.human_position[i, 0]), float(self.human_position[i, 1])
            if pref is not None:
                dx, dy = float(pref[i, 0]), float(pref[i, 1])
            else:
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
        discomfort_count = int(sum(1 for d in dmin if d < cfg.discomfort_dist))

        # 3. move; the robot's path over the step against the obstacle edges
        new_rx, new_ry = rx + vx * dt, ry + vy * dt
        obstacle_collision = any(segment_distance(rx, ry, new_rx, new_ry, *edge) < cfg.robot_radius
                                 for edge in self._edges)
        collided = min_separation < 0 or obstacle_collision
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
            "obstacle_collision": obstacle_collision,  # the robot touched an obstacle (False without any)
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
        if self.obstacles:
            return self._new_obstacle_goal(human)
        clearance = cfg.spawn_clearance
        # every agent's position and goal, the robot's and the human's own included (the batched rule:
        # a goal next to where the human stands would be reached again at once)
        others = [(self.robot_position, self.robot_goal)] + [
            (self.human_position[j], self.human_goal[j]) for j in range(self.num_humans)
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

    def _new_obstacle_goal(self, human: int) -> tuple[float, float]:
        """A new goal in an obstacle scenario (the module docstring): reachable in a straight line."""
        cfg = self.cfg
        clear = cfg.human_radius + cfg.obstacle_clearance_margin
        hx, hy = float(self.human_position[human, 0]), float(self.human_position[human, 1])
        # every agent's position and goal, the human's own included (as in the batched rule)
        others = [self.robot_position, self.robot_goal, *self.human_position, *self.human_goal]
        fallback = None
        for _ in range(OBSTACLE_GOAL_TRIES):
            ux, uy, u_side = self._rng.random(), self._rng.random(), self._rng.random()
            if cfg.scenario == "room":  # square crossing: a random side of x
                side = -1.0 if u_side > 0.5 else 1.0
                goal = (ux * cfg.square_width * 0.5 * side, (uy - 0.5) * cfg.square_width)
            else:  # the other end of the corridor, the other side of the doorway's wall
                side = -1.0 if hy > 0 else 1.0
                if cfg.scenario == "corridor":
                    half_l = cfg.corridor_length / 2
                    goal = ((ux * 2 - 1) * (cfg.corridor_width / 2 - clear), side * half_l * (0.2 + 0.8 * uy))
                else:
                    half_w, half_h = min(cfg.doorway_width, cfg.square_width) / 2 - clear, cfg.square_width / 2
                    goal = ((ux * 2 - 1) * half_w, (clear + uy * (half_h - clear)) * side)
            gx, gy = goal
            reachable = not _inside_solid(gx, gy, self.obstacles) and all(
                point_to_segment_dist(ax, ay, bx, by, gx, gy) >= clear
                and segment_distance(hx, hy, gx, gy, ax, ay, bx, by) >= clear for ax, ay, bx, by in self._edges)
            if not reachable:
                continue
            if all(math.hypot(gx - p[0], gy - p[1]) >= cfg.spawn_clearance for p in others):
                return goal
            fallback = goal if fallback is None else fallback
        if fallback is not None:
            return fallback
        return float(self.human_goal[human, 0]), float(self.human_goal[human, 1])
