"""Constants of the crowd-navigation MDP (``docs/mdp.md``), validated once at construction."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from crowdrl.sim.kinematics import KINEMATICS

SCENARIOS = ("circle", "square", "corridor", "doorway", "room")
OPEN_SCENARIOS = ("circle", "square")  # no obstacles: the paper's scenarios
OBSTACLE_SCENARIOS = ("corridor", "doorway", "room")  # static obstacles (crowdrl.sim.scenarios)
# CrowdConfig's obstacle geometry keys (the Hydra env group's keys of the same names)
OBSTACLE_KEYS = ("corridor_width", "corridor_length", "doorway_gap", "doorway_width", "room_pillars",
                 "room_pillar_min", "room_pillar_max", "orca_time_horizon_obst", "obstacle_tokens")
LIDAR_KEYS = ("lidar_rays", "lidar_range")  # CrowdConfig's lidar keys (the Hydra env group's, every scenario)
# At most this many lidar rays: a fine 2-D lidar's resolution (0.35°). The scan is computed against every
# edge and disc at once ([B, rays, targets] floats per step), so a larger count would exhaust memory.
MAX_LIDAR_RAYS = 1024
ORCA_BACKENDS = ("eager", "compiled")  # compiled: crowdrl.sim.orca_compiled (torch.compile, minutes to build)
# How one human moves (crowdrl.sim.humans); a human's index here is its code in CrowdState.human_model.
HUMAN_MODELS = ("orca", "social_force", "linear")
MIXED = "mixed"  # human_model="mixed": a share of the crowd follows each of HUMAN_MODELS (the *_share keys)
HUMAN_MODEL_CHOICES = (*HUMAN_MODELS, MIXED)  # the values of CrowdConfig.human_model
SHARE_KEYS = ("social_force_share", "linear_share")  # human_model="mixed": the shares of the non-ORCA models
# CrowdConfig's keys of the humans' model (the Hydra env group's keys of the same names)
HUMAN_KEYS = ("human_model", "robot_visible", "sf_tau", "sf_v0", "sf_sigma", "sf_substeps", *SHARE_KEYS)
# read only where social-force humans may be present (human_model="social_force", or "mixed" with a social_force_share)
SOCIAL_FORCE_KEYS = ("sf_tau", "sf_v0", "sf_sigma", "sf_substeps")
MAX_HUMANS = 64  # spawn rejection sampling is sized for this many; more cannot be placed reliably
# Spawn feasibility of the obstacle scenarios (CrowdConfig.max_spawnable_humans): the agents' points that one
# start or goal region must hold, at most this share of its cells (the region grown by the spawn clearance s
# on each side, in units of s^2); calibrated on 20k-episode spawns at the default geometry (docs/mdp.md), where
# the bound gives corridor 14, doorway 14, room 18 humans, a few below the first crowds that ever failed
# (corridor 16, doorway 17, room 24)
# room: the least chance of a candidate start and goal (clear paths' share times the square left free, squared)
SPAWN_DENSITY = {"corridor": 0.29, "doorway": 0.10, "room": 0.10}
# room: K pillars leave the humans' straight crossing paths (1 - d / square_width)^K of the square, d a pillar's
# largest width plus the obstacle clearance on both sides; pillar centres at most this share of their cells
PILLAR_DENSITY = 0.5


def is_integer(value: object) -> bool:
    """Whether ``value`` is an integer (``int``, a numpy integer), not a bool and not a float such as ``10.0``:
    a count given as a float would pass a range check and fail later, far from its key."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


