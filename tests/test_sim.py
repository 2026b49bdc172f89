"""The crowd MDP (SPEC §1): actions, kinematics, collision, reward, events, scenarios, seeds."""

from __future__ import annotations

import math

import pytest
import torch

from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import COLLISION, RUNNING, SUCCESS, TIMEOUT, closest_surface_distance, observe, step
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, check_actions, unicycle_step
from crowdrl.sim.scenarios import SpawnError, initial_states
from crowdrl.sim.state import CrowdState


def make_state(robot_pos, robot_goal, human_pos, human_vel=None, human_goal=None, heading=math.pi / 2) -> CrowdState:
    """A single-episode state placed by hand."""
    hp = torch.tensor(human_pos, dtype=torch.float32).view(1, -1, 2)
    N = hp.shape[1]
    return CrowdState(
        robot_position=torch.tensor([robot_pos], dtype=torch.float32),
        robot_velocity=torch.zeros(1, 2),
        robot_heading=torch.tensor([heading]),
        robot_goal=torch.tensor([robot_goal], dtype=torch.float32),
        human_position=hp,
        human_velocity=torch.zeros(1, N, 2) if human_vel is None else torch.tensor(human_vel, dtype=torch.float32).view(1, N, 2),
        human_goal=hp.clone() if human_goal is None else torch.tensor(human_goal, dtype=torch.float32).view(1, N, 2),
        human_goal_steps=torch.zeros(1, N, dtype=torch.int64),
        step_count=torch.zeros(1, dtype=torch.int64),
        episode_key=torch.zeros(1, dtype=torch.int64),
        human_mask=torch.ones(1, N, dtype=torch.bool),
    )


# --------------------------------------------------------------------------- actions
def test_action_table_matches_spec():
    table = action_table()
    assert table.shape == (NUM_ACTIONS, 2) == (81, 2)
    assert table[0].tolist() == [0.0, 0.0]
    speeds = sorted(set(round(v, 6) for v in table[1:, 0].tolist()))
    assert speeds == [0.2, 0.4, 0.6, 0.8, 1.0]
    rots = table[1::5, 1]
    torch.testing.assert_close(rots, torch.linspace(-math.pi / 6, math.pi / 6, 16))
    assert not bool((table[1:, 1].abs() < 1e-6).any()), "no zero rotation"
    # index = 1 + 5 * i_rot + j_speed
    i_rot, j_speed = 7, 3
    assert table[1 + 5 * i_rot + j_speed, 0].item() == pytest.approx(0.8)
    assert table[1 + 5 * i_rot + j_speed, 1].item() == pytest.approx(-math.pi / 6 + i_rot * math.pi / 3 / 15)


def test_unicycle_rotates_then_moves():
    heading, vel = unicycle_step(torch.tensor([0.0]), torch.tensor([1.0]), torch.tensor([math.pi / 6]))
    assert heading.item() == pytest.approx(math.pi / 6)
    torch.testing.assert_close(vel, torch.tensor([[math.cos(math.pi / 6), math.sin(math.pi / 6)]]))


@pytest.mark.parametrize("bad", [torch.tensor([81]), torch.tensor([-1]), torch.tensor([0.5]), torch.tensor([[1, 2]])])
def test_out_of_range_or_malformed_actions_raise(bad):
    with pytest.raises((ValueError, TypeError), match="action"):
        check_actions(bad, 1)


# --------------------------------------------------------------------------- collision
def test_continuous_collision_catches_a_pass_through():
    # start 2 m ahead, move 4 m backwards relative: both endpoints are clear, the middle is not
    d = closest_surface_distance(torch.tensor([[2.0, 0.0]]), torch.tensor([[-16.0, 0.0]]), 0.25, 0.6)
    assert d.item() == pytest.approx(-0.6)
    d = closest_surface_distance(torch.tensor([[2.0, 1.0]]), torch.tensor([[-16.0, 0.0]]), 0.25, 0.6)
    assert d.item() == pytest.approx(0.4)
    d = closest_surface_distance(torch.tensor([[2.0, 0.0]]), torch.zeros(1, 2), 0.25, 0.6)
    assert d.item() == pytest.approx(1.4)


