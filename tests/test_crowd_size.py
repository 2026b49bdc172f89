"""Crowds of variable size: each episode draws its size, absent humans are masked everywhere, and
one network serves any crowd."""

from __future__ import annotations

import math

import pytest
import torch

from crowdrl_testing import fresh_network
from crowdrl.envs import CrowdNavEnv
from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import observe, step, step_reward
from crowdrl.sim.kinematics import action_table
from crowdrl.sim.scenarios import crowd_sizes, initial_states
from crowdrl.training.config import ConfigError, crowd_range
from crowdrl.training.validation import validate

torch.set_num_threads(1)
VARIABLE = CrowdConfig(scenario="circle", num_humans=12, min_humans=3)


# ---------------------------------------------------------------- the draw
def test_crowd_sizes_cover_the_range_and_are_a_pure_function_of_the_episode():
    keys = rng.episode_keys("train", 0, torch.arange(4000))
    sizes = crowd_sizes(VARIABLE, keys)
    assert sizes.min() == 3 and sizes.max() == 12
    counts = torch.bincount(sizes - 3, minlength=10).double()
    assert counts.min() > 0.8 * 400 and counts.max() < 1.2 * 400  # uniform over 3..12
    assert torch.equal(crowd_sizes(VARIABLE, keys[1234:1300]), sizes[1234:1300])  # whatever the batch
    fixed = CrowdConfig(num_humans=7)
    assert torch.equal(crowd_sizes(fixed, keys[:5]), torch.full((5,), 7))


@pytest.mark.parametrize("scenario", ["circle", "square"])
def test_the_present_humans_are_those_of_the_fixed_crowd_of_that_size(scenario):
    """Human i is placed clear of humans 0..i-1 only, so an episode of the range with n humans
    starts as the same episode of a fixed crowd of n; absent humans stand apart, masked."""
    cfg = CrowdConfig(scenario=scenario, num_humans=12, min_humans=3)
    keys = rng.episode_keys("test", 0, torch.arange(40))
    var = initial_states(cfg, keys)
    sizes = crowd_sizes(cfg, keys)
    assert torch.equal(var.human_mask, torch.arange(12) < sizes.unsqueeze(1))
    for n in sizes.unique().tolist():
        idx = (sizes == n).nonzero().squeeze(1)
        fixed = initial_states(CrowdConfig(scenario=scenario, num_humans=n), keys[idx])
        assert torch.equal(var.human_position[idx, :n], fixed.human_position)
        assert torch.equal(var.human_goal[idx, :n], fixed.human_goal)
        far = var.human_position[idx, n:]
        assert bool((far.abs() > 1000).all())  # parked far from everything


def test_a_variable_episode_unrolls_as_the_fixed_episode_of_its_size():
    """Same robot actions: the robot, the present humans, rewards and events follow the fixed
    crowd's episode (ORCA with absent agents masked equals ORCA without them)."""
    cfg = CrowdConfig(scenario="circle", num_humans=9, min_humans=2)
    keys = rng.episode_keys("val", 3, torch.arange(24))
    sizes = crowd_sizes(cfg, keys)
    table = action_table()
    gen = torch.Generator().manual_seed(0)
    actions = torch.randint(0, 81, (40, 24), generator=gen)
    var = initial_states(cfg, keys)
    fixed = {n: initial_states(CrowdConfig(scenario="circle", num_humans=n), keys[sizes == n])
             for n in sizes.unique().tolist()}
    for t in range(40):
        vel = table[actions[t]]  # holonomic-style velocities from the table's (speed, angle) pairs
        vel = torch.stack((vel[:, 0] * torch.cos(vel[:, 1]), vel[:, 0] * torch.sin(vel[:, 1])), -1)
        var, res = step(cfg, var, vel)
        assert bool((var.human_velocity[~var.human_mask] == 0).all())  # absent humans stand still
        for n, state in fixed.items():
            sel = sizes == n
            fixed[n], fres = step(CrowdConfig(scenario="circle", num_humans=n), state, vel[sel])
            torch.testing.assert_close(var.human_position[sel, :n], fixed[n].human_position, atol=1e-5, rtol=0)
            torch.testing.assert_close(res.reward[sel], fres.reward, atol=1e-5, rtol=0)
            assert torch.equal(res.event[sel], fres.event)
            assert torch.equal(res.discomfort_count[sel], fres.discomfort_count)