@dataclass(frozen=True)
class CrowdConfig:
    """Every number that defines one crowd-navigation episode.

    Defaults are the paper's (upstream SG-D3QN / CrowdNav) values.
    """

    scenario: str = "circle"
    num_humans: int = 10  # the crowd size, or its maximum when min_humans is smaller
    # A crowd of variable size: each episode draws its size uniformly from min_humans..num_humans
    # (a pure function of its episode id); tensors hold num_humans, absent ones masked. None: fixed.
    min_humans: int | None = None
    time_step: float = 0.25
    time_limit: float = 29.25  # upstream's 30 s limit fires at t >= 29 s: 117 steps
    robot_radius: float = 0.3
    robot_v_pref: float = 1.0
    human_radius: float = 0.3
    human_v_pref: float = 1.0
    circle_radius: float = 4.0
    square_width: float = 10.0
    circle_humans_max: int = 5  # circle scenario: the first 5 humans are circle humans
    discomfort_dist: float = 0.2
    goal_reward: float = 0.25
    collision_penalty: float = -0.25
    progress_factor: float = 0.2
    goal_steps_before_new_goal: int = 2  # non-stop humans: steps within radius of goal
    # ORCA parameters of the humans (CrowdNav's ORCA policy)
    orca_neighbor_dist: float = 10.0
    orca_max_neighbors: int = 10
    orca_time_horizon: float = 5.0
    orca_radius_margin: float = 0.01  # CrowdNav adds 0.01 m to every ORCA radius
    orca_backend: str = "eager"  # "compiled" for the torch.compile backend (same numbers, faster)
    # Collision check over the step with the humans' velocities of this step ("new", the motion
    # that happens) or, as upstream CrowdNav did, those from the start of the step ("start").
    collision_velocity: str = "new"
    # Static obstacles (scenarios corridor, doorway, room; docs in crowdrl.sim.scenarios). The robot
    # still goes from (0, -circle_radius) to (0, circle_radius).
    corridor_width: float = 4.0  # corridor: the distance between its two walls (x = -w/2 and +w/2)
    corridor_length: float = 10.0  # corridor: the walls' length, centred on the origin along y
    doorway_gap: float = 2.0  # doorway: the gap's width, centred on x = 0 in the wall y = 0
    doorway_width: float = 10.0  # doorway: the wall's full length along x (gap included)
    room_pillars: int = 4  # room: convex pillars (rectangles at random positions and angles)
    room_pillar_min: float = 0.5  # room: a pillar's side lengths, each uniform in [min, max]
    room_pillar_max: float = 1.5
    # ORCA time horizon of the humans towards obstacles (RVO2's timeHorizonObst): CrowdNav's ORCA
    # policy and RVO2's examples use 5 s, as for other agents.
    orca_time_horizon_obst: float = 5.0
    # The robot observes the obstacle edges nearest to it: at most this many (``"obstacles"``
    # ``[B, K, 4]``, K = min(obstacle_tokens, the scenario's edge count); crowdrl.envs.CrowdNavEnv).
    obstacle_tokens: int = 8
    # A 2-D lidar scan in the observation (``"lidar"`` ``[B, lidar_rays]``, every scenario; conventions in
    # crowdrl.sim.lidar): lidar_rays rays from the robot's centre, evenly spaced over 360° counter-clockwise
    # from its heading, against the obstacle edges and the humans' discs, clipped at lidar_range metres
    # (a 4 m range: the circle's radius). 0 rays: no scan; at most MAX_LIDAR_RAYS (1024).
    lidar_rays: int = 0
    lidar_range: float = 4.0
    # The robot: the paper's unicycle with 81 discrete actions, or holonomic (a continuous velocity
    # clipped to robot_v_pref; the ORCA robot baseline acts this way).
    robot_kinematics: str = "unicycle"
    # How the humans move (crowdrl.sim.humans): "orca" (RVO2's, the paper's), "social_force" (Helbing-Molnar
    # as the socialforce 0.2.3 package computes it; open scenarios only) or "linear" (straight to the goal);
    # "mixed": a crowd with a share of each, social_force_share and linear_share of it, ORCA the rest
    # (per episode, the social-force humans are round(social_force_share * n) of its n present humans, the
    # social-force and linear ones together round((social_force_share + linear_share) * n), halves rounded up;
    # which humans follow which model is drawn from the episode's own random numbers: model_counts,
    # crowdrl.sim.scenarios.assign_human_models).
    human_model: str = "orca"
    social_force_share: float = 0.0  # human_model="mixed" only: in [0, 1]; with linear_share, sum <= 1
    linear_share: float = 0.0
    # Whether the humans see the robot (one more ORCA neighbour / social-force pedestrian); invisible in the paper.
    robot_visible: bool = False
    # Social force (socialforce 0.2.3's defaults): relaxation time tau (s), the repulsive potential's
    # V0 (m^2/s^2) and sigma (m), and the leapfrog sub-steps per time step (the package's oversampling).
    sf_tau: float = 0.5
    sf_v0: float = 2.1
    sf_sigma: float = 0.3
    sf_substeps: int = 10

    def __post_init__(self) -> None:
        if self.orca_backend not in ORCA_BACKENDS:
            raise ValueError(f"orca_backend must be one of {ORCA_BACKENDS}, got {self.orca_backend!r}")
        if self.collision_velocity not in ("new", "start"):
            raise ValueError(f"collision_velocity must be 'new' or 'start', got {self.collision_velocity!r}")
        if self.robot_kinematics not in KINEMATICS:
            raise ValueError(f"robot_kinematics must be one of {KINEMATICS}, got {self.robot_kinematics!r}")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario must be one of {SCENARIOS}, got {self.scenario!r}")
        if not is_integer(self.num_humans) or self.num_humans < 1:
            raise ValueError(f"num_humans must be an integer >= 1, got {self.num_humans!r}")
        if self.num_humans > MAX_HUMANS:
            raise ValueError(
                f"num_humans={self.num_humans} cannot be placed with the spawn clearance in a "
                f"{self.square_width} m square; at most {MAX_HUMANS} are supported"
            )
        if self.min_humans is not None and not (is_integer(self.min_humans) and 1 <= self.min_humans <= self.num_humans):
            raise ValueError(f"min_humans must be an integer in 1..num_humans ({self.num_humans}), got {self.min_humans!r}")
        for name in ("time_step", "time_limit", "robot_radius", "human_radius", "robot_v_pref",
                     "human_v_pref", "circle_radius", "square_width", "orca_time_horizon"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        self._check_obstacle_keys()
        self._check_human_keys()
        if not is_integer(self.lidar_rays) or not 0 <= self.lidar_rays <= MAX_LIDAR_RAYS:
            raise ValueError(f"lidar_rays must be an integer in 0..{MAX_LIDAR_RAYS} (0: no scan), got {self.lidar_rays!r}")
        if isinstance(self.lidar_range, bool) or not (isinstance(self.lidar_range, (int, float))
                                                      and math.isfinite(self.lidar_range) and self.lidar_range > 0):
            raise ValueError(f"lidar_range must be a finite number > 0, got {self.lidar_range!r}")
        if self.time_limit < self.time_step:
            raise ValueError(f"time_limit ({self.time_limit}) must be >= time_step ({self.time_step})")
        if self.discomfort_dist < 0:
            raise ValueError(f"discomfort_dist must be >= 0, got {self.discomfort_dist}")
        if self.orca_neighbor_dist < 0:
            raise ValueError(f"orca_neighbor_dist must be >= 0, got {self.orca_neighbor_dist!r}")
        if not is_integer(self.orca_max_neighbors) or self.orca_max_neighbors < 0:
            raise ValueError(f"orca_max_neighbors must be an integer >= 0, got {self.orca_max_neighbors!r}")
        if not is_integer(self.goal_steps_before_new_goal) or self.goal_steps_before_new_goal < 1:
            raise ValueError(f"goal_steps_before_new_goal must be an integer >= 1, got {self.goal_steps_before_new_goal!r}")

    def _check_human_keys(self) -> None:
        """The humans' model keys (the social-force parameters checked whatever the model, so that a bad
        value is named even before it is used)."""
        if self.human_model not in HUMAN_MODEL_CHOICES:
            raise ValueError(f"human_model must be one of {HUMAN_MODEL_CHOICES}, got {self.human_model!r}")
        if not isinstance(self.robot_visible, bool):
            raise ValueError(f"robot_visible must be true or false, got {self.robot_visible!r}")
        for name in ("sf_tau", "sf_v0", "sf_sigma"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not is_integer(self.sf_substeps) or self.sf_substeps < 1:
            raise ValueError(f"sf_substeps must be an integer >= 1, got {self.sf_substeps!r}")
        if self.human_model == "social_force" and self.scenario in OBSTACLE_SCENARIOS:
            raise ValueError(f"human_model='social_force' runs in the open scenarios {OPEN_SCENARIOS} only, got "
                             f"scenario={self.scenario!r} (its reference, socialforce 0.2.3, samples walls as "
                             "points; use human_model='orca' or 'linear' among obstacles)")
        self._check_shares()

    def _check_shares(self) -> None:
        """``human_model="mixed"``'s shares: each a number in [0, 1], their sum at most 1 (the rest: ORCA);
        given (non-zero) only with ``human_model="mixed"``; a social-force share in the open scenarios only."""
        for name in SHARE_KEYS:
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                               and 0 <= value <= 1):
                raise ValueError(f"{name} must be a finite number in [0, 1], got {value!r}")
            if value != 0 and self.human_model != MIXED:
                raise ValueError(f"{name} ({value!r}) applies to human_model='mixed' only, got "
                                 f"human_model={self.human_model!r} (set human_model='mixed' for a crowd with a share "
                                 f"of each model, or {name}=0)")
        total = self.social_force_share + self.linear_share
        if total > 1 + 1e-9:
            raise ValueError(f"social_force_share + linear_share must be <= 1 (the rest of the crowd is ORCA), got "
                             f"{self.social_force_share!r} + {self.linear_share!r} = {total!r}")
        if self.social_force_share > 0 and self.scenario in OBSTACLE_SCENARIOS:
            raise ValueError(f"social_force_share ({self.social_force_share!r}) must be 0 in scenario={self.scenario!r}: "
                             f"social-force humans run in the open scenarios {OPEN_SCENARIOS} only (their reference, "
                             "socialforce 0.2.3, samples walls as points; mix ORCA and linear humans among obstacles)")

    @property
    def model_shares(self) -> tuple[float, float]:
        """The cumulative shares ``(s, s + l)`` of the social-force and linear humans (``s = 1`` for
        ``human_model="social_force"``, ``s + l = 1`` for ``"linear"``, both 0 for ``"orca"``); the sum is
        clipped to 1."""
        if self.human_model != MIXED:
            s = 1.0 if self.human_model == "social_force" else 0.0
            return s, 1.0 if self.human_model in ("social_force", "linear") else 0.0
        return float(self.social_force_share), min(float(self.social_force_share + self.linear_share), 1.0)

    def model_counts(self, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per episode of ``present`` humans (``[B]`` int64), how many follow each model: ``(social_force,
        linear)`` (``[B]`` int64; ORCA the rest). The social-force humans are ``round(s * n)``, the social-force
        and linear ones together ``round((s + l) * n)`` (:attr:`model_shares`; halves rounded up, in float64), so
        the three counts always sum to ``n`` and each share's count lies within one human of ``share * n``."""
        n = present.to(torch.float64)
        s, sl = self.model_shares
        first = torch.floor(s * n + 0.5).long()
        both = torch.floor(sl * n + 0.5).long()
        return first, both - first

    @property
    def human_models_present(self) -> tuple[str, ...]:
        """The models of :data:`HUMAN_MODELS` that some human of some episode follows, in that order: the
        config's model, or for ``"mixed"`` those that :meth:`model_counts` gives a human at any crowd size
        ``min_humans..num_humans``."""
        if self.human_model != MIXED:
            return (self.human_model,)
        low = self.min_humans if self.variable_crowd else self.num_humans
        sizes = torch.arange(low, self.num_humans + 1)
        sf, lin = self.model_counts(sizes)
        counts = (sizes - sf - lin, sf, lin)
        return tuple(m for m, c in zip(HUMAN_MODELS, counts) if bool((c > 0).any()))

    @property
    def humans_react_to_robot(self) -> bool:
        """Whether the robot's motion changes the humans' (``robot_visible`` with humans of a model that looks
        at others: ORCA or social force; linear humans ignore everyone; in a mixed crowd, whether some episode
        has an ORCA or a social-force human, :attr:`human_models_present`). A feature that replays a step with
        another robot action and the same humans must refuse such a config."""
        return self.robot_visible and any(m != "linear" for m in self.human_models_present)

    def _check_obstacle_keys(self) -> None:
        """The obstacle geometry's keys: finite, positive, and roomy enough for the agents (checked
        whatever the scenario, so that a bad value is named even before it is used)."""
        for name in ("corridor_width", "corridor_length", "doorway_gap", "doorway_width", "room_pillar_min",
                     "room_pillar_max", "orca_time_horizon_obst"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not is_integer(self.room_pillars) or self.room_pillars < 0:
            raise ValueError(f"room_pillars must be an integer >= 0, got {self.room_pillars!r}")
        if not is_integer(self.obstacle_tokens) or self.obstacle_tokens < 1:
            raise ValueError(f"obstacle_tokens must be an integer >= 1, got {self.obstacle_tokens!r}")
        if self.room_pillar_min > self.room_pillar_max:
            raise ValueError(f"room_pillar_min ({self.room_pillar_min}) must be <= room_pillar_max "
                             f"({self.room_pillar_max})")
        if self.scenario not in OBSTACLE_SCENARIOS:
            return
        need = 2 * (max(self.human_radius, self.robot_radius) + self.obstacle_clearance_margin)
        if self.scenario == "corridor":
            if self.corridor_width <= need:
                raise ValueError(f"corridor_width ({self.corridor_width}) must exceed {need:g} m (an agent's "
                                 "diameter plus its obstacle clearance on both sides)")
            if self.corridor_length < 2 * self.circle_radius:
                raise ValueError(f"corridor_length ({self.corridor_length}) must be >= 2 * circle_radius "
                                 f"({2 * self.circle_radius:g}): the robot starts and ends inside the corridor")
        if self.scenario == "doorway":
            if self.doorway_gap <= need:
                raise ValueError(f"doorway_gap ({self.doorway_gap}) must exceed {need:g} m (an agent's diameter "
                                 "plus its obstacle clearance on both sides)")
            if self.doorway_width <= self.doorway_gap:
                raise ValueError(f"doorway_width ({self.doorway_width}) must exceed doorway_gap ({self.doorway_gap})")
        self._check_spawn_feasible()

    def _check_spawn_feasible(self) -> None:
        """An obstacle scenario's crowd (and room's pillars) must fit its geometry (:attr:`max_spawnable_humans`,
        :attr:`pillars_fit`), so that a run is refused at start rather than failing to spawn an episode hours in."""
        keys = {"corridor": "corridor_width, corridor_length", "doorway": "doorway_gap, doorway_width, square_width",
                "room": "room_pillars, room_pillar_max, square_width"}[self.scenario]
        if self.scenario == "room" and not self.pillars_fit:
            raise ValueError(f"room_pillars ({self.room_pillars}) pillars of sides up to room_pillar_max "
                             f"({self.room_pillar_max}) m cannot be placed apart in a {self.square_width} m square "
                             "(square_width); use fewer or smaller pillars or a larger square")
        bound = self.max_spawnable_humans
        if self.num_humans > bound:
            raise ValueError(f"num_humans ({self.num_humans}) cannot be spawned reliably in scenario {self.scenario} "
                             f"with this geometry ({keys}): at most {bound} humans keep the spawn clearance "
                             f"({self.spawn_clearance:g} m) and clear straight paths (docs/mdp.md); use fewer humans "
                             "or roomier obstacles")

    @property
    def pillars_fit(self) -> bool:
        """``room``: whether its pillars fit apart: the ``room_pillars`` discs of a pillar's circumradius plus
        half the passage between pillars hold at most :data:`PILLAR_DENSITY` of the centres' square (grown by
        that radius on each side)."""
        radius = self.room_pillar_max / math.sqrt(2) + self.human_radius + self.obstacle_clearance_margin
        side = self.square_width - 2.0 + 2 * radius
        return self.room_pillars * (2 * radius) ** 2 <= PILLAR_DENSITY * side * side

    @property
    def max_spawnable_humans(self) -> int:
        """The largest crowd that an obstacle scenario spawns reliably (:data:`MAX_HUMANS` in the open ones).

        The agents' points that one start or goal region holds (the busier direction's humans, ``ceil(n / 2)``,
        plus the robot's start or goal in corridor and doorway; all ``n`` humans plus the robot in room) are at
        most :data:`SPAWN_DENSITY` of the region's cells, ``(w + s) (l + s) / s^2`` for a ``w x l`` region and the
        spawn clearance ``s``: corridor, the goal region (``corridor_width`` less the obstacle clearance on both
        sides, by ``0.4 * corridor_length``); doorway, one side (``min(doorway_width, square_width)`` less the
        clearances by ``square_width / 2`` less one), times the share of the gap a straight path can use
        (``doorway_gap`` less the clearances, per the agent's cleared diameter, at most 1). Room: a candidate's
        chance, the share of crossing paths its pillars leave clear (:data:`PILLAR_DENSITY`'s note) times the
        square's share left free by the points' discs of radius ``s`` (for its start, then its goal), at least
        :data:`SPAWN_DENSITY`."""
        if self.scenario not in OBSTACLE_SCENARIOS:
            return MAX_HUMANS
        s, clear = self.spawn_clearance, self.human_radius + self.obstacle_clearance_margin
        density = SPAWN_DENSITY[self.scenario]
        if self.scenario == "corridor":
            cells = (self.corridor_width - 2 * clear + s) * (0.4 * self.corridor_length + s) / s**2
        elif self.scenario == "doorway":
            width = min(self.doorway_width, self.square_width) - 2 * clear
            window = min(1.0, (self.doorway_gap - 2 * clear) / (2 * clear))
            cells = (width + s) * (self.square_width / 2 - clear + s) / s**2 * window
        else:  # a candidate's chance: the clear paths' share times the square's share the others leave (start, goal)
            blocked = self.room_pillar_max * math.sqrt(2) + 2 * clear
            clear_paths = max(0.0, 1.0 - blocked / self.square_width) ** self.room_pillars
            if clear_paths <= density:
                return 0
            free = 1.0 - math.sqrt(density / clear_paths)  # the share of the square the agents' discs may exclude
            cells = free * (self.square_width + s) ** 2 / (math.pi * s**2)
            density = 1.0
        points = math.floor(density * cells + 1e-9)
        humans = points - 1 if self.scenario == "room" else 2 * (points - 1)  # room: all n share it; else ceil(n/2)
        return max(0, min(MAX_HUMANS, humans))

    @property
    def obstacles_shape(self) -> tuple[int, int]:
        """``(P, V)``: the polygons and vertices per polygon of every episode's obstacles (``(0, 2)``
        for the open scenarios: no obstacles)."""
        if self.scenario in ("corridor", "doorway"):
            return 2, 2  # two wall segments
        if self.scenario == "room":
            return self.room_pillars, 4
        return 0, 2

    @property
    def num_obstacle_edges(self) -> int:
        """The edges of every episode's obstacles: a wall has one, a solid polygon one per vertex."""
        P, V = self.obstacles_shape
        return P * (1 if V == 2 else V)

    @property
    def num_obstacle_tokens(self) -> int:
        """``K``: the obstacle edges the robot observes (0 in the open scenarios)."""
        return min(self.obstacle_tokens, self.num_obstacle_edges)

    @property
    def obstacle_clearance_margin(self) -> float:
        """Margin beyond an agent's radius that spawns, goals and the humans' straight paths keep from
        obstacles (the discomfort distance, 0.2 m)."""
        return self.discomfort_dist

    @property
    def variable_crowd(self) -> bool:
        """Whether episodes draw their crowd size (``min_humans < num_humans``)."""
        return self.min_humans is not None and self.min_humans < self.num_humans

    @property
    def max_steps(self) -> int:
        """Steps before truncation (117 for 29.25 s at 0.25 s)."""
        return int(math.floor(self.time_limit / self.time_step + 1e-9))

    @property
    def spawn_clearance(self) -> float:
        """Minimum start/goal distance between two agents at spawn (0.8 m)."""
        return self.human_radius + max(self.human_radius, self.robot_radius) + self.discomfort_dist

    @property
    def num_circle_humans(self) -> int:
        return min(self.num_humans, self.circle_humans_max) if self.scenario == "circle" else 0
