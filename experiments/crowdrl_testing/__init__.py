"""The test support shared by ``tests/`` and the scripts of ``experiments/``: random ORCA scenes
and their RVO2 answers (through pyrvo), plausible robot-centric states, a run killed mid-training;
:mod:`crowdrl_testing.reference`, the plain RVO2-based reference simulator.

Not part of the library and not in its wheel. It lives in ``experiments/``, the folder both import
from: a script run as ``python experiments/<name>.py`` has it on ``sys.path``, and pytest puts it
there (``pythonpath`` in ``pyproject.toml``). :func:`rvo2_velocities` needs ``pyrvo``, a
test/benchmark-only install (``make install``); it is imported when that function is called, so
importing this package does not need it.
"""

from __future__ import annotations

import numpy as np
import torch

from crowdrl.sim.orca import OrcaParams

KINDS = ("crowd", "dense", "overlap", "many")
ORCA_TOLERANCE = 1e-4  # m/s: the accepted |dv| between our ORCA and RVO2 on well-conditioned agents
SCENE_PARAMS = OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0)  # the scenes' ORCA


def random_scene(rng: np.random.Generator, kind: str, n: int | None = None) -> dict[str, np.ndarray]:
    """One scene of ``kind`` (see :data:`KINDS`): positions, velocities, preferred velocities,
    radius and max speed, float32-exact. ``n`` agents, or a random count for the kind if ``None``.

    ``crowd``: spread over a 10 m square; ``dense``: clustered with surface gaps of 1-50 mm;
    ``overlap``: clustered, some overlapping by up to 0.15 m; ``many``: 12-40 agents of random
    radius. Radius 0.31 m (the humans' ORCA radius) except for ``many``; max speed 1 m/s.
    """
    counts = {"crowd": (2, 12), "dense": (4, 14), "overlap": (3, 10), "many": (12, 41)}
    if kind not in counts:
        raise ValueError(f"unknown scene kind {kind!r}; expected one of {KINDS}")
    if n is None:
        n = int(rng.integers(*counts[kind]))
    if kind == "dense":
        pos = _cluster(rng, n, gap_lo=1e-3, gap_hi=5e-2)
    elif kind == "overlap":
        pos = _cluster(rng, n, gap_lo=-0.15, gap_hi=0.02)
    else:
        pos = rng.uniform(-5, 5, (n, 2))
    radius = np.full(n, 0.31) if kind != "many" else rng.uniform(0.2, 0.4, n)
    speed = rng.uniform(0, 1, n)
    ang = rng.uniform(0, 2 * np.pi, n)
    vel = np.stack((speed * np.cos(ang), speed * np.sin(ang)), -1)
    goals = -pos + rng.normal(0, 0.5, (n, 2)) if kind in ("dense", "overlap") else rng.uniform(-5, 5, (n, 2))
    pref = goals - pos
    norm = np.linalg.norm(pref, axis=-1, keepdims=True)
    pref = np.where(norm > 1, pref / np.maximum(norm, 1e-9), pref)
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return {"positions": f32(pos), "velocities": f32(vel), "pref_velocities": f32(pref),
            "radius": f32(radius), "max_speed": f32(np.ones(n))}


def _cluster(rng: np.random.Generator, n: int, gap_lo: float, gap_hi: float) -> np.ndarray:
    """Agents placed one by one touching an earlier one, with a surface gap in [gap_lo, gap_hi]."""
    pos = [np.zeros(2)]
    for _ in range(1, n):
        anchor = pos[int(rng.integers(len(pos)))]
        ang = rng.uniform(0, 2 * np.pi)
        dist = 0.62 + rng.uniform(gap_lo, gap_hi)
        pos.append(anchor + dist * np.array([np.cos(ang), np.sin(ang)]))
    return np.array(pos)