def test_absent_humans_neither_collide_nor_cause_discomfort_nor_enter_the_reward():
    cfg = CrowdConfig(num_humans=3)
    robot, goal = torch.tensor([[0.0, -4.0]]), torch.tensor([[0.0, 4.0]])
    v = torch.tensor([[0.0, 1.0]])
    humans = torch.tensor([[[0.0, -3.9], [0.25, -3.5], [5.0, 5.0]]])  # 0 on the robot, 1 in discomfort
    hv = torch.zeros(1, 3, 2)
    everyone = step_reward(cfg, robot, v, goal, humans, hv)
    assert bool(everyone.collided) and int(everyone.discomfort_count) == 2
    only_far = step_reward(cfg, robot, v, goal, humans, hv, torch.tensor([[False, False, True]]))
    assert not bool(only_far.collided) and int(only_far.discomfort_count) == 0
    alone = step_reward(cfg, robot, v, goal, humans[:, 2:], hv[:, 2:])
    assert torch.equal(only_far.reward, alone.reward) and torch.equal(only_far.min_separation, alone.min_separation)
    assert math.isclose(float(alone.reward), 0.2 * 0.25, rel_tol=1e-5)  # progress only
    nobody = step_reward(cfg, robot, v, goal, humans, hv, torch.zeros(1, 3, dtype=torch.bool))
    assert float(nobody.min_separation) == math.inf and not bool(nobody.collided)


def test_absent_humans_are_zero_rows_of_the_observation():
    keys = rng.episode_keys("train", 0, torch.arange(16))
    state = initial_states(VARIABLE, keys)
    _, humans = observe(VARIABLE, state)
    assert bool((humans[~state.human_mask] == 0).all())
    assert bool((humans[state.human_mask][:, 4] == VARIABLE.human_radius).all())


# ---------------------------------------------------------------- the env and its transforms
def test_env_emits_the_mask_and_the_robot_centric_transform_keeps_it():
    from crowdrl.training.validation import validate as v
    from crowdrl.training.facts import obs_keys
    from crowdrl.training.factories import make_env

    run = v({"env": {"min_humans": 2, "max_humans": 6}, "train": {"num_envs": 8}})
    env = make_env(run, split="train")
    base = env.base_env
    assert base.config.num_humans == 6 and base.config.min_humans == 2
    assert obs_keys(base.config) == ("robot_rc", "humans_rc", "humans_mask")
    td = env.rollout(30, break_when_any_done=False)
    mask = td.get("humans_mask")
    assert mask.shape == (8, 30, 6) and mask.dtype == torch.bool
    assert env.observation_spec["humans_mask"].shape == (8, 6)
    sizes = mask.sum(-1)
    assert sizes.min() >= 2 and sizes.max() <= 6 and sizes.unique().numel() > 1
    assert bool(td.get("humans_rc")[~mask].isfinite().all())
    fixed = make_env(validate({"train": {"num_envs": 2}}), split="train")
    assert obs_keys(fixed.base_env.config) == ("robot_rc", "humans_rc")
    assert bool(fixed.reset().get("humans_mask").all())


