"""Scenarios with static obstacles: corridor, doorway, room.

Spawns and goals clear of the obstacles with reachable goals, determinism in (stream, seed,
episode id), the humans' ORCA among obstacles, the robot's continuous collision with walls, the
open scenarios unchanged, bad inputs, the TorchRL env and the Hydra keys.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import pytest
import torch

from crowdrl.sim import rng
from crowdrl.sim.config import OBSTACLE_SCENARIOS, CrowdConfig
from crowdrl.sim.crowd import COLLISION, RUNNING, human_velocities, step
from crowdrl.sim.kinematics import action_table, decode_action
from crowdrl.sim.obstacles import (check_obstacles, path_obstacle_distance, point_obstacle_distance,
                                   process_obstacles, segment_distance)
from crowdrl.sim.scenarios import SpawnError, initial_states, new_human_goals, scenario_obstacles

ROOT = Path(__file__).resolve().parents[1]


def _states(scenario: str, ids, num_humans: int = 10, split: str = "train", seed: int = 0, **keys):
    cfg = CrowdConfig(scenario=scenario, num_humans=num_humans, **keys)
    return cfg, initial_states(cfg, rng.episode_keys(split, seed, torch.as_tensor(ids)))


# --- open scenarios: bit-identical to before obstacles ---------------------------------------------

# sha256 of 40 steps of 5 episodes (test stream, seed 7, 6 humans, seeded random unicycle actions) and
# of a 60-step CrowdNavEnv rollout with partial resets, generated with the code of main at 76b8ca1
# (before obstacles) by this file's _trajectory_digest/_env_digest
# float64 rounds an ulp apart on CPUs with and without AVX-512 (tests/test_orca_obstacles.py), and 40 steps
# carry it into the hash: the second float64 digest of each scenario is the same code's on an Intel Xeon
# with AVX-512 (checked at 76b8ca1's successor 934fbbd); the first, the AMD EPYC's that recorded them
OPEN_DIGESTS = {
    ("circle", "float32"): {"53689000adca21d4351e02b12fea08b5fbf7b63f75a66bb4a2df190d5372e64e"},
    ("circle", "float64"): {"5fca35d5eb88dd71d9357b9eecd20a4be596e5a8183cbeccc9fa1a9cc681fa05",
                            "3a2ed6242d14ace0863afe57e13615610502b88e4ec0b15e128c1b8aff3fc494"},
    ("square", "float32"): {"ad7474634190dd570090d514a87a61d435c4c40df9771e11a1b35ba13413e22e"},
    ("square", "float64"): {"6935963cf78981d0d3be6647bc15b0fc9dd6732b3b35d7b785e9d79919d31565",
                            "567c73c7297e58e5e006378d55fa2338c7c9c32c8f4b157b04279c4f685a095f"},
}
OPEN_ENV_DIGESTS = {
    "circle": ("270629f287ea13b02813010476c69712b14b636388998901072fa8ceb6098c6a", 5),
    "square": ("3cbab473c59a3f25e2f0fa38af2ac3c67ff11720df0366e4355a00ba150dea0d", 5),
}


def _trajectory_digest(scenario: str, dtype: torch.dtype, steps: int = 40) -> str:
    cfg = CrowdConfig(scenario=scenario, num_humans=6)
    state = initial_states(cfg, rng.episode_keys("test", 7, torch.arange(5)), dtype=dtype)
    table = action_table(cfg.robot_v_pref, dtype=dtype)
    g = torch.Generator().manual_seed(3)
    h = hashlib.sha256()
    for _ in range(steps):
        a = torch.randint(0, table.shape[0], (5,), generator=g)
        v, hd = decode_action("unicycle", a, state.robot_heading, table, cfg.robot_v_pref)
        state, res = step(cfg, state, v, hd)
        for t in (state.robot_position, state.human_position, state.human_velocity, state.human_goal, res.reward,
                  res.event):
            h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()


def _env_digest(scenario: str, steps: int = 60) -> tuple[str, int]:
    from crowdrl.envs.crowd_nav import CrowdNavEnv

    env = CrowdNavEnv(scenario, num_envs=4, num_humans=5, seed=2, split="val")
    actions = iter(torch.randint(0, 81, (steps, 4), generator=torch.Generator().manual_seed(5)))
    td = env.rollout(steps, policy=lambda td: td.set("action", next(actions)), break_when_any_done=False)
    h = hashlib.sha256()
    for k in ("robot", "humans", "episode_id", ("next", "reward"), ("next", "done"), ("next", "robot")):
        h.update(td.get(k).contiguous().numpy().tobytes())
    return h.hexdigest(), int(td["next", "done"].sum())


@pytest.mark.parametrize("scenario", ["circle", "square"])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_open_scenario_trajectories_are_unchanged(scenario, dtype):
    assert _trajectory_digest(scenario, getattr(torch, dtype)) in OPEN_DIGESTS[scenario, dtype]


@pytest.mark.parametrize("scenario", ["circle", "square"])
def test_open_scenario_env_rollouts_are_unchanged(scenario):
    assert _env_digest(scenario) == OPEN_ENV_DIGESTS[scenario]


def test_open_scenarios_have_no_obstacles():
    _, state = _states("square", [0, 1, 2])
    assert state.obstacles.shape == (3, 0, 2, 2) and state.obstacle_mask.shape == (3, 0, 2)
    assert not state.has_obstacles


# --- scenario geometry -------------------------------------------------------------------------------

@pytest.mark.parametrize("scenario", OBSTACLE_SCENARIOS)
def test_scenarios_are_pure_functions_of_stream_seed_and_episode(scenario):
    _, a = _states(scenario, range(12))
    _, b = _states(scenario, [7, 3, 11])  # other batch, other order
    for name in ("human_position", "human_goal", "obstacles", "obstacle_mask", "human_mask"):
        assert torch.equal(getattr(a, name)[[7, 3, 11]], getattr(b, name)), name
    _, c = _states(scenario, range(12), seed=1)
    _, d = _states(scenario, range(12), split="val")
    assert not torch.equal(a.human_position, c.human_position)
    assert not torch.equal(a.human_position, d.human_position)


def test_geometry_defaults():
    cfg = CrowdConfig(scenario="corridor")
    obs, mask = scenario_obstacles(cfg, torch.arange(2))
    assert obs.shape == (2, 2, 2, 2) and bool(mask.all())
    assert sorted(obs[0, :, :, 0].abs().flatten().tolist()) == [2.0] * 4  # walls at x = -/+ 2
    assert obs[0, :, :, 1].abs().max() == 5.0  # 10 m long
    obs, _ = scenario_obstacles(CrowdConfig(scenario="doorway", doorway_gap=1.6, num_humans=4), torch.arange(2))
    assert torch.equal(obs[0], torch.tensor([[[-5.0, 0.0], [-0.8, 0.0]], [[0.8, 0.0], [5.0, 0.0]]]))
    obs, _ = scenario_obstacles(CrowdConfig(scenario="room", room_pillars=3), rng.episode_keys("train", 0,
                                                                                                 torch.arange(64)))
    assert obs.shape == (64, 3, 4, 2)
    check_obstacles(obs)  # counter-clockwise convex polygons
    side = torch.linalg.vector_norm(obs.roll(-1, 2) - obs, dim=-1)
    assert side.min() >= 0.5 - 1e-5 and side.max() <= 1.5 + 1e-5
    assert len({tuple(o.flatten().tolist()) for o in obs}) == 64  # random per episode


@pytest.mark.parametrize("scenario", OBSTACLE_SCENARIOS)
def test_spawns_goals_and_paths_keep_clear_of_obstacles(scenario):
    cfg, s = _states(scenario, range(200))
    clear = cfg.human_radius + cfg.obstacle_clearance_margin
    for points in (s.human_position, s.human_goal):
        assert bool((point_obstacle_distance(points, s.obstacles, s.obstacle_mask) >= clear - 1e-6).all())
    assert bool((path_obstacle_distance(s.human_position, s.human_goal, s.obstacles, s.obstacle_mask)
                 >= clear - 1e-6).all())
    robot = torch.stack((s.robot_position, s.robot_goal), 1)
    assert bool((point_obstacle_distance(robot, s.obstacles, s.obstacle_mask)
                 >= cfg.robot_radius + cfg.obstacle_clearance_margin - 1e-6).all())
    # agents keep the spawn clearance among themselves, as in the open scenarios
    pos = torch.cat((s.robot_position.unsqueeze(1), s.human_position), 1)
    d = torch.cdist(pos, pos) + torch.eye(pos.shape[1]) * 100
    assert d.min() >= cfg.human_radius + cfg.robot_radius + cfg.discomfort_dist - 1e-5


def test_corridor_humans_walk_both_ways_inside_the_corridor():
    cfg, s = _states("corridor", range(100))
    direction = torch.sign(s.human_goal[..., 1] - s.human_position[..., 1])
    assert bool((direction != 0).all())
    assert bool(((direction == 1).sum(-1) == 5).all()) and bool(((direction == -1).sum(-1) == 5).all())
    inner = cfg.corridor_width / 2 - cfg.human_radius
    assert s.human_position[..., 0].abs().max() <= inner and s.human_goal[..., 0].abs().max() <= inner


def test_doorway_humans_start_and_end_on_opposite_sides_through_the_gap():
    cfg, s = _states("doorway", range(100))
    assert bool((s.human_position[..., 1] * s.human_goal[..., 1] < 0).all())
    # the straight line crosses the wall's line inside the gap, with room for a human
    p, g = s.human_position, s.human_goal
    t = p[..., 1] / (p[..., 1] - g[..., 1])
    x = p[..., 0] + t * (g[..., 0] - p[..., 0])
    assert x.abs().max() < cfg.doorway_gap / 2 - cfg.human_radius


def _run_humans(cfg, state, steps):
    """Humans only (the robot stands still far away): the fraction that ever came within their radius of
    their first goal."""
    state = state.replace(robot_position=torch.full_like(state.robot_position, 50.0),
                          robot_goal=torch.full_like(state.robot_goal, 60.0))
    goal0 = state.human_goal.clone()
    reached = torch.zeros(state.human_goal.shape[:2], dtype=torch.bool)
    edges = process_obstacles(state.obstacles, state.obstacle_mask)
    for _ in range(steps):
        v, _ = human_velocities(cfg, state, edges)
        pos = state.human_position + v * cfg.time_step
        state = state.replace(human_position=pos, human_velocity=v)
        reached |= torch.linalg.vector_norm(pos - goal0, dim=-1) < cfg.human_radius
        # never through a wall: every move is clear of the edges by (nearly) a radius
    return reached, state


@pytest.mark.parametrize("scenario", OBSTACLE_SCENARIOS)
def test_humans_reach_their_goals_among_the_obstacles(scenario):
    cfg, s = _states(scenario, range(16))
    reached, end = _run_humans(cfg, s, steps=int(30 / cfg.time_step))
    assert reached.float().mean() >= 0.8, reached.float().mean()
    # no human ended up inside a wall or beyond it: within ORCA's tolerance of its radius
    d = point_obstacle_distance(end.human_position, end.obstacles, end.obstacle_mask)
    assert d.min() > cfg.human_radius - 0.05
    if scenario == "doorway":  # they passed the gap: on the other side from where they started
        crossed = (end.human_position[..., 1] * s.human_position[..., 1] < 0)
        assert crossed.float().mean() >= 0.8


@pytest.mark.parametrize("scenario", OBSTACLE_SCENARIOS)
def test_new_goals_of_non_stop_humans_are_reachable(scenario):
    cfg, s = _states(scenario, range(32))
    s = s.replace(human_position=s.human_goal.clone(), step_count=torch.full_like(s.step_count, 5))
    goals = new_human_goals(cfg, s, torch.ones_like(s.human_mask))
    clear = cfg.human_radius + cfg.obstacle_clearance_margin
    moved = (goals != s.human_goal).any(-1)
    assert moved.float().mean() > 0.9
    assert bool((path_obstacle_distance(s.human_position, goals, s.obstacles, s.obstacle_mask)[moved]
                 >= clear - 1e-6).all())
    if scenario in ("corridor", "doorway"):  # to the other end / side
        assert bool((goals[..., 1] * s.human_position[..., 1] < 0)[moved].all())


# --- the robot and obstacles ------------------------------------------------------------------------

def _wall_state(cfg, robot_y: float, dtype=torch.float32):
    """One corridor episode with its robot at (0, robot_y), heading +x, its humans far away."""
    s = initial_states(cfg, rng.episode_keys("train", 0, torch.arange(1)), dtype=dtype)
    far = torch.full_like(s.human_position, 40.0) + torch.arange(s.num_humans, dtype=dtype).view(1, -1, 1) * 3
    return s.replace(robot_position=torch.tensor([[0.0, robot_y]], dtype=dtype), human_position=far,
                     human_goal=far.clone(), robot_goal=torch.tensor([[0.0, 4.0]], dtype=dtype))


def test_robot_tunnelling_through_a_wall_is_a_collision():
    # a thin wall across x = 2 (the corridor's right wall); the robot at x = 1.6 (0.1 m clear of it) moves
    # at 10 m/s for 0.25 s: it ends at x = 4.1, past the wall, yet collides within the step
    cfg = CrowdConfig(scenario="corridor", num_humans=2)
    s = _wall_state(cfg, 0.0).replace(robot_position=torch.tensor([[1.6, 0.0]]))
    nxt, res = step(cfg, s, torch.tensor([[10.0, 0.0]]))
    assert nxt.robot_position[0, 0] > 2.0 + cfg.robot_radius  # ended beyond the wall
    assert int(res.event) == COLLISION and bool(res.terminated) and bool(res.obstacle_collision)
    # the reward of a human collision: progress (here negative) plus the collision penalty, no goal bonus
    progress = cfg.progress_factor * (math.hypot(1.6, 4.0) - math.hypot(4.1, 4.0))
    assert math.isclose(float(res.reward), progress + cfg.collision_penalty, abs_tol=1e-5)


def test_robot_at_full_speed_into_a_wall_collides_in_the_step_it_touches_it():
    cfg = CrowdConfig(scenario="corridor", num_humans=2)
    s = _wall_state(cfg, 0.0)
    events = []
    for _ in range(10):
        before = s.robot_position[0, 0].item()
        s, res = step(cfg, s, torch.tensor([[cfg.robot_v_pref, 0.0]]))
        events.append(int(res.event))
        if res.terminated:
            break
    # from x = 0 at 1 m/s the disc (radius 0.3) reaches the wall at x = 2 after 1.7 m: during step 7
    assert events == [RUNNING] * 6 + [COLLISION]
    assert before + cfg.robot_radius < 2.0 <= s.robot_position[0, 0].item() + cfg.robot_radius


def test_a_robot_moving_along_a_wall_does_not_collide():
    cfg = CrowdConfig(scenario="corridor", num_humans=2)
    s = _wall_state(cfg, -3.0).replace(robot_position=torch.tensor([[2.0 - cfg.robot_radius - 0.01, -3.0]]))
    for _ in range(8):
        s, res = step(cfg, s, torch.tensor([[0.0, 1.0]]))
        assert int(res.event) == RUNNING and not bool(res.obstacle_collision)


def test_segment_distance():
    p0, p1 = torch.tensor([0.0, 0.0]), torch.tensor([2.0, 0.0])
    assert segment_distance(p0, p1, torch.tensor([1.0, -1.0]), torch.tensor([1.0, 1.0])) == 0  # crossing
    assert math.isclose(float(segment_distance(p0, p1, torch.tensor([3.0, -1.0]), torch.tensor([3.0, 1.0]))), 1.0)
    assert math.isclose(float(segment_distance(p0, p0, torch.tensor([0.0, 1.0]), torch.tensor([5.0, 1.0]))), 1.0)


# --- bad inputs ---------------------------------------------------------------------------------------

def test_bad_obstacle_polygons_are_refused_by_the_step():
    cfg = CrowdConfig(scenario="room", num_humans=3)
    _, s = _states("room", [0, 1], num_humans=3)
    v = torch.zeros(2, 2)
    cw = s.obstacles.flip(2)  # clockwise
    with pytest.raises(ValueError, match=r"polygon \(b=0, p=0\) is clockwise.*counter-clockwise"):
        step(cfg, s.replace(obstacles=cw), v)
    nan = s.obstacles.clone()
    nan[1, 2, 1, 0] = float("nan")
    with pytest.raises(ValueError, match=r"polygon \(b=1, p=2\) has a NaN"):
        step(cfg, s.replace(obstacles=nan), v)
    one = s.obstacle_mask.clone()
    one[0, 1, 1:] = False
    with pytest.raises(ValueError, match=r"polygon \(b=0, p=1\) has 1 vertex; a polygon needs at least 2"):
        step(cfg, s.replace(obstacle_mask=one), v)


def test_obstacles_on_another_device_are_refused():
    cfg, s = _states("doorway", [0], num_humans=2)
    meta = s.replace(obstacles=s.obstacles.to("meta"))
    with pytest.raises(ValueError, match="state.obstacles is on meta.*agents are on cpu"):
        step(cfg, meta, torch.zeros(1, 2))


@pytest.mark.parametrize("keys, word", [
    ({"scenario": "corridor", "corridor_width": 0.9}, "corridor_width"),
    ({"scenario": "corridor", "corridor_length": 6.0}, "corridor_length"),
    ({"scenario": "doorway", "doorway_gap": 0.8}, "doorway_gap"),
    ({"scenario": "doorway", "doorway_width": 2.0}, "doorway_width"),
    ({"scenario": "room", "room_pillars": -1}, "room_pillars"),
    ({"scenario": "room", "room_pillar_min": 2.0, "room_pillar_max": 1.0}, "room_pillar_min"),
    ({"scenario": "room", "room_pillar_max": float("nan")}, "room_pillar_max"),
    ({"scenario": "doorway", "orca_time_horizon_obst": 0.0}, "orca_time_horizon_obst"),
])
def test_bad_geometry_keys_are_named(keys, word):
    with pytest.raises(ValueError, match=word):
        CrowdConfig(**keys)


# the documented maxima (docs/mdp.md) at the default geometry
SPAWN_MAXIMA = {"corridor": 14, "doorway": 14, "room": 18}


@pytest.mark.parametrize("scenario", OBSTACLE_SCENARIOS)
def test_the_documented_maximum_crowd_spawns_in_thousands_of_episodes_and_one_more_is_refused(scenario):
    """Issue #52 D1: a crowd the geometry cannot spawn is refused at construction naming num_humans (every
    entry point builds a CrowdConfig), and the largest one accepted spawns every episode (8000 per scenario;
    corridor 17 first failed at episode 865, room 24 at 5002)."""
    top = SPAWN_MAXIMA[scenario]
    cfg = CrowdConfig(scenario=scenario, num_humans=top)
    assert cfg.max_spawnable_humans == top
    for start in range(0, 8000, 1000):
        s = initial_states(cfg, rng.episode_keys("train", 0, torch.arange(start, start + 1000)))
        assert bool(s.human_mask.all())
    with pytest.raises(ValueError, match=rf"^num_humans \({top + 1}\) cannot be spawned reliably in scenario {scenario}"):
        CrowdConfig(scenario=scenario, num_humans=top + 1)


@pytest.mark.parametrize("keys, word", [
    ({"scenario": "room", "room_pillars": 1000}, "^room_pillars"),
    ({"scenario": "room", "room_pillar_min": 5.0, "room_pillar_max": 20.0}, "^room_pillars"),
    ({"scenario": "room", "num_humans": 64}, "^num_humans"),
    ({"scenario": "corridor", "num_humans": 19}, "^num_humans"),
    ({"scenario": "corridor", "num_humans": 17}, "^num_humans"),
    ({"scenario": "doorway", "num_humans": 64}, "^num_humans"),
    ({"scenario": "doorway", "doorway_gap": 1.5}, "^num_humans"),  # 10 humans: 0.8 % of the episodes failed
])
def test_the_crowds_of_issue_52_are_refused_at_construction(keys, word):
    with pytest.raises(ValueError, match=word):
        CrowdConfig(**keys)


@pytest.mark.parametrize("keys, words, rounds", [
    ({"scenario": "room", "room_pillars": 5, "num_humans": 2}, ["scenario room", "room_pillars=5", "room_pillar_max=1.5",
                                                                "pillar"],
     "PILLAR_ROUNDS"),
    ({"scenario": "corridor", "num_humans": 14}, ["scenario corridor", "corridor_width=4.0", "num_humans=14",
                                                  "rejection rounds"], "SPAWN_ROUNDS"),
])
def test_an_unclearable_spawn_raises_naming_the_scenario_and_its_keys(monkeypatch, keys, words, rounds):
    """The safety net behind the bound: with a single rejection round a draw does fail, naming its keys."""
    from crowdrl.sim import scenarios

    monkeypatch.setattr(scenarios, rounds, 1)
    cfg = CrowdConfig(**keys)
    with pytest.raises(SpawnError) as err:
        initial_states(cfg, rng.episode_keys("train", 0, torch.arange(64)))
    for word in words:
        assert word in str(err.value)


# --- the TorchRL env ----------------------------------------------------------------------------------

def test_doorway_env_random_rollout_with_batched_resets():
    from torchrl.envs.utils import check_env_specs

    from crowdrl.envs.crowd_nav import CrowdNavEnv

    env = CrowdNavEnv("doorway", num_envs=3, num_humans=4, seed=1)
    check_env_specs(env)
    env = CrowdNavEnv("doorway", num_envs=4, num_humans=4, seed=1)
    td = env.reset()
    before = env.state.obstacles.clone()
    g = torch.Generator().manual_seed(0)
    resets = 0
    for _ in range(30):
        td = env.step(td.set("action", torch.randint(0, 81, (4,), generator=g)))["next"]
        done = td["done"].squeeze(-1)
        if done.any():
            resets += int(done.sum())
            td = env.reset(td.set("_reset", done.unsqueeze(-1)))
    assert resets > 0 and torch.equal(env.state.obstacles, before)  # the doorway is the same in every episode


def test_room_env_partial_reset_replaces_only_the_reset_episodes_obstacles():
    from tensordict import TensorDict

    from crowdrl.envs.crowd_nav import CrowdNavEnv
    from crowdrl.sim.kinematics import decode_action as decode

    env = CrowdNavEnv("room", num_envs=4, num_humans=3, seed=0)
    td = env.reset()
    first = env.state.obstacles.clone()
    td = env.step(td.set("action", torch.zeros(4, dtype=torch.int64)))["next"]
    reset = torch.tensor([False, True, False, True])
    env.reset(TensorDict({"_reset": reset.unsqueeze(-1)}, batch_size=[4]))
    now = env.state.obstacles
    assert torch.equal(now[~reset], first[~reset]) and not torch.equal(now[reset], first[reset])
    keys = rng.episode_keys("train", 0, torch.tensor([4, 5]))  # the stream's next episodes
    assert torch.equal(now[reset], initial_states(env.config, keys).obstacles)
    # the env's cached, merged obstacle edges give the same step as processing the polygons afresh
    state = env.state
    a = torch.randint(0, 81, (4,), generator=torch.Generator().manual_seed(1))
    v, h = decode("unicycle", a, state.robot_heading, env._actions, 1.0)
    expected, _ = step(env.config, state, v, h)
    env.step(TensorDict({"action": a}, batch_size=[4]))
    assert torch.equal(env.state.human_position, expected.human_position)
    assert torch.equal(env.state.human_velocity, expected.human_velocity)


def test_env_snapshot_restore_keeps_the_obstacles():
    from crowdrl.envs.crowd_nav import CrowdNavEnv

    env = CrowdNavEnv("room", num_envs=2, num_humans=3, seed=0)
    env.reset()
    saved = env.snapshot()
    env2 = CrowdNavEnv("room", num_envs=2, num_humans=3, seed=0)
    env2.restore(saved)
    env2.reset()
    assert torch.equal(env2.state.obstacles, env.state.obstacles)


# --- Hydra ---------------------------------------------------------------------------------------------

def _compose(overrides):
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from crowdrl.training.config import RunConfig

    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()
    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize("scenario", OBSTACLE_SCENARIOS)
def test_hydra_env_groups_set_the_geometry(scenario):
    from crowdrl.training.validation import validate
    from crowdrl.training.config import crowd_config

    key = {"corridor": "corridor_width=3.0", "doorway": "doorway_gap=1.8", "room": "room_pillars=2"}[scenario]
    run = validate(_compose([f"env={scenario}", f"env.{key}", "logger=csv"]), resources=False)
    cfg = crowd_config(run)
    name, value = key.split("=")
    assert cfg.scenario == scenario and getattr(cfg, name) == type(getattr(cfg, name))(float(value))


def test_hydra_bad_geometry_is_named():
    from crowdrl.training.config import ConfigError
    from crowdrl.training.validation import validate

    with pytest.raises(ConfigError, match="env.doorway_gap"):
        validate(_compose(["env=doorway", "env.doorway_gap=0.5", "logger=csv"]), resources=False)


# --- rendering ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("scenario, artists", [("doorway", 2), ("room", 4)])
def test_recorded_trajectories_draw_the_obstacles(tmp_path, scenario, artists):
    from crowdrl.envs.crowd_nav import CrowdNavEnv
    from crowdrl.evaluation.rollout import evaluate
    from crowdrl.viz.trajectory import OBSTACLE_GID, animate_trajectory, plot_trajectory

    env = CrowdNavEnv(scenario, num_envs=2, num_humans=3, split="test")
    straight = lambda td: td.set("action", torch.zeros(2, dtype=torch.int64))  # noqa: E731
    _, traj = evaluate(env, straight, num_episodes=2, record_episode=1)
    expected = initial_states(env.config, rng.episode_keys("test", 0, torch.tensor([1]))).obstacles[0]
    assert len(traj.obstacles) == artists
    assert all(torch.equal(torch.from_numpy(p).float(), e) for p, e in zip(traj.obstacles, expected))
    fig = plot_trajectory(traj, tmp_path / "t.png")
    ax = fig.axes[0]
    drawn = [a for a in (*ax.lines, *ax.patches) if a.get_gid() == OBSTACLE_GID]
    assert len(drawn) == artists and (tmp_path / "t.png").stat().st_size > 0
    lo, hi = ax.get_xlim()
    assert lo <= expected[..., 0].min() and hi >= expected[..., 0].max()  # the limits include them
    short = type(traj)(**{**traj.__dict__, "robot_positions": traj.robot_positions[:3],
                          "human_positions": traj.human_positions[:3], "human_goals": traj.human_goals[:3],
                          "robot_headings": traj.robot_headings[:3]})
    animate_trajectory(short, tmp_path / "t.gif")
    assert (tmp_path / "t.gif").stat().st_size > 0


def test_trajectory_refuses_bad_obstacles():
    from crowdrl.evaluation.trajectory import Trajectory

    base = dict(robot_positions=[[0.0, 0.0]], robot_goal=[0.0, 1.0], robot_radius=0.3,
                human_positions=[[[1.0, 1.0]]], human_goals=[[[2.0, 2.0]]], human_radius=0.3, time_step=0.25)
    with pytest.raises(ValueError, match=r"obstacles\[0\]: expected shape \[n >= 2, 2\]"):
        Trajectory(**base, obstacles=([[0.0, 0.0]],))
    with pytest.raises(ValueError, match=r"obstacles\[1\]: contains non-finite"):
        Trajectory(**base, obstacles=([[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.0], [float("nan"), 0.0]]))


# --- the ORCA robot baseline among obstacles --------------------------------------------------------

def test_orca_robot_baseline_sees_the_obstacles_as_rvo2_does():
    """A robot 1 m below a wall, its goal straight through it: with the wall visible its obstacle
    ORCA line caps the speed towards the wall at (distance - radius) / time_horizon_obst, as RVO2's
    does; blind to it (``use_obstacles=False``) it heads straight on at full speed. Through the
    policy's TensorDict face, it reads the env's ``obstacle_polygons`` and their mask."""
    from tensordict import TensorDict

    from crowdrl.envs import CrowdNavEnv
    from crowdrl.policies.orca_baseline import OrcaRobotPolicy

    cfg = CrowdConfig(scenario="doorway", robot_kinematics="holonomic")
    robot = torch.tensor([[-3.0, -1.0, 0.0, 0.0, 0.3, -3.0, 4.0, 1.0, 0.0]])
    humans = torch.tensor([[[4.0, 3.0, 0.0, 0.0, 0.3]]])  # one human far away
    wall = torch.tensor([[[[-5.0, 0.0], [5.0, 0.0]]]])  # [B, P, V, 2]: one wall segment on y = 0
    td = TensorDict({"robot": robot, "humans": humans, "humans_mask": torch.ones(1, 1, dtype=torch.bool),
                     "obstacle_polygons": wall, "obstacle_polygons_mask": torch.ones(1, 1, 2, dtype=torch.bool)},
                    batch_size=[1])
    seen = OrcaRobotPolicy(cfg)(td.clone())["action"][0]
    blind = OrcaRobotPolicy(cfg, use_obstacles=False)(td.clone())["action"][0]
    cap = (1.0 - (0.3 + 0.01)) / cfg.orca_time_horizon_obst
    assert 0 < float(seen[1]) <= cap + 1e-6, seen
    assert torch.allclose(blind, torch.tensor([0.0, 1.0]), atol=1e-6), blind

    # in the env the baseline reads the map it observes; seeing the walls, it hits them less
    env = CrowdNavEnv("doorway", num_envs=16, robot_kinematics="holonomic", split="val", seed=0)
    collisions = {}
    for use in (True, False):
        rollout = env.rollout(cfg.max_steps, OrcaRobotPolicy(env.config, use_obstacles=use),
                              break_when_any_done=False, tensordict=env.reset())
        collisions[use] = int((rollout["next", "event"] == COLLISION).any(1).sum())
    assert collisions[True] < collisions[False], collisions