def rvo2_velocities(scene: dict[str, np.ndarray], params: OrcaParams = SCENE_PARAMS) -> np.ndarray:
    """One RVO2 ``doStep`` of ``scene`` through pyrvo with ``params``: the new velocities ``[n, 2]`` (float64).

    ``scene["obstacles"]``, if present, lists polygons ``[n_vertices, 2]`` (RVO2's convention), added
    in order and processed before the agents are added."""
    import pyrvo

    constants = (params.neighbor_dist, params.max_neighbors, params.time_horizon, params.obstacle_horizon)
    sim = pyrvo.RVOSimulator(params.time_step, *constants, 0.3, 1.0)
    for polygon in scene.get("obstacles", ()):
        sim.add_obstacle([tuple(map(float, v)) for v in polygon])
    sim.process_obstacles()
    for p, v, r, m in zip(scene["positions"], scene["velocities"], scene["radius"], scene["max_speed"]):
        sim.add_agent(tuple(map(float, p)), *constants, float(r), float(m), tuple(map(float, v)))
    for i, pv in enumerate(scene["pref_velocities"]):
        sim.set_agent_pref_velocity(i, tuple(map(float, pv)))
    sim.do_step()
    return np.array([sim.get_agent_velocity(i).to_tuple() for i in range(len(scene["positions"]))], dtype=np.float64)