# --------------------------------------------------------------------------- reward and events
def test_progress_reward_without_humans_nearby():
    cfg = CrowdConfig(num_humans=1)
    s = make_state((0.0, -4.0), (0.0, 4.0), [(8.0, 8.0)])
    s2, res = step(cfg, s, torch.tensor([[0.0, 1.0]]))
    assert res.reward.item() == pytest.approx(0.2 * 0.25)
    assert res.event.item() == RUNNING and not res.terminated.item() and not res.truncated.item()
    torch.testing.assert_close(s2.robot_position, torch.tensor([[0.0, -3.75]]))


def test_goal_reward_and_termination():
    cfg = CrowdConfig(num_humans=1)
    s = make_state((0.0, 3.5), (0.0, 4.0), [(8.0, 8.0)])
    _, res = step(cfg, s, torch.tensor([[0.0, 1.0]]))  # ends 0.25 m from the goal (< 0.3)
    assert res.event.item() == SUCCESS and res.terminated.item()
    assert res.reward.item() == pytest.approx(0.25 + 0.2 * 0.25)


def test_collision_penalty_includes_discomfort_term():
    cfg = CrowdConfig(num_humans=1)
    s = make_state((0.0, 0.0), (0.0, 4.0), [(0.0, 0.7)], human_goal=[(0.0, 0.7)])
    _, res = step(cfg, s, torch.tensor([[0.0, 1.0]]))  # closes 0.1 m -> 0.5 m apart: overlap
    surface = 0.7 - 0.25 - 0.6  # -0.15
    assert res.event.item() == COLLISION and res.terminated.item()
    assert res.min_separation.item() == pytest.approx(surface, abs=1e-6)
    expected = -0.25 + 0.2 * 0.25 + (surface - 0.2)
    assert res.reward.item() == pytest.approx(expected, abs=1e-6)
    assert res.discomfort_count.item() == 1


def test_discomfort_penalty_sums_over_humans():
    cfg = CrowdConfig(num_humans=2)
    # two static humans 0.75 and 0.7 m from a robot standing still: surface 0.15 and 0.1
    s = make_state((0.0, 0.0), (0.0, 4.0), [(0.75, 0.0), (-0.7, 0.0)])
    _, res = step(cfg, s, torch.zeros(1, 2), torch.tensor([math.pi / 2]))
    assert res.reward.item() == pytest.approx((0.15 - 0.2) + (0.1 - 0.2), abs=1e-5)
    assert res.discomfort_count.item() == 2 and res.event.item() == RUNNING


def test_collision_has_priority_over_goal():
    cfg = CrowdConfig(num_humans=1)
    s = make_state((0.0, 3.5), (0.0, 4.0), [(0.0, 4.3)], human_goal=[(0.0, 4.3)])
    _, res = step(cfg, s, torch.tensor([[0.0, 1.0]]))
    assert res.event.item() == COLLISION


def test_timeout_is_a_truncation_at_117_steps():
    cfg = CrowdConfig(num_humans=1)
    assert cfg.max_steps == 117
    s = make_state((0.0, -4.0), (0.0, 4.0), [(8.0, 8.0)])
    for t in range(cfg.max_steps):
        s, res = step(cfg, s, torch.zeros(1, 2), torch.tensor([math.pi / 2]))
        if t < cfg.max_steps - 1:
            assert not res.truncated.item()
    assert res.truncated.item() and not res.terminated.item() and res.event.item() == TIMEOUT


