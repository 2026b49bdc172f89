"""The planner's run-time safety check (``planning.safety_horizon``): an action is unsafe when, held, it
collides with the predicted crowd within the horizon; the planner then acts by a safe one. Off by default,
and neutral in the fingerprint when off."""

from __future__ import annotations

import pytest
import torch

from crowdrl.envs import CrowdNavEnv
from crowdrl.models import make_q_network
from crowdrl.models.predictor import ConstantVelocityPredictor
from crowdrl.policies import OnlinePlanner
from crowdrl.sim.lookahead import look_ahead
from crowdrl.training import ConfigError, validate

GAMMA = 0.97


def _planner(env, horizon: int) -> OnlinePlanner:
    torch.manual_seed(0)
    return OnlinePlanner(make_q_network("sarl"), ConstantVelocityPredictor(env.config.time_step), env.config,
                         gamma=GAMMA, width=5, safety_horizon=horizon)


def _head_on(env: CrowdNavEnv, distance: float = 1.0):
    """Observations with human 0 in front of the robot (1.0 m between centres), walking at it at 1 m/s."""
    td = env.reset()
    humans = td["humans"].clone()
    robot = td["robot"]
    humans[:, 0, 0:2] = robot[:, 0:2] + torch.tensor([0.0, distance])
    humans[:, 0, 2:4] = torch.tensor([0.0, -1.0])
    return robot, humans


def test_one_step_safety_is_the_look_aheads_collision():
    env = CrowdNavEnv("circle", num_envs=3, num_humans=5, seed=0)
    robot, humans = _head_on(env)
    planner = _planner(env, 1)
    safe = planner.safe_actions(robot, humans)
    cv = ConstantVelocityPredictor(env.config.time_step)
    actions = torch.arange(81).expand(3, 81)
    _, judged = look_ahead(env.config, planner.table, robot, humans, cv(robot, humans, None), actions)
    assert torch.equal(safe, ~judged.collided)
    assert not bool(safe.all())  # something in front is unsafe
    assert bool(_planner(env, 0).safe_actions(robot, humans).all())  # off: everything is allowed


def test_a_longer_horizon_forbids_more():
    env = CrowdNavEnv("circle", num_envs=3, num_humans=5, seed=0)
    robot, humans = _head_on(env)
    counts = [int(_planner(env, h).safe_actions(robot, humans).sum()) for h in (1, 2, 4)]
    assert counts[0] >= counts[1] >= counts[2] and counts[0] > counts[2], counts


def test_the_planner_acts_by_a_safe_action_whenever_there_is_one():
    env = CrowdNavEnv("circle", num_envs=8, num_humans=5, seed=0)
    robot, humans = _head_on(env)
    for horizon in (1, 2, 3):
        planner = _planner(env, horizon)
        safe = planner.safe_actions(robot, humans)
        action = planner.plan(robot, humans).action
        chosen_safe = safe.gather(-1, action[:, None]).squeeze(-1)
        assert bool((chosen_safe | ~safe.any(-1)).all()), horizon


class Straight(torch.nn.Module):
    """A Q network that prefers action 40 (1 m/s, 2 degrees to the right): straight ahead, fast."""

    def forward(self, robot_rc, humans_rc, mask=None):
        q = torch.zeros(robot_rc.shape[0], 81)
        q[:, 40] = 1.0
        return q


def test_the_check_replaces_an_action_that_collides_beyond_the_planners_step():
    """1.5 m head-on: one step ahead nothing collides, so the planner keeps going straight; two steps ahead
    that collides, so the two-step check turns away."""
    env = CrowdNavEnv("circle", num_envs=2, num_humans=5, seed=0)
    robot, humans = _head_on(env, 1.5)
    cv = ConstantVelocityPredictor(env.config.time_step)
    plain = OnlinePlanner(Straight(), cv, env.config, gamma=GAMMA, width=5)
    checked = OnlinePlanner(Straight(), cv, env.config, gamma=GAMMA, width=5, safety_horizon=2)
    assert plain.plan(robot, humans).action.tolist() == [40, 40]
    assert not bool(checked.safe_actions(robot, humans)[:, 40].any())
    action = checked.plan(robot, humans).action
    assert bool((action != 40).all()) and bool(checked.safe_actions(robot, humans).gather(-1, action[:, None]).all())


@pytest.mark.parametrize("value, message", [(-1, "planning.safety_horizon"), (21, "planning.safety_horizon")])
def test_bad_safety_horizons_are_refused_naming_the_key(value, message):
    with pytest.raises(ConfigError, match=message):
        validate({"planning": {"enabled": True, "safety_horizon": value}})
    with pytest.raises(ValueError, match="safety_horizon"):
        OnlinePlanner(make_q_network("sarl"), ConstantVelocityPredictor(0.25), CrowdNavEnv("circle").config,
                      gamma=GAMMA, safety_horizon=value)


def test_the_safety_check_needs_the_planner():
    with pytest.raises(ConfigError, match="planning.safety_horizon.*planning.enabled=true"):
        validate({"planning": {"enabled": False, "safety_horizon": 2}})


def test_the_check_off_leaves_the_fingerprint_of_a_run_without_the_key():
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict

    cfg = to_dict(validate({}))
    without = {**cfg, "planning": {k: v for k, v in cfg["planning"].items() if k != "safety_horizon"}}
    assert config_fingerprint(cfg) == config_fingerprint(without)
    assert config_fingerprint(to_dict(validate({"planning": {"safety_horizon": 2}}))) != config_fingerprint(cfg)


def test_evaluate_acts_with_another_planner_without_retraining():
    """``eval.planning_depth`` / ``_width`` / ``_safety_horizon``: a checkpoint acts with another planner; the
    checkpoint's own values give its own numbers; bad values (depth -1; 0 is planning off:
    tests/test_export_planner.py) and the ORCA baseline are refused naming the key."""
    from pathlib import Path

    from crowdrl.agents import evaluate_spec

    ck = Path(__file__).resolve().parents[1] / "pretrained" / "sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s0"
    common = dict(checkpoint=ck, episodes=4, batch=4, record_episode=None)
    own, _ = evaluate_spec(**common)
    same, _ = evaluate_spec(**common, planning={"depth": 1, "width": 10, "safety_horizon": None})
    assert same["planning_depth"] == 1 and "planning_safety_horizon" not in same
    assert {k: same[k] for k in own} == own
    deeper, _ = evaluate_spec(**common, planning={"depth": 2, "safety_horizon": 2})
    assert deeper["planning_depth"] == 2 and deeper["planning_safety_horizon"] == 2
    for planning, key in (({"depth": -1}, "eval.planning_depth"), ({"width": 82}, "eval.planning_width"),
                          ({"safety_horizon": 21}, "eval.planning_safety_horizon")):
        with pytest.raises(ValueError, match=key):
            evaluate_spec(**common, planning=planning)
    with pytest.raises(ValueError, match="eval.planning_depth: the ORCA baseline has no planner"):
        evaluate_spec(policy="orca", episodes=4, record_episode=None, planning={"depth": 2})