def padded_batch(scenes: list[dict[str, np.ndarray]],
                 dtype: torch.dtype = torch.float32) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Stack scenes of different sizes into ``[B, Nmax]`` tensors and a presence mask ``[B, Nmax]``;
    absent agents sit at the origin with zero velocity (the mask, not the distance, excludes them)."""
    n_max = max(len(s["positions"]) for s in scenes)
    B = len(scenes)
    out = {k: torch.zeros(B, n_max, 2, dtype=dtype) for k in ("positions", "velocities", "pref_velocities")}
    out.update({k: torch.ones(B, n_max, dtype=dtype) for k in ("radius", "max_speed")})
    mask = torch.zeros(B, n_max, dtype=torch.bool)
    for b, s in enumerate(scenes):
        n = len(s["positions"])
        for k in out:
            out[k][b, :n] = torch.as_tensor(np.asarray(s[k]), dtype=dtype)
        mask[b, :n] = True
    return out, mask



OBSTACLE_KINDS = ("walls", "pillars", "gap", "concave", "room")


def random_obstacle_scene(rng: np.random.Generator, kind: str) -> dict[str, np.ndarray | list[np.ndarray]]:
    """A scene among static obstacles (see :data:`OBSTACLE_KINDS`), float32-exact, for ORCA tests.

    ``walls``: random wall segments; ``pillars``: convex polygons; ``gap``: two boxes or two
    collinear walls with a narrow gap (about one to three agent diameters); ``concave``: L, U and
    star polygons; ``room``: four walls around pillars (many edges within reach). Agents (3 to 8,
    radius 0.2-0.4 m, max speed 0.5-1.5 m/s) are placed near corners, touching or overlapping edges
    (surface gap -0.5r to +0.3r), in the gaps, or anywhere, never inside a solid polygon.
    ``obstacles`` lists the polygons (counter-clockwise, 2 vertices for a wall).
    """
    if kind not in OBSTACLE_KINDS:
        raise ValueError(f"unknown obstacle scene kind {kind!r}; expected one of {OBSTACLE_KINDS}")
    polys: list[np.ndarray] = []
    gaps: list[np.ndarray] = []

    def box(c, w, h, ang=0.0):
        pts = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
        rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        return c + pts @ rot.T

    def convex(c):
        n = int(rng.integers(3, 8))
        ang = np.cumsum(rng.uniform(0.3, 1.0, n))
        ang = ang / ang[-1] * 2 * np.pi + rng.uniform(0, 2 * np.pi)
        rad = rng.uniform(0.4, 1.5)
        return c + rad * np.stack((np.cos(ang), np.sin(ang)), -1)

    def wall(c):
        a, length = rng.uniform(0, np.pi), rng.uniform(1, 6)
        d = 0.5 * length * np.array([np.cos(a), np.sin(a)])
        return np.array([c - d, c + d])

    if kind == "walls":
        polys = [wall(rng.uniform(-4, 4, 2)) for _ in range(int(rng.integers(1, 6)))]
    elif kind == "pillars":
        polys = [convex(rng.uniform(-4, 4, 2)) for _ in range(int(rng.integers(1, 5)))]
    elif kind == "gap":
        g = rng.uniform(0.5, 1.6)
        a = rng.uniform(0, np.pi)
        d, n = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
        if rng.random() < 0.5:
            w = rng.uniform(1, 3)
            polys = [box(side * (g / 2 + w / 2) * d, w, rng.uniform(0.3, 2), a) for side in (1, -1)]
        else:
            polys = [np.array([g / 2 * d, (g / 2 + rng.uniform(1, 4)) * d]),
                     np.array([-(g / 2 + rng.uniform(1, 4)) * d, -g / 2 * d])]
        gaps = [rng.uniform(-0.2, 0.2) * d + t * n for t in (-1.0, -0.3, 0.0, 0.3, 1.0)]
        if rng.random() < 0.5:
            polys.append(wall(rng.uniform(-3, 3, 2)))
    elif kind == "concave":
        for _ in range(int(rng.integers(1, 3))):
            c = rng.uniform(-3, 3, 2)
            shape = int(rng.integers(3))
            if shape == 0:  # L
                w, t = rng.uniform(1, 3), rng.uniform(0.3, 0.9)
                q = np.array([[0, 0], [w, 0], [w, t], [t, t], [t, w], [0, w]])
            elif shape == 1:  # U
                w, t = rng.uniform(1.5, 3), rng.uniform(0.3, 0.6)
                q = np.array([[0, 0], [w, 0], [w, w], [w - t, w], [w - t, t], [t, t], [t, w], [0, w]])
            else:  # star
                k = int(rng.integers(4, 7))
                ang = np.arange(2 * k) * np.pi / k
                rad = np.where(np.arange(2 * k) % 2 == 0, rng.uniform(1, 2), rng.uniform(0.3, 0.8))
                q = np.stack((rad * np.cos(ang), rad * np.sin(ang)), -1)
            ang = rng.uniform(0, 2 * np.pi)
            rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
            polys.append(c + q @ rot.T)
        if rng.random() < 0.5:
            polys.append(convex(rng.uniform(-4, 4, 2)))
    else:  # room
        h = rng.uniform(2.5, 5)
        corners = [np.array([-h, -h]), np.array([h, -h]), np.array([h, h]), np.array([-h, h])]
        polys = [np.array([corners[i], corners[(i + 1) % 4]]) for i in range(4)]
        polys += [convex(rng.uniform(-h + 1, h - 1, 2)) for _ in range(int(rng.integers(1, 4)))]
    polys = [np.asarray(p, dtype=np.float32) for p in polys]

    solids = [p for p in polys if len(p) >= 3]
    edges = [(p[i], p[(i + 1) % len(p)]) for p in polys for i in range(len(p) if len(p) > 2 else 1)]
    vertices = np.concatenate(polys)

    def inside(x):  # even-odd rule
        for p in solids:
            y0, y1 = p[:, 1], np.roll(p[:, 1], -1)
            x0, x1 = p[:, 0], np.roll(p[:, 0], -1)
            cross = (y0 > x[1]) != (y1 > x[1])
            xs = x0 + (x[1] - y0) * (x1 - x0) / np.where(y1 != y0, y1 - y0, 1)
            if np.sum(cross & (x[0] < xs)) % 2 == 1:
                return True
        return False

    n = int(rng.integers(3, 9))
    radius = rng.uniform(0.2, 0.4, n)
    pos = []
    for i in range(n):
        for _ in range(100):
            how = rng.random()
            if how < 0.3:  # near a corner
                x = vertices[int(rng.integers(len(vertices)))] + rng.normal(0, 0.6, 2)
            elif how < 0.6:  # touching an edge (either side; solids reject the inner one)
                a, b = edges[int(rng.integers(len(edges)))]
                e = b - a
                nrm = np.array([e[1], -e[0]]) / np.linalg.norm(e) * rng.choice([-1, 1])
                x = a + rng.uniform(-0.1, 1.1) * e + nrm * radius[i] * (1 + rng.uniform(-0.5, 0.3))
            elif how < 0.8 and gaps:
                x = gaps[int(rng.integers(len(gaps)))] + rng.normal(0, 0.15, 2)
            else:
                x = rng.uniform(-5, 5, 2)
            if not inside(x):
                break
        pos.append(x)
    pos = np.array(pos)
    max_speed = rng.uniform(0.5, 1.5, n)
    speed = rng.uniform(0, 1, n) * max_speed
    ang = rng.uniform(0, 2 * np.pi, n)
    vel = np.stack((speed * np.cos(ang), speed * np.sin(ang)), -1)
    pref = rng.uniform(-5, 5, (n, 2)) - pos
    norm = np.linalg.norm(pref, axis=-1, keepdims=True)
    pref = np.where(norm > 1, pref / np.maximum(norm, 1e-9), pref)
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return {"positions": f32(pos), "velocities": f32(vel), "pref_velocities": f32(pref), "radius": f32(radius),
            "max_speed": f32(max_speed), "obstacles": polys}


def padded_obstacles(scenes: list[dict], dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """The scenes' ``obstacles`` as ``[B, P, V, 2]`` polygons and their vertex mask ``[B, P, V]``."""
    P = max(1, max(len(s.get("obstacles", ())) for s in scenes))
    V = max([2] + [len(p) for s in scenes for p in s.get("obstacles", ())])
    out = torch.zeros(len(scenes), P, V, 2, dtype=dtype)
    mask = torch.zeros(len(scenes), P, V, dtype=torch.bool)
    for b, s in enumerate(scenes):
        for p, poly in enumerate(s.get("obstacles", ())):
            out[b, p, :len(poly)] = torch.as_tensor(np.asarray(poly), dtype=dtype)
            mask[b, p, :len(poly)] = True
    return out, mask