def test_non_stop_human_gets_a_new_goal_after_two_steps_near_it():
    cfg = CrowdConfig(num_humans=1)
    s = make_state((0.0, -4.0), (0.0, 4.0), [(3.0, 3.0)], human_goal=[(3.0, 3.1)])
    s, _ = step(cfg, s, torch.zeros(1, 2), torch.tensor([math.pi / 2]))
    assert s.human_goal_steps.item() == 1
    torch.testing.assert_close(s.human_goal, torch.tensor([[[3.0, 3.1]]]))
    s, _ = step(cfg, s, torch.zeros(1, 2), torch.tensor([math.pi / 2]))
    assert s.human_goal_steps.item() == 0
    assert torch.all(s.human_velocity == 0)
    new_goal = s.human_goal[0, 0]
    assert (new_goal - torch.tensor([3.0, 3.1])).norm() > 0.5
    assert abs(new_goal.norm().item() - 4.0) <= 0.75  # a fresh circle goal


def test_humans_move_by_orca_and_robot_is_invisible_to_them():
    cfg = CrowdConfig(num_humans=1)
    # human heading straight through the robot's position: ORCA ignores the robot
    s = make_state((0.0, 0.0), (0.0, 4.0), [(-2.0, 0.0)], human_goal=[(4.0, 0.0)])
    s, _ = step(cfg, s, torch.zeros(1, 2), torch.tensor([math.pi / 2]))
    torch.testing.assert_close(s.human_velocity, torch.tensor([[[1.0, 0.0]]]))
    torch.testing.assert_close(s.human_position, torch.tensor([[[-1.75, 0.0]]]))


def test_observation_layout():
    cfg = CrowdConfig(num_humans=2)
    s = make_state((1.0, -2.0), (0.0, 4.0), [(2.0, 2.0), (-1.0, 0.5)], human_vel=[(0.1, 0.2), (0.3, 0.4)])
    robot, humans = observe(cfg, s)
    assert robot.shape == (1, 9) and humans.shape == (1, 2, 5)
    assert robot[0].tolist() == pytest.approx([1.0, -2.0, 0.0, 0.0, 0.3, 0.0, 4.0, 1.0, math.pi / 2])
    assert humans[0, 1].tolist() == pytest.approx([-1.0, 0.5, 0.3, 0.4, 0.3])


# --------------------------------------------------------------------------- scenarios and seeds
@pytest.mark.parametrize("scenario", ["circle", "square"])
def test_spawn_clearance_and_layout(scenario):
    cfg = CrowdConfig(scenario=scenario, num_humans=10)
    s = initial_states(cfg, rng.episode_keys("train", 5, torch.arange(200)))
    pos = torch.cat((s.robot_position.unsqueeze(1), s.human_position), 1)
    goals = torch.cat((s.robot_goal.unsqueeze(1), s.human_goal), 1)
    d = torch.cdist(pos, pos) + torch.eye(11) * 99
    assert d.min() >= 0.8 - 1e-5
    dg = torch.cdist(goals, goals) + torch.eye(11) * 99
    assert dg.min() >= 0.8 - 1e-5
    assert torch.all(s.human_velocity == 0) and torch.all(s.robot_velocity == 0)
    torch.testing.assert_close(s.robot_position[0], torch.tensor([0.0, -4.0]))
    if scenario == "circle":
        circle = s.human_position[:, :5]
        torch.testing.assert_close(s.human_goal[:, :5], -circle)
        assert ((circle.norm(dim=-1) - 4).abs() <= 0.5 * math.sqrt(2) + 1e-5).all()
        square = s.human_position[:, 5:]
    else:
        square = s.human_position
    assert (square.abs() <= 5 + 1e-6).all()
    # square humans start and end on opposite sides of x = 0
    sq_goals = s.human_goal[:, 5:] if scenario == "circle" else s.human_goal
    assert (square[..., 0] * sq_goals[..., 0] <= 0).all()