def test_snapshot_restore_of_a_variable_crowd_and_refusal_of_an_older_snapshot():
    env = CrowdNavEnv("circle", num_envs=4, num_humans=8, min_humans=2, seed=1)
    env.reset()
    for _ in range(5):
        env.rand_step()
    saved = env.snapshot()
    env2 = CrowdNavEnv("circle", num_envs=4, num_humans=8, min_humans=2, seed=1)
    env2.restore(saved)
    assert torch.equal(env2.reset().get("humans_mask"), env.state.human_mask)
    other = CrowdNavEnv("circle", num_envs=4, num_humans=8, seed=1)
    with pytest.raises(ValueError, match="min_humans"):
        other.restore(saved)
    old = CrowdNavEnv("circle", num_envs=4, num_humans=8, seed=1)
    old.reset()
    legacy = old.snapshot()
    del legacy["tensors"]["state.human_mask"], legacy["min_humans"]
    legacy["format"] = 1  # as written before crowds varied: no mask
    fresh = CrowdNavEnv("circle", num_envs=4, num_humans=8, seed=1)
    with pytest.raises(ValueError, match="snapshot of format 1; this code restores format 2 only"):
        fresh.restore(legacy)


# ---------------------------------------------------------------- configuration
def test_crowd_range_defaults_each_end_to_num_humans():
    assert crowd_range(validate({}).env) == (10, 10)
    assert crowd_range(validate({"env": {"min_humans": 5}}).env) == (5, 10)
    assert crowd_range(validate({"env": {"max_humans": 20}}).env) == (10, 20)
    assert crowd_range(validate({"env": {"min_humans": 5, "max_humans": 20}}).env) == (5, 20)