CROWD_KINDS = ("crowd", "dense", "overlap")  # random_scene kinds of equal radii: crowds of CrowdConfig's humans


def random_crowd_scene(rng: np.random.Generator, kind: str) -> dict[str, np.ndarray]:
    """A :func:`random_scene` of ``kind`` (one of :data:`CROWD_KINDS`) as humans with goals (``goals`` =
    position + preferred velocity) and a robot: ``robot_position``/``robot_velocity`` ``[2]``, placed in
    the 10 m square (``crowd``) or at a surface gap of -0.1..0.05 m from a random human (``dense``,
    ``overlap``), at a random speed below 1 m/s; float32-exact."""
    if kind not in CROWD_KINDS:
        raise ValueError(f"unknown crowd scene kind {kind!r}; expected one of {CROWD_KINDS}")
    scene = random_scene(rng, kind)
    scene["goals"] = (scene["positions"] + scene["pref_velocities"]).astype(np.float32)
    if kind == "crowd":
        robot = rng.uniform(-5, 5, 2)
    else:
        ang = rng.uniform(0, 2 * np.pi)
        robot = scene["positions"][int(rng.integers(len(scene["positions"])))] + (0.61 + rng.uniform(-0.1, 0.05)) * \
            np.array([np.cos(ang), np.sin(ang)])
    speed, heading = rng.uniform(0, 1), rng.uniform(0, 2 * np.pi)
    scene["robot_position"] = robot.astype(np.float32)
    scene["robot_velocity"] = np.array([speed * np.cos(heading), speed * np.sin(heading)], dtype=np.float32)
    return scene


def crowd_scene_state(scenes: list[dict[str, np.ndarray]]):
    """A :class:`~crowdrl.sim.state.CrowdState` of :func:`random_crowd_scene` scenes with equally many humans
    (robot heading 0, goal (0, 4), counters 0)."""
    from crowdrl.sim.state import CrowdState

    stack = lambda key: torch.as_tensor(np.stack([s[key] for s in scenes]))  # noqa: E731
    B, N = len(scenes), len(scenes[0]["positions"])
    return CrowdState(
        robot_position=stack("robot_position"), robot_velocity=stack("robot_velocity"), robot_heading=torch.zeros(B),
        robot_goal=torch.tensor([[0.0, 4.0]]).repeat(B, 1), human_position=stack("positions"),
        human_velocity=stack("velocities"), human_goal=stack("goals"),
        human_goal_steps=torch.zeros(B, N, dtype=torch.long), step_count=torch.zeros(B, dtype=torch.long),
        episode_key=torch.zeros(B, dtype=torch.long), human_mask=torch.ones(B, N, dtype=torch.bool))