def test_episode_is_a_pure_function_of_stream_seed_and_index():
    cfg = CrowdConfig(scenario="circle")
    a = initial_states(cfg, rng.episode_keys("test", 3, torch.arange(64)))
    b = initial_states(cfg, rng.episode_keys("test", 3, torch.tensor([40, 7])))
    torch.testing.assert_close(b.human_position, a.human_position[[40, 7]], rtol=0, atol=0)
    torch.testing.assert_close(b.human_goal, a.human_goal[[40, 7]], rtol=0, atol=0)


def test_streams_and_seeds_are_disjoint():
    ids = torch.arange(5000)
    keys = {s: set(rng.episode_keys(s, 0, ids).tolist()) for s in ("train", "val", "test")}
    assert not keys["train"] & keys["test"] and not keys["train"] & keys["val"] and not keys["val"] & keys["test"]
    assert len(keys["train"]) == 5000
    assert not set(rng.episode_keys("test", 1, ids).tolist()) & keys["test"]
    cfg = CrowdConfig()
    tr = initial_states(cfg, rng.episode_keys("train", 0, torch.arange(8)))
    te = initial_states(cfg, rng.episode_keys("test", 0, torch.arange(8)))
    assert not torch.allclose(tr.human_position, te.human_position)


def test_uniform_draws_look_uniform():
    u = rng.uniform(torch.tensor([12345]), torch.arange(200_000))
    assert 0 <= float(u.min()) and float(u.max()) < 1
    assert abs(float(u.mean()) - 0.5) < 0.005
    hist = torch.histc(u, bins=10, min=0, max=1) / u.numel()
    assert (hist - 0.1).abs().max() < 0.005


def test_fifty_humans_spawn_and_step():
    cfg = CrowdConfig(scenario="square", num_humans=50)
    s = initial_states(cfg, rng.episode_keys("train", 0, torch.arange(16)))
    s, res = step(cfg, s, torch.zeros(16, 2))
    assert torch.isfinite(s.human_position).all() and res.reward.shape == (16,)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(scenario="triangle"), "scenario"),
        (dict(num_humans=0), "num_humans"),
        (dict(num_humans=2.5), "num_humans"),
        (dict(num_humans=5.0), "num_humans"),  # a count as a float would fail later, far from its key
        (dict(num_humans="5"), "num_humans"),
        (dict(num_humans=500), "num_humans"),
        (dict(min_humans=2.0), "min_humans"),
        (dict(lidar_rays=8.0), "lidar_rays"),
        (dict(orca_max_neighbors=10.0), "orca_max_neighbors"),
        (dict(goal_steps_before_new_goal=1.0), "goal_steps_before_new_goal"),
        (dict(room_pillars=3.0), "room_pillars"),
        (dict(obstacle_tokens=4.0), "obstacle_tokens"),
        (dict(time_step=-0.1), "time_step"),
        (dict(time_limit=0.1), "time_limit"),
    ],
)
def test_bad_config_raises_naming_the_field(kwargs, word):
    with pytest.raises(ValueError, match=word):
        CrowdConfig(**kwargs)


def test_numpy_integer_counts_are_accepted():
    import numpy as np

    assert CrowdConfig(num_humans=np.int64(5), min_humans=np.int32(2)).num_humans == 5


def test_impossible_crowd_raises_spawn_error():
    cfg = CrowdConfig(scenario="square", num_humans=60, square_width=3.0)
    with pytest.raises(SpawnError, match="too crowded"):
        initial_states(cfg, rng.episode_keys("train", 0, torch.arange(4)))


def test_bad_stream_and_seed():
    with pytest.raises(ValueError, match="stream"):
        rng.episode_keys("holdout", 0, torch.arange(2))
    with pytest.raises(ValueError, match="seed"):
        rng.episode_keys("train", -1, torch.arange(2))


def test_step_rejects_wrong_velocity_shape():
    cfg = CrowdConfig(num_humans=1)
    s = make_state((0.0, -4.0), (0.0, 4.0), [(8.0, 8.0)])
    with pytest.raises(ValueError, match="robot_velocity"):
        step(cfg, s, torch.zeros(2, 2))


