"""CrowdNavEnv (TorchRL); the Gymnasium face is tested in ``test_gym_face.py``."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from crowdrl.envs import CrowdNavEnv, RobotCentric, robot_centric
from crowdrl.sim import rng
from crowdrl.sim.scenarios import initial_states


@pytest.mark.parametrize("scenario, num_envs, num_humans", [("circle", 4, 10), ("square", 3, 5), ("circle", 1, 1)])
def test_check_env_specs(scenario, num_envs, num_humans):
    env = CrowdNavEnv(scenario, num_envs=num_envs, num_humans=num_humans, seed=1)
    check_env_specs(env)
    check_env_specs(TransformedEnv(env, RobotCentric()))


def test_observation_shapes_and_rollout_events():
    env = CrowdNavEnv("circle", num_envs=8, num_humans=10, seed=0)
    td = env.rollout(150, break_when_any_done=False)
    assert td["robot"].shape == (8, 150, 9) and td["humans"].shape == (8, 150, 10, 5)
    done = td["next", "done"]
    assert bool(done.any()), "random actions end some episodes within 150 steps"
    torch.testing.assert_close(done, td["next", "terminated"] | td["next", "truncated"])
    ev = td["next", "event"]
    assert bool(((ev > 0) == done).all())


def test_partial_reset_keeps_running_envs_and_takes_next_episode_ids():
    env = CrowdNavEnv("circle", num_envs=4, num_humans=5, seed=2)
    td = env.reset()
    assert td["episode_id"].view(-1).tolist() == [0, 1, 2, 3]
    td["action"] = torch.zeros(4, dtype=torch.int64)
    td = env.step(td)["next"]
    before = td["humans"].clone()
    mask = torch.tensor([[False], [True], [False], [True]])
    td["_reset"] = mask  # as a collector does: the last observation plus the reset mask
    out = env.reset(td)
    assert out["episode_id"].view(-1).tolist() == [0, 4, 2, 5]
    torch.testing.assert_close(out["humans"][[0, 2]], before[[0, 2]])
    fresh = initial_states(env.config, rng.episode_keys("train", 2, torch.tensor([4, 5])))
    torch.testing.assert_close(out["humans"][[1, 3], :, :2], fresh.human_position)


def test_test_episode_is_the_same_whatever_num_envs():
    a = CrowdNavEnv("square", num_envs=1, split="test", seed=7)
    b = CrowdNavEnv("square", num_envs=5, split="test", seed=7)
    ta = a.reset(TensorDict({"load_episode": torch.tensor([[3]])}, batch_size=[1]))
    tb = b.reset(TensorDict({"load_episode": torch.arange(5).view(5, 1)}, batch_size=[5]))
    torch.testing.assert_close(ta["humans"][0], tb["humans"][3], rtol=0, atol=0)
    assert ta["episode_id"].item() == 3
    with pytest.raises(ValueError, match="load_episode"):
        a.reset(TensorDict({"load_episode": torch.tensor([[-1]])}, batch_size=[1]))


def test_reset_seed_restarts_the_stream():
    env = CrowdNavEnv("circle", num_envs=2)
    env.set_seed(11)
    first = env.reset()["humans"].clone()
    env.reset()
    env.set_seed(11)
    torch.testing.assert_close(env.reset()["humans"], first)


def test_robot_centric_transform_values():
    robot = torch.tensor([[1.0, 1.0, 0.0, 1.0, 0.3, 1.0, 5.0, 1.0, math.pi / 2]])
    humans = torch.tensor([[[1.0, 3.0, 1.0, 0.0, 0.3]]])
    r, h = robot_centric(robot, humans)
    # goal straight ahead (+y): the frame rotates by -pi/2
    torch.testing.assert_close(r, torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.3, 4.0, 0.0, 1.0, 0.0]]), atol=1e-6, rtol=0)
    torch.testing.assert_close(h, torch.tensor([[[2.0, 0.0, 0.0, -1.0, 0.6]]]), atol=1e-6, rtol=0)


def test_robot_centric_transform_in_env_and_on_batches():
    env = TransformedEnv(CrowdNavEnv("circle", num_envs=2), RobotCentric())
    td = env.reset()
    assert td["robot_rc"].shape == (2, 9) and td["humans_rc"].shape == (2, 10, 5)
    assert torch.all(td["robot_rc"][:, :2] == 0)
    with pytest.raises(KeyError, match="robot"):
        RobotCentric()(TensorDict({"humans": torch.zeros(2, 3, 5)}, batch_size=[2]))


@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(scenario="maze"), "scenario"),
        (dict(num_humans=0), "num_humans"),
        (dict(num_envs=0), "num_envs"),
        (dict(split="holdout"), "split"),
        (dict(seed=-3), "seed"),
    ],
)
def test_bad_constructor_arguments(kwargs, word):
    with pytest.raises(ValueError, match=word):
        CrowdNavEnv(**kwargs)


@pytest.mark.parametrize(
    "action, word",
    [
        (torch.full((2,), 81), "0..80"),
        (torch.full((2,), -1), "0..80"),
        (torch.zeros(3, dtype=torch.int64), "shaped"),
        (torch.zeros(2), "integer"),
    ],
)
def test_bad_actions_raise(action, word):
    env = CrowdNavEnv("circle", num_envs=2)
    env.reset()
    with pytest.raises((ValueError, TypeError), match=word):
        env._step(TensorDict({"action": action}, batch_size=[]))


def test_one_hot_actions_are_accepted():
    env = CrowdNavEnv("circle", num_envs=2)
    env.reset()
    onehot = torch.zeros(2, 81, dtype=torch.bool)
    onehot[:, 5] = True
    out = env._step(TensorDict({"action": onehot}, batch_size=[2]))
    ref = CrowdNavEnv("circle", num_envs=2)
    ref.reset()
    out2 = ref._step(TensorDict({"action": torch.full((2,), 5)}, batch_size=[2]))
    torch.testing.assert_close(out["robot"], out2["robot"])


def test_env_runs_in_a_torchrl_collector_with_auto_reset():
    from torchrl.collectors import Collector

    env = TransformedEnv(CrowdNavEnv("circle", num_envs=4, num_humans=5, seed=0), RobotCentric())
    collector = Collector(env, policy=None, frames_per_batch=200, total_frames=400)
    try:
        batches = [b for b in collector]
    finally:
        collector.shutdown()
    batch = torch.cat(batches, dim=1)
    done = batch["next", "done"].squeeze(-1)
    assert bool(done.any())
    env_i, t = done[:, :-1].nonzero(as_tuple=True)[0][0], done[:, :-1].nonzero(as_tuple=True)[1][0]
    after = batch[env_i, t + 1]
    # the step after an episode's end starts a fresh episode at the robot's start pose
    torch.testing.assert_close(after["robot"][:2], torch.tensor([0.0, -4.0]))
    assert after["episode_id"].item() > batch[env_i, t]["episode_id"].item()


def test_step_count_and_episode_reward_count_from_each_reset():
    env = CrowdNavEnv("circle", num_envs=8, num_humans=5)
    td = env.rollout(60, break_when_any_done=False)  # auto-resets the envs that finish
    nxt = td["next"]
    steps, total = torch.zeros(8, dtype=torch.int64), torch.zeros(8)
    for t in range(60):
        steps, total = steps + 1, total + nxt["reward"][:, t, 0]
        assert torch.equal(nxt["step_count"][:, t, 0], steps)
        torch.testing.assert_close(nxt["episode_reward"][:, t, 0], total)
        done = nxt["done"][:, t, 0]
        steps, total = torch.where(done, 0, steps), torch.where(done, 0.0, total)
    assert bool(nxt["done"].any()), "no episode ended: the test did not cover a reset"


def test_a_restored_snapshot_continues_the_episodes_exactly():
    """Snapshot mid-episode, restore into a new env: its first reset hands back the same
    observations, and the same actions give the same steps, auto-resets included."""
    gen = torch.Generator().manual_seed(3)
    actions = torch.randint(0, 81, (80, 6), generator=gen)
    env = CrowdNavEnv("square", num_envs=6, num_humans=5, seed=4)
    td = env.reset()
    for t in range(25):
        _, td = env.step_and_maybe_reset(td.set("action", actions[t]))
    saved = env.snapshot()
    twin = CrowdNavEnv("square", num_envs=6, num_humans=5, seed=4)
    twin.restore(saved)
    td2 = twin.reset()
    assert (td.exclude("action") == td2).all()
    for t in range(25, 80):
        out, td = env.step_and_maybe_reset(td.set("action", actions[t]))
        out2, td2 = twin.step_and_maybe_reset(td2.set("action", actions[t]))
        assert (out == out2).all(), f"step {t}"
    assert twin.next_episode == env.next_episode > 6


@pytest.mark.parametrize("change, word", [({"seed": 5}, "seed"), ({"split": "val"}, "split"),
                                          ({"num_envs": 3}, "num_envs"), ({"num_humans": 4}, "num_humans")])
def test_a_snapshot_of_another_env_is_refused_naming_what_differs(change, word):
    env = CrowdNavEnv("circle", **{"num_envs": 2, "num_humans": 5, "seed": 0, "split": "train"})
    env.reset()
    other = CrowdNavEnv("circle", **{"num_envs": 2, "num_humans": 5, "seed": 0, "split": "train", **change})
    with pytest.raises(ValueError, match=word):
        other.restore(env.snapshot())
    with pytest.raises(ValueError, match="snapshot"):
        other.restore({"format": 0})
