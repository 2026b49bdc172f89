"""Metrics (SPEC §5) on hand-computed cases, and the ORCA baseline end to end."""

from __future__ import annotations

import math

import pytest
import torch

from crowdrl.evaluation import average_returns, discount_per_step, episode_metrics, evaluate_policy
from crowdrl.policies import OrcaRobotPolicy
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import COLLISION, SUCCESS, TIMEOUT


def test_discount_is_upstreams():
    assert discount_per_step() == pytest.approx(0.9 ** 0.25) == pytest.approx(0.97400, abs=1e-5)


def test_average_return_by_hand():
    g = 0.5
    rewards = torch.tensor([[1.0, 2.0, 4.0], [3.0, 0.0, 0.0]], dtype=torch.float64)
    lengths = torch.tensor([3, 1])
    # episode 0: G0 = 1 + .5*2 + .25*4 = 3, G1 = 2 + .5*4 = 4, G2 = 4 -> mean 11/3; episode 1: 3
    out = average_returns(rewards, lengths, g)
    torch.testing.assert_close(out, torch.tensor([11 / 3, 3.0], dtype=torch.float64))


def test_episode_metrics_by_hand():
    events = torch.tensor([SUCCESS, COLLISION, TIMEOUT, SUCCESS])
    lengths = torch.tensor([40, 10, 117, 60])
    rewards = torch.zeros(4, 117, dtype=torch.float64)
    rewards[2, 116] = 0.0
    disc_steps = torch.tensor([2, 0, 1, 1])
    disc_sep = torch.tensor([0.2, 0.0, 0.05, 0.1], dtype=torch.float64)
    m = episode_metrics(events, lengths, rewards, disc_steps, disc_sep, time_step=0.25, discount=1.0)
    assert m.success_rate == 0.5 and m.collision_rate == 0.25 and m.timeout_rate == 0.25
    assert m.navigation_time == pytest.approx((40 + 60) / 2 * 0.25)
    # only the timeout's -0.25 on its last step counts; with discount 1 its mean return is -0.25
    assert m.average_return == pytest.approx(-0.25 / 4)
    assert m.discomfort_frequency == pytest.approx(4 / 227)
    assert m.discomfort_min_separation == pytest.approx(0.35 / 4)


def test_metrics_without_success_report_nan_time():
    m = episode_metrics(torch.tensor([COLLISION]), torch.tensor([3]), torch.zeros(1, 5, dtype=torch.float64),
                        torch.tensor([0]), torch.tensor([0.0], dtype=torch.float64), time_step=0.25, discount=0.9)
    assert math.isnan(m.navigation_time) and math.isnan(m.discomfort_min_separation)


def test_orca_baseline_navigates_and_is_batch_size_invariant():
    cfg = CrowdConfig(scenario="circle")
    m1, traj = evaluate_policy(cfg, OrcaRobotPolicy(), num_episodes=40, batch_size=40, record_episode=3)
    m2, _ = evaluate_policy(cfg, OrcaRobotPolicy(), num_episodes=40, batch_size=16)
    assert m1 == m2
    assert m1.success_rate >= 0.6  # upstream measured 0.769 on 1000 cases
    assert 10.0 < m1.navigation_time < 20.0
    assert traj is not None and traj.robot_positions.shape[1] == 2
    assert traj.outcome in ("success", "collision", "timeout")


def test_evaluate_policy_rejects_bad_arguments():
    cfg = CrowdConfig()
    with pytest.raises(ValueError):
        evaluate_policy(cfg, OrcaRobotPolicy(), num_episodes=0)
    with pytest.raises(ValueError, match="record_episode"):
        evaluate_policy(cfg, OrcaRobotPolicy(), num_episodes=5, record_episode=9)


def test_demo_script_trains_tests_and_compares_with_orca(tmp_path, capsys):
    """`make demo`'s script end to end on the smoke budget: run folder, files, the ORCA comparison."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    import demo

    result = demo.main(["--out", str(tmp_path / "run"), "preset=smoke", "logger=csv", "train.test_episodes=6"])
    files = {p.name for p in (tmp_path / "run").iterdir()}
    assert {"learning_curves.png", "test_case0.png", "test_case0.gif", "eval.json", "demo.json", "config.yaml"} <= files
    assert result["test_cases"] == 6 and result["agent"]["episodes"] == 6 and result["orca"]["episodes"] == 6
    assert result["beats_orca"] == (result["agent"]["success_rate"] > result["orca"]["success_rate"])
    out = capsys.readouterr().out
    assert "ORCA (same cases)" in out and "ORCA on success rate" in out