def socialforce_velocities(positions: np.ndarray, velocities: np.ndarray, goals: np.ndarray,
                           preferred_speeds: np.ndarray, has_goal: np.ndarray, *, time_step: float, substeps: int,
                           tau: float, v0: float, sigma: float) -> np.ndarray:
    """One call of the ``socialforce`` package (0.2.3; a test-only install) on ``M`` pedestrians: their
    velocities ``[M, 2]`` (float64) after ``Simulator(delta_t=time_step, oversampling=substeps)`` from rest
    in acceleration, float32 as the package computes by default. A pedestrian without ``has_goal`` gets the
    package's NaN destination (it heads where it goes)."""
    import socialforce

    M = len(positions)
    destination = np.where(np.asarray(has_goal)[:, None], goals, np.nan)
    state = np.concatenate((positions, velocities, np.zeros((M, 2)), destination, np.full((M, 1), tau),
                            np.asarray(preferred_speeds).reshape(M, 1)), 1)
    sim = socialforce.Simulator(ped_ped=socialforce.potentials.PedPedPotential(v0=v0, sigma=sigma),
                                delta_t=time_step, tau=tau, oversampling=substeps)
    with torch.no_grad():
        out = sim(torch.tensor(state, dtype=torch.float32))
    return out[:, 2:4].double().numpy()


def robot_centric_states(*batch: int, n: int = 10, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Plausible robot-centric states ``(robot_rc [*batch, 9], humans_rc [*batch, n, 5])`` for
    encoder tests: positions of a few metres, speeds ~1 m/s, drawn from torch's global RNG."""
    robot = torch.randn(*batch, 9, dtype=dtype)
    robot[..., :2] = 0
    robot[..., 4] = 0.3
    robot[..., 5] = 4 * torch.rand(batch, dtype=dtype) + 0.5
    robot[..., 6] = 0
    robot[..., 7] = 1.0
    humans = torch.randn(*batch, n, 5, dtype=dtype)
    humans[..., :2] *= 3
    humans[..., 4] = 0.6
    return robot, humans


def fresh_network(run, num_actions: int = 81):
    """A fresh Q network of ``run`` modified by a strategy of its own (``make_strategy(run.exploration)``): for
    tests that load weights into it or act greedily with it, where no exploration schedule acts."""
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import make_network

    return make_network(run, num_actions, strategy=make_strategy(run.exploration))


class KilledRun(BaseException):
    """Stops a training run mid-update as SIGKILL would (a ``BaseException``: no handler of the run catches it)."""


def train_until_killed(run, folder, frame: int) -> None:
    """Train ``run`` into ``folder`` and kill it in the updates of the batch that reaches ``frame`` collected
    frames, after that batch entered the replay buffer (what an exact-resume test resumes from); fails if
    the run ends before that frame."""
    from crowdrl.training.pipeline import run_training
    from crowdrl.training.trainer import Trainer

    update = Trainer.update

    def dies_at_frame(self, frames):
        if self.counters.frames == frame:
            raise KilledRun(f"killed at frame {frame}")
        return update(self, frames)

    Trainer.update = dies_at_frame
    try:
        run_training(run, folder)
    except KilledRun:
        return
    finally:
        Trainer.update = update
    raise AssertionError(f"the run ended without an update at frame {frame}")


__all__ = ["KINDS", "OBSTACLE_KINDS", "ORCA_TOLERANCE", "SCENE_PARAMS", "KilledRun", "fresh_network", "padded_batch",
           "padded_obstacles", "random_obstacle_scene", "random_scene", "robot_centric_states", "rvo2_velocities",
           "train_until_killed"]