def test_upstream_collision_check_uses_start_velocities():
    """collision_velocity="start" checks the motion with the humans' old velocities (CrowdNav)."""
    # a human walking away fast at the start is turned back by ORCA towards a goal behind the robot
    s = make_state((0.0, 0.0), (0.0, 4.0), [(0.0, 0.7)], human_vel=[(0.0, 1.0)], human_goal=[(0.0, -3.0)])
    v = torch.zeros(1, 2)
    _, new = step(CrowdConfig(num_humans=1), s, v, torch.tensor([math.pi / 2]))
    _, old = step(CrowdConfig(num_humans=1, collision_velocity="start"), s, v, torch.tensor([math.pi / 2]))
    assert old.min_separation.item() == pytest.approx(0.1, abs=1e-6)  # moving away: start gap
    assert new.min_separation.item() < old.min_separation.item()
    with pytest.raises(ValueError, match="collision_velocity"):
        CrowdConfig(collision_velocity="later")


def test_the_hash_gives_the_same_bits_on_tensors_arrays_and_python_ints():
    """CPU draws hash NumPy views of the tensors; torch (other devices) and Python ints must agree."""
    import numpy as np

    g = torch.Generator().manual_seed(0)
    keys = torch.randint(0, 2**63 - 1, (64, 1), generator=g)
    idx = torch.cat((torch.randint(0, 2**32, (5,), generator=g), torch.tensor([0, 1, 2**32 - 1])))
    by_torch = rng.fold_ints(keys, 3, idx)
    by_numpy = rng.fold_ints(keys.numpy(), 3, idx.numpy())
    assert by_torch.dtype == torch.int64 and by_numpy.dtype == np.int64
    assert np.array_equal(by_torch.numpy(), by_numpy)
    assert torch.equal(rng.fold(keys, 3, idx), by_torch)  # the public CPU path (NumPy)
    assert torch.equal(rng.fold(keys, torch.tensor(3), idx), by_torch)  # a tensor index = the int
    one = [rng.fold_ints(int(k), 3, int(i)) for k, i in ((keys[5, 0], idx[2]), (keys[60, 0], idx[7]))]
    assert one == [int(by_torch[5, 2]), int(by_torch[60, 7])]
    # pinned: the stream of every episode ever generated (changing these changes every scenario)
    k = rng.episode_keys("train", 0, torch.tensor([0, 1, 123456789]))
    assert k.tolist() == [2152384760656441742, 2210934865073242055, 6789695922308809281]
    assert rng.fold(k, 3, torch.tensor([7, 8, 9])).tolist() == [720644922299940120, 1023220482165265465,
                                                               2335978299231985139]


@pytest.mark.parametrize("big", [1e18, 1e20, 3e38])
def test_a_huge_finite_holonomic_velocity_is_capped_to_v_pref_in_its_direction(big):
    """[1e20, 1e20]: the float32 norm overflows; the robot must still move at v_pref towards +x+y."""
    from crowdrl.envs import CrowdNavEnv
    from crowdrl.sim.kinematics import clip_speed

    capped = clip_speed(torch.tensor([[big, big], [-big, 0.0], [0.6, 0.8], [0.3, 0.4]]), 1.0)
    assert torch.allclose(capped, torch.tensor([[0.5 ** 0.5, 0.5 ** 0.5], [-1.0, 0.0], [0.6, 0.8], [0.3, 0.4]]))
    env = CrowdNavEnv("circle", num_envs=1, num_humans=1, seed=0, robot_kinematics="holonomic")
    td = env.reset()
    before = td["robot"][0, :2].clone()
    td["action"] = torch.tensor([[big, big]])
    after = env.step(td)["next", "robot"][0, :2]
    moved = after - before
    v_pref, dt = env.config.robot_v_pref, env.config.time_step
    assert torch.allclose(moved, torch.full((2,), v_pref * dt * 0.5 ** 0.5), atol=1e-5), moved
