"""The pretrained agents in ``pretrained/`` load safely from a clone, their records match their
checkpoints, and ``evaluate.py`` on one of them reproduces its ``eval.json``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from crowdrl_testing.cli import run_cli  # refusals, in this process
from crowdrl.evaluation.report import read_eval_record, read_eval_records

ROOT = Path(__file__).resolve().parents[1]
AGENTS = sorted(p.parent for p in (ROOT / "pretrained").glob("*/best.pt"))
METRICS = ("success_rate", "collision_rate", "timeout_rate", "navigation_time", "average_return")


def test_the_repo_ships_pretrained_agents_with_their_records():
    assert len(AGENTS) >= 3, AGENTS
    index = (ROOT / "pretrained" / "README.md").read_text()
    for agent in AGENTS:
        assert f"`{agent.name}`" in index, agent.name
        assert {p.name for p in agent.iterdir()} >= {"best.pt", "config.yaml", "eval.json"}


@pytest.mark.parametrize("agent", AGENTS, ids=[a.name for a in AGENTS])
def test_each_agent_loads_with_weights_only_and_matches_its_config_and_record(agent):
    from crowdrl.training.compat import stored_config
    from crowdrl.training.config import to_dict
    from crowdrl.training.validation import validate
    from crowdrl.training.pipeline import load_trained_network

    run, net, data = load_trained_network(agent)  # weights_only=True, fingerprint, finite weights
    # its config.yaml, keys it predates at the values it ran with (not today's defaults: issue 50's learner)
    assert to_dict(run) == to_dict(validate(stored_config(OmegaConf.load(agent / "config.yaml")), resources=False))
    records = {r["scenario"]: r for r in read_eval_records(agent / "eval.json")}
    from make_pretrained import default_scenarios
    # where it was trained (plus square, zero-shot, after circle): circle and square in open space, its own among walls
    assert list(records) == default_scenarios(run)
    for scenario, rec in records.items():
        assert rec["episodes"] == 1000 and rec["seed"] == 0, scenario
        assert rec["checkpoint"] == f"pretrained/{agent.name}/best.pt"
        assert rec["checkpoint_frames"] == data["frames"] and rec["train_seed"] == run.seed
        assert rec["success_rate"] + rec["collision_rate"] + rec["timeout_rate"] == pytest.approx(1.0)


def test_an_unknown_pretrained_name_lists_the_agents_that_exist(tmp_path):
    proc = run_cli("evaluate.py", "checkpoint=pretrained/nope", f"hydra.run.dir={tmp_path / 'eval'}", cwd=ROOT)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "no pretrained agent 'nope'" in proc.stderr and AGENTS[0].name in proc.stderr


@pytest.mark.slow  # ~1.5 min (1000 test cases with online planning); make test-slow
def test_evaluate_py_on_a_pretrained_agent_reproduces_its_eval_json(tmp_path):
    agent = AGENTS[0]
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "evaluate.py"),
                           f"checkpoint=pretrained/{agent.name}", "env=square", "eval.record_episode=null",
                           f"hydra.run.dir={tmp_path / 'eval'}"], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "WANDB_MODE": "offline"}, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = read_eval_record(tmp_path / "eval" / "eval.json")
    want = {r["scenario"]: r for r in read_eval_records(agent / "eval.json")}["square"]
    # The same cases through the same code. On the machine that wrote eval.json every digit is equal;
    # on another CPU the compiled kernels round differently, so a robot's path can drift by a step in
    # a few of the 1000 episodes (measured: the same outcomes, navigation time 11.8817 vs 11.8825 s).
    for key in ("success_rate", "collision_rate", "timeout_rate"):
        assert abs(got[key] - want[key]) <= 0.003, (key, got[key], want[key])  # at most 3 of 1000 outcomes
    for key in ("navigation_time", "average_return"):
        assert got[key] == pytest.approx(want[key], rel=1e-3), key


def test_check_pretrained_tells_an_identical_record_from_a_moved_one():
    from check_pretrained import compare
    want = read_eval_records(AGENTS[0] / "eval.json")[0]
    same = compare(want, dict(want))
    assert same["identical"] and same["max_rel_diff"] == 0 and same["outcomes_moved"] == 0
    drift = compare(want, {**want, "navigation_time": want["navigation_time"] * (1 + 1e-4)})
    assert not drift["identical"] and drift["max_rel_diff"] == pytest.approx(1e-4) and drift["outcomes_moved"] == 0
    moved = compare(want, {**want, "success_rate": want["success_rate"] - 0.004,
                           "collision_rate": want["collision_rate"] + 0.004})
    assert moved["outcomes_moved"] == 4 and moved["max_rate_diff"] == pytest.approx(0.004)


def test_check_pretrained_refuses_an_unknown_agent_listing_the_ones_that_exist():
    proc = run_cli("check_pretrained.py", "--agents", "nope")
    assert proc.returncode == 2 and "--agents: no pretrained agent 'nope'" in proc.stderr and AGENTS[0].name in proc.stderr


def test_load_agent_acts_as_evaluate_does():
    """The README's Python example: ``load_agent``'s env and actor play test case 0 to the outcome evaluate gives."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from crowdrl.training import load_agent
    from crowdrl.agents import evaluate_spec

    agent = ROOT / "pretrained" / "sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s0"
    env, actor = load_agent(agent)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        episode = env.rollout(117, policy=actor)
    record, _ = evaluate_spec(checkpoint=agent, episodes=1, record_episode=None)
    event = int(episode["next", "event"][0, -1])
    assert bool(episode["next", "done"][0, -1]) and event in (1, 2, 3)
    assert (event == 1) == (record["success_rate"] == 1.0)
    assert int(episode["step_count"][0, -1]) + 1 == episode.shape[-1]
    for kwargs, named in (({"num_envs": 0}, "num_envs"), ({"device": "cuda:9"}, "device"), ({"split": "x"}, "split"),
                          ({"scenario": "moon"}, "scenario")):
        with pytest.raises(ValueError, match=named):
            load_agent(agent, **kwargs)