@pytest.mark.parametrize("env, key", [
    ({"min_humans": 12, "max_humans": 5}, "env.min_humans/env.max_humans"),
    ({"min_humans": 15}, "env.min_humans/env.max_humans"),  # above num_humans = 10
    ({"min_humans": 0, "max_humans": 5}, "env.min_humans"),
    ({"max_humans": 65}, "env.max_humans"),
])
def test_bad_crowd_ranges_are_named(env, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.").replace("/", "/")):
        validate({"env": env})


def test_crowd_config_and_env_reject_bad_min_humans():
    with pytest.raises(ValueError, match="min_humans"):
        CrowdConfig(num_humans=5, min_humans=6)
    with pytest.raises(ValueError, match="min_humans"):
        CrowdConfig(num_humans=5, min_humans=0)
    with pytest.raises(ValueError, match="min_humans"):
        CrowdNavEnv("circle", num_humans=5, config=CrowdConfig(num_humans=5), min_humans=2)


def test_older_run_configs_keep_their_fingerprint():
    """Run folders recorded before the crowd range existed still load (the keys at null are left out)."""
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict

    now = to_dict(validate({}))
    before = {**now, "env": {k: v for k, v in now["env"].items() if k not in ("min_humans", "max_humans")}}
    assert config_fingerprint(now) == config_fingerprint(before)
    ranged = to_dict(validate({"env": {"min_humans": 5}}))
    assert config_fingerprint(ranged) != config_fingerprint(now)


def test_obstacle_geometry_is_in_the_fingerprint_only_where_there_are_obstacles():
    """Open-space runs recorded before the obstacle keys existed keep their fingerprint (their best.pt
    still loads); in an obstacle scenario the geometry is part of the problem."""
    from crowdrl.sim.config import OBSTACLE_KEYS
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict

    now = to_dict(validate({}))
    before = {**now, "env": {k: v for k, v in now["env"].items() if k not in OBSTACLE_KEYS}}
    assert config_fingerprint(now) == config_fingerprint(before)
    assert config_fingerprint(to_dict(validate({"env": {"corridor_width": 3.0}}))) == config_fingerprint(now)
    room = to_dict(validate({"env": {"scenario": "room"}}))
    wider = to_dict(validate({"env": {"scenario": "room", "room_pillars": 2}}))
    assert config_fingerprint(room) != config_fingerprint(wider)


def test_orca_ignores_absent_humans_wherever_they_stand():
    """Absent humans moved into the crowd (not parked): the present humans' ORCA velocities are
    those of the crowd without them."""
    from crowdrl.sim.crowd import human_velocities

    cfg = CrowdConfig(scenario="square", num_humans=8, min_humans=2)
    state = initial_states(cfg, rng.episode_keys("train", 5, torch.arange(32)))
    mask = state.human_mask
    intruders = state.human_position[:, :1] + torch.tensor([0.7, 0.0])  # next to human 0
    moved = state.replace(human_position=torch.where(mask.unsqueeze(-1), state.human_position, intruders))
    vel, _ = human_velocities(cfg, moved)
    for n in crowd_sizes(cfg, state.episode_key).unique().tolist():
        sel = mask.sum(-1) == n
        alone = moved.index(sel)
        alone = alone.replace(**{k: getattr(alone, k)[:, :n] for k in
                                 ("human_position", "human_velocity", "human_goal", "human_goal_steps", "human_mask")})
        ref, _ = human_velocities(CrowdConfig(scenario="square", num_humans=n), alone)
        torch.testing.assert_close(vel[sel, :n], ref, atol=1e-6, rtol=0)


def test_a_recorded_episode_holds_only_the_humans_present():
    from crowdrl.evaluation import evaluate
    from crowdrl.policies import OrcaRobotPolicy
    from crowdrl.sim.config import CrowdConfig as C

    cfg = C(scenario="circle", num_humans=9, min_humans=2, robot_kinematics="holonomic")
    env = CrowdNavEnv("circle", num_envs=4, num_humans=9, config=cfg, split="test")
    _, traj = evaluate(env, OrcaRobotPolicy(cfg), num_episodes=4, record_episode=1)
    n = int(crowd_sizes(cfg, rng.episode_keys("test", 0, torch.tensor([1]))))
    assert traj.num_humans == n < 9


def test_the_orca_robot_sees_only_the_humans_present():
    """ORCA on a variable crowd moves the robot, episode for episode, as ORCA on the fixed crowd of
    each episode's size (same test cases), until the episode ends."""
    from crowdrl.policies import OrcaRobotPolicy

    cfg = CrowdConfig(scenario="circle", num_humans=6, min_humans=2, robot_kinematics="holonomic")
    env = CrowdNavEnv("circle", num_envs=12, num_humans=6, config=cfg, split="test")
    sizes = crowd_sizes(cfg, rng.episode_keys("test", 0, torch.arange(12)))
    rollout = env.rollout(cfg.max_steps, OrcaRobotPolicy(cfg), break_when_any_done=False)
    ended = rollout["next", "done"].squeeze(-1).long().cumsum(1) > 0
    running = torch.cat((torch.ones_like(ended[:, :1]), ~ended[:, :-1]), 1)  # steps up to and including the end
    for n in sizes.unique().tolist():
        fixed_cfg = CrowdConfig(scenario="circle", num_humans=n, robot_kinematics="holonomic")
        ids = (sizes == n).nonzero().squeeze(1)
        fixed = CrowdNavEnv("circle", num_envs=ids.numel(), num_humans=n, config=fixed_cfg, split="test")
        fixed.load_episodes(ids)
        ref = fixed.rollout(cfg.max_steps, OrcaRobotPolicy(fixed_cfg), auto_reset=False, tensordict=fixed.reset(),
                            break_when_any_done=False)
        keep = running[ids]
        got, want = rollout["next", "robot"][ids][..., :4][keep], ref["next", "robot"][..., :4][keep]
        torch.testing.assert_close(got, want, atol=1e-5, rtol=0)
        assert torch.equal(rollout["next", "reward"][ids][keep], ref["next", "reward"][keep])


# ---------------------------------------------------------------- one model, any crowd
@pytest.fixture(scope="module")
def range_run(tmp_path_factory):
    """A tiny run trained on crowds of 1..4 humans."""
    from crowdrl.training.trainer import Trainer

    run = validate({"env": {"min_humans": 1, "max_humans": 4}, "logger": {"name": "csv", "progress_bar": False,
                                                                          "render": False},
                    "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 96, "buffer_size": 1000,
                              "batch_size": 16, "warmup_frames": 32, "updates_per_frame": 0.25,
                              "target_update_frames": 32, "val_every_frames": 96, "val_episodes": 2,
                              "checkpoint_every_frames": 96, "test_episodes": 2, "compile_loss": False}})
    folder = tmp_path_factory.mktemp("range_run")
    trainer = Trainer(run, folder)
    try:
        trainer.train()
    finally:
        trainer.close()
    return folder


