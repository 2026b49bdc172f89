"""Obstacles in the robot's observation: the nearest edges, their robot-frame entity tokens, the
encoders' padding invariance over them, the planner's wall check, and the keys a run reads."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from crowdrl_testing import fresh_network
from crowdrl.envs import ENTITY_DIM, CrowdNavEnv, RobotCentric, entity_tokens, obstacles_centric, robot_centric
from crowdrl.models import make_encoder
from crowdrl.models.predictor import ConstantVelocityPredictor
from crowdrl.policies import OnlinePlanner
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import obstacle_hit, step_reward
from crowdrl.sim.kinematics import action_table, decode_action
from crowdrl.sim.obstacles import nearest_edges, obstacle_segments, point_obstacle_distance
from crowdrl.training import validate
from crowdrl.training.facts import ENTITY_OBS_KEYS, OBS_KEYS
from crowdrl.training.factories import make_actor, make_env


def _room(num_envs: int = 6, steps: int = 3) -> CrowdNavEnv:
    env = CrowdNavEnv("room", num_envs=num_envs, seed=4)
    env.rollout(steps, break_when_any_done=False)
    return env


def test_nearest_edges_are_the_k_nearest_by_brute_force():
    env = _room()
    s = env.state
    a, b, valid = obstacle_segments(s.obstacles, s.obstacle_mask)
    edges, mask = nearest_edges(s.robot_position, s.obstacles, s.obstacle_mask, 5)
    assert edges.shape == (6, 5, 4) and bool(mask.all())
    for i in range(6):
        p = s.robot_position[i].double()
        dist = []
        for j in range(a.shape[1]):
            if not valid[i, j]:
                continue
            u, w = (b[i, j] - a[i, j]).double(), p - a[i, j].double()
            t = float((w @ u / (u @ u)).clamp(0, 1))
            dist.append((float(torch.linalg.vector_norm(w - t * u)), torch.cat((a[i, j], b[i, j]))))
        dist.sort(key=lambda d: d[0])
        edge_set = [e for _, e in dist]
        for k in range(5):  # the k-th nearest distance (edges sharing a nearest vertex tie: either may come first)
            assert any(torch.equal(edges[i, k], e) for e in edge_set)
            ax, ay, bx, by = edges[i, k].double()
            u, w = torch.stack((bx - ax, by - ay)), p - torch.stack((ax, ay))
            t = (w @ u / (u @ u)).clamp(0, 1)
            assert abs(float(torch.linalg.vector_norm(w - t * u)) - dist[k][0]) < 1e-6
    # more tokens than edges: the rest is masked padding (zeros)
    edges, mask = nearest_edges(s.robot_position, s.obstacles, s.obstacle_mask, 40)
    assert int(mask[0].sum()) == int(valid[0].sum()) and bool((edges[~mask] == 0).all())


def test_env_observes_the_nearest_edges_and_the_map_only_among_obstacles():
    env = _room()
    td = env.reset()  # the episodes in flight go on: a reset with nothing done is a fresh start
    s = env.state
    edges, mask = nearest_edges(s.robot_position, s.obstacles, s.obstacle_mask, env.config.num_obstacle_tokens)
    assert torch.equal(td["obstacles"], edges) and torch.equal(td["obstacles_mask"], mask)
    assert torch.equal(td["obstacle_polygons"], s.obstacles)
    assert torch.equal(td["obstacle_polygons_mask"], s.obstacle_mask)
    assert env.config.num_obstacle_tokens == 8 and CrowdConfig("doorway").num_obstacle_tokens == 2
    assert "obstacles" not in CrowdNavEnv("circle", num_envs=2).reset().keys()
    check_env_specs(TransformedEnv(CrowdNavEnv("doorway", num_envs=3), RobotCentric(entities=True)))
    with pytest.raises(ValueError, match="obstacle_tokens"):
        CrowdConfig("room", obstacle_tokens=0)


def test_entity_tokens_keep_the_geometry_in_the_robot_frame():
    env = _room()
    td = env.reset()
    robot_rc, humans_rc = robot_centric(td["robot"], td["humans"])
    tokens, mask = entity_tokens(robot_rc, humans_rc, obstacles_centric(td["robot"], td["obstacles"]),
                                 None, td["obstacles_mask"])
    N, K = humans_rc.shape[1], td["obstacles"].shape[1]
    assert tokens.shape == (6, N + K, ENTITY_DIM) and bool(mask.all())
    assert torch.equal(tokens[:, :N, :5], humans_rc) and bool((tokens[:, :N, 5:] == 0).all())
    edge = tokens[:, N:]
    # the point nearest the robot lies at the robot's distance to that edge (a rotation keeps lengths)
    walls = td["obstacles"].reshape(6, K, 2, 2)
    nearest = point_obstacle_distance(td["robot"][:, None, 0:2], walls[:, :1], torch.ones(6, 1, 2, dtype=torch.bool))
    torch.testing.assert_close(torch.linalg.vector_norm(edge[:, 0, 0:2], dim=-1), nearest[:, 0])
    assert torch.all(edge[..., 9] == 1) and torch.all(edge[..., 2:4] == 0)
    torch.testing.assert_close(edge[..., 4], robot_rc[:, 4:5].expand(6, K))
    length = torch.linalg.vector_norm(edge[..., 5:7] - edge[..., 7:9], dim=-1)
    torch.testing.assert_close(length, torch.linalg.vector_norm(td["obstacles"][..., :2] - td["obstacles"][..., 2:], dim=-1))
    # the goal lies on +x: a wall across the way to the goal is crossed by the +x axis
    robot = torch.tensor([[0.0, 0.0, 0, 0, 0.3, 0.0, 5.0, 1, 0]])
    wall = torch.tensor([[[-1.0, 2.0, 1.0, 2.0]]])
    torch.testing.assert_close(obstacles_centric(robot, wall), torch.tensor([[[2.0, 1.0, 2.0, -1.0]]]))


@pytest.mark.parametrize("name", ["sgd3qn", "sarl", "lstm_rl", "mp_rgl"])
def test_encoders_over_entity_tokens_ignore_padding(name):
    torch.manual_seed(0)
    enc = make_encoder(name, human_dim=ENTITY_DIM).double().eval()
    env = _room(num_envs=4)
    td = TransformedEnv(env, RobotCentric(entities=True)).reset()
    robot, tokens, mask = td["robot_rc"].double(), td["entities_rc"].double(), td["entities_mask"].clone()
    mask[:, -3:] = False  # three edges fewer
    padded = torch.where(mask.unsqueeze(-1), tokens, torch.randn_like(tokens) * 100)
    out = enc(robot, padded, mask)
    torch.testing.assert_close(out, enc(robot, tokens[:, :-3], mask[:, :-3]), rtol=0, atol=1e-10)
    assert not torch.allclose(out, enc(robot, tokens, td["entities_mask"]))  # the edges matter


def test_obstacle_hit_takes_candidate_steps():
    cfg = CrowdConfig("doorway")
    env = CrowdNavEnv("doorway", num_envs=3, seed=1)
    env.reset()
    s = env.state
    velocity = torch.randn(3, 5, 2)
    batched = obstacle_hit(cfg, s.robot_position[:, None].expand(3, 5, 2), velocity, s.obstacles, s.obstacle_mask)
    for m in range(5):
        assert torch.equal(batched[:, m], obstacle_hit(cfg, s.robot_position, velocity[:, m], s.obstacles,
                                                       s.obstacle_mask))


class _PreferAction(nn.Module):
    """A stand-in Q network that values one action at 1 and every other at 0."""

    def __init__(self, action: int) -> None:
        super().__init__()
        self.action = action

    def forward(self, robot_rc, humans_rc, mask=None):
        q = torch.zeros(robot_rc.shape[0], 81)
        q[:, self.action] = 1.0
        return q


def test_planner_does_not_drive_into_an_observed_wall():
    cfg = CrowdConfig("doorway")
    table = action_table()
    heading = torch.full((81,), math.pi / 2)
    velocity, _ = decode_action("unicycle", torch.arange(81), heading, table)
    forward = int(velocity[:, 1].argmax())  # full speed towards the goal (+y)
    robot = torch.tensor([[0.0, -0.5, 0.0, 0.0, 0.3, 0.0, 4.0, 1.0, math.pi / 2]])
    humans = torch.tensor([[[5.0, 5.0, 0.0, 0.0, 0.3]]])  # far away
    wall = torch.tensor([[[-2.0, 0.0, 2.0, 0.0]]])  # 0.5 m ahead: a full-speed step touches it
    planner = OnlinePlanner(_PreferAction(forward), ConstantVelocityPredictor(cfg.time_step), cfg, gamma=0.97,
                            depth=1, width=10)
    assert int(planner.plan(robot, humans).action) == forward  # blind to the wall
    plan = planner.plan(robot, humans, None, wall, torch.ones(1, 1, dtype=torch.bool))
    chosen = int(plan.action)
    assert chosen != forward
    hits = step_reward(cfg, robot[:, 0:2], velocity[chosen:chosen + 1], robot[:, 5:7], humans[..., 0:2],
                       humans[..., 2:4], None, wall.reshape(1, 1, 2, 2), torch.ones(1, 1, 2, dtype=torch.bool))
    assert not bool(hits.collided)


def test_a_run_among_obstacles_reads_entity_tokens_and_an_open_one_does_not():
    small = {"train": {"num_envs": 2, "compile_acting": False}}
    door = validate({"env": {"scenario": "doorway"}, **small})
    circle = validate(small)
    assert fresh_network(door).encoder.human_dim == ENTITY_DIM and fresh_network(circle).encoder.human_dim == 5
    env = make_env(door)
    td = env.reset()
    assert td["entities_rc"].shape == (2, 10 + 2, ENTITY_DIM)
    actor = make_actor(door, env, fresh_network(door), ConstantVelocityPredictor(0.25))
    assert actor.entities and "action" in actor(td).keys()
    # a network trained in open space, evaluated among obstacles (zero-shot): the humans only
    door_env = make_env(circle, scenario="doorway")
    assert "entities_rc" not in door_env.reset().keys()
    plain = make_actor(validate({**small, "planning": {"enabled": False}}), door_env, fresh_network(circle))
    assert tuple(plain.in_keys) == OBS_KEYS
    assert tuple(make_actor(validate({"env": {"scenario": "room"}, **small, "planning": {"enabled": False}}),
                            make_env(door), fresh_network(door)).in_keys) == ENTITY_OBS_KEYS


def test_gymnasium_face_observes_the_nearest_edges():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import crowdrl  # noqa: F401  (registers the ids)
    from crowdrl.gym_env import CrowdNavGymEnv

    env = gym.make("crowdrl/Doorway-v0").unwrapped
    assert isinstance(env, CrowdNavGymEnv) and env.config.scenario == "doorway"
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    assert obs["obstacles"].shape == (2, 4) and obs["obstacles_mask"].tolist() == [1, 1]
    batched = CrowdNavEnv("doorway", num_envs=1, seed=3, split="train").reset()
    assert obs["obstacles"].tolist() == batched["obstacles"][0].tolist()
    assert "obstacles" not in gym.make("crowdrl/CircleCrossing-v0").reset(seed=0)[0]
