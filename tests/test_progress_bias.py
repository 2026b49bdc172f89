"""The planner's progress bias (``planning.progress_bias`` κ): the step's progress term counts (1 + κ) times in
the look-ahead's scores, at act time, without retraining. Off by default, exact when off, neutral in the
fingerprint when off, validated like every planner key, and carried by evaluate and export."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from crowdrl.envs import CrowdNavEnv
from crowdrl.models import make_q_network
from crowdrl.models.predictor import ConstantVelocityPredictor
from crowdrl.policies import OnlinePlanner
from crowdrl.sim.lookahead import look_ahead
from crowdrl.training import ConfigError, validate

GAMMA = 0.97
PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained" / "sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s0"


def _planner(env: CrowdNavEnv, bias: float, depth: int = 1, width: int = 6) -> OnlinePlanner:
    torch.manual_seed(0)
    return OnlinePlanner(make_q_network("sarl"), ConstantVelocityPredictor(env.config.time_step), env.config,
                         gamma=GAMMA, depth=depth, width=width, progress_bias=bias)


def _progress(env: CrowdNavEnv, planner: OnlinePlanner, robot, humans, candidates) -> torch.Tensor:
    """Metres towards the goal of each candidate's step, from the simulator's one-step model."""
    cv = ConstantVelocityPredictor(env.config.time_step)
    robot_next, _ = look_ahead(env.config, planner.table, robot, humans, cv(robot, humans, None), candidates)
    goal = robot[:, None, 5:7]
    return (goal - robot[:, None, 0:2]).norm(dim=-1) - (goal - robot_next[..., 0:2]).norm(dim=-1)


def test_the_bias_adds_half_kappa_times_the_progress_reward_to_every_score():
    env = CrowdNavEnv("circle", num_envs=16, num_humans=5, seed=3)
    td = env.reset()
    robot, humans = td["robot"], td["humans"]
    plain = _planner(env, 0.0).plan(robot, humans)
    for bias in (0.5, 2.0):
        planner = _planner(env, bias)
        biased = planner.plan(robot, humans)
        assert torch.equal(biased.candidates, plain.candidates)  # the candidates are Q's top width
        progress = _progress(env, planner, robot, humans, plain.candidates)
        expected = plain.scores + 0.5 * bias * env.config.progress_factor * progress
        torch.testing.assert_close(biased.scores, expected, rtol=0, atol=1e-6)


def test_off_is_the_plain_planner_at_every_depth():
    env = CrowdNavEnv("circle", num_envs=8, num_humans=4, seed=1)
    td = env.reset()
    for depth in (1, 2):
        default = OnlinePlanner(_planner(env, 0.0).net, ConstantVelocityPredictor(env.config.time_step), env.config,
                                gamma=GAMMA, depth=depth, width=4)
        off = _planner(env, 0.0, depth=depth, width=4)
        a, b = default.plan(td["robot"], td["humans"]), off.plan(td["robot"], td["humans"])
        assert torch.equal(a.scores, b.scores) and torch.equal(a.action, b.action)


def test_a_large_bias_acts_by_the_candidate_with_the_most_progress():
    env = CrowdNavEnv("circle", num_envs=32, num_humans=5, seed=2)
    td = env.reset()
    robot, humans = td["robot"], td["humans"]
    planner = _planner(env, 1e6)
    plan = planner.plan(robot, humans)
    progress = _progress(env, planner, robot, humans, plan.candidates)
    chosen = progress.gather(-1, (plan.candidates == plan.action[:, None]).float().argmax(-1, keepdim=True))
    assert torch.allclose(chosen.squeeze(-1), progress.amax(-1))
    assert not torch.equal(plan.action, _planner(env, 0.0).plan(robot, humans).action)  # it changed something


@pytest.mark.parametrize("value", [-0.5, math.inf, math.nan, True])
def test_bad_biases_are_refused_naming_the_key(value):
    with pytest.raises(ConfigError, match="planning.progress_bias"):
        validate({"planning": {"enabled": True, "progress_bias": value}})
    with pytest.raises(ValueError, match="progress_bias"):
        OnlinePlanner(make_q_network("sarl"), ConstantVelocityPredictor(0.25), CrowdNavEnv("circle").config,
                      gamma=GAMMA, progress_bias=value)


def test_the_bias_needs_the_planner():
    with pytest.raises(ConfigError, match="planning.progress_bias.*planning.enabled=true"):
        validate({"planning": {"enabled": False, "progress_bias": 1.0}})


def test_the_bias_off_leaves_the_fingerprint_of_a_run_without_the_key():
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict

    cfg = to_dict(validate({}))
    without = {**cfg, "planning": {k: v for k, v in cfg["planning"].items() if k != "progress_bias"}}
    assert config_fingerprint(cfg) == config_fingerprint(without)
    assert config_fingerprint(to_dict(validate({"planning": {"progress_bias": 0.5}}))) != config_fingerprint(cfg)


@pytest.mark.skipif(not (PRETRAINED / "best.pt").exists(), reason="needs the shipped pretrained agent")
def test_evaluate_acts_with_a_bias_and_records_it():
    from crowdrl.agents import evaluate_spec

    common = dict(checkpoint=PRETRAINED, episodes=4, batch=4, record_episode=None)
    own, _ = evaluate_spec(**common)
    zero, _ = evaluate_spec(**common, planning={"progress_bias": 0.0})
    assert zero["planning_progress_bias"] == 0.0 and {k: zero[k] for k in own} == own
    biased, _ = evaluate_spec(**common, planning={"progress_bias": 1.0})
    assert biased["planning_progress_bias"] == 1.0
    for value in (-1.0, math.nan):
        with pytest.raises(ValueError, match="eval.planning_progress_bias"):
            evaluate_spec(**common, planning={"progress_bias": value})
    greedy = {"depth": 0, "progress_bias": 1.0}
    with pytest.raises(ValueError, match="eval.planning_progress_bias: planning is off"):
        evaluate_spec(**common, planning=greedy)