@pytest.mark.parametrize("num_humans", [1, 7])
def test_a_model_trained_on_a_range_is_tested_on_any_fixed_crowd(range_run, num_humans):
    from crowdrl.agents import evaluate_spec

    record, _ = evaluate_spec(checkpoint=range_run, episodes=6, num_humans=num_humans, batch=3)
    assert record["episodes"] == 6
    assert record["success_rate"] + record["collision_rate"] + record["timeout_rate"] == pytest.approx(1.0)
    ranged, _ = evaluate_spec(checkpoint=range_run, episodes=6)  # the run's own range
    assert ranged["episodes"] == 6


def test_eval_num_humans_out_of_range_is_named(range_run):
    from crowdrl.agents import evaluate_spec

    for bad in (0, 65, 2.5):
        with pytest.raises(ValueError, match=r"eval\.num_humans"):
            evaluate_spec(checkpoint=range_run, episodes=2, num_humans=bad)


def test_crowd_sizes_script_writes_the_generalisation_table(range_run, tmp_path):
    import json

    from crowdrl_testing.cli import run_cli

    cmd = ["crowd_sizes.py", "--out", str(tmp_path), "--sizes", "1", "3", "--episodes", "4",
           "--group", f"1-4 humans={range_run}", "--json"]
    done = run_cli(*cmd)  # in this process
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert list(result["table"]) == ["1-4 humans", "ORCA"] and result["sizes"] == [1, 3]
    cells = sorted((tmp_path / "cells").glob("*.json"))
    assert len(cells) == 4  # (run + ORCA) x 2 sizes
    orca3 = [json.loads(c.read_text()) for c in cells if json.loads(c.read_text())["source"] == "orca"]
    assert sorted(r["num_humans"] for r in orca3) == [1, 3]
    md = (tmp_path / "table.md").read_text()
    assert "| 1-4 humans | 1 |" in md and "| ORCA | 1 |" in md
    bad = run_cli(*cmd[:-1], "--group", "x=/nonexistent")
    assert bad.returncode != 0 and "/nonexistent does not exist" in bad.stderr


@pytest.mark.parametrize("predictor", ["const_vel", "learned"])
def test_the_planner_on_a_variable_crowd_plans_as_on_the_humans_present(predictor):
    """planning.enabled with a crowd range: the planner reads the mask, and each row's plan equals
    the plan of the same state with the absent humans cut off."""
    from crowdrl.training.acting import make_predictor_of
    from crowdrl.training.facts import RunFacts
    from crowdrl.training.factories import make_actor, make_env

    torch.manual_seed(0)
    run = validate({"env": {"min_humans": 2, "max_humans": 6}, "train": {"num_envs": 12},
                    "planning": {"enabled": True, "predictor": predictor}})
    env = make_env(run, split="val")
    net = fresh_network(run).eval()
    planner = make_actor(run, env, net, make_predictor_of(run.planning, RunFacts.of(run)))
    assert "humans_mask" in planner.in_keys
    td = env.reset()
    td = env.rollout(5, planner, auto_reset=False, tensordict=td, break_when_any_done=False)[:, -1]["next"]
    padded = planner.plan(td["robot"], td["humans"], td["humans_mask"])
    for row in range(12):
        n = int(td["humans_mask"][row].sum())
        alone = planner.plan(td["robot"][row:row + 1], td["humans"][row:row + 1, :n])
        torch.testing.assert_close(padded.scores[row], alone.scores[0], atol=1e-5, rtol=1e-5)
        assert int(padded.action[row]) == int(alone.action[0])
    fixed = validate({"train": {"num_envs": 2}, "planning": {"enabled": True}})
    fixed_env = make_env(fixed, split="val")
    assert "humans_mask" not in make_actor(fixed, fixed_env, fresh_network(fixed),
                                           make_predictor_of(fixed.planning, RunFacts.of(fixed))).in_keys
