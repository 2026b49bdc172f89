"""Metrics (SPEC §5) on hand-computed cases, and the ORCA baseline end to end."""

from __future__ import annotations

import math

import pytest
import torch

from crowdrl.exploration import make_strategy
from crowdrl.envs import CrowdNavEnv
from crowdrl.evaluation import (average_returns, discount_per_step, episode_metrics, episode_records, evaluate,
                                 evaluate_orca)
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


# The numbers of the pre-refactor evaluation loop (a second loop straight on ``sim.step``, commit
# 6dfef2c, on this development machine) for the first test cases of seed 0. The one rollout path
# must reproduce them: the rates and times exactly; the ORCA robot's return and separation to
# 1e-5, because the holonomic env clips ORCA's float32 speed overshoot (|v| > v_pref) that the old
# loop let through (with the clip disabled, all eight metrics were bit-identical on 1000 cases).
OLD_LOOP_ORCA = {
    "circle": dict(success_rate=0.7, collision_rate=0.275, timeout_rate=0.025, navigation_time=13.142857142857142,
                   average_return=0.2794836038950747, discomfort_frequency=0.10438972162740899,
                   discomfort_min_separation=0.11561820140251747),
    "square": dict(success_rate=0.775, collision_rate=0.225, timeout_rate=0.0, navigation_time=14.209677419354838,
                   average_return=0.37096755891770206, discomfort_frequency=0.09575518262586377,
                   discomfort_min_separation=0.13080209078862495),
}
# a Q network initialised from torch.manual_seed(0) (sgd3qn, egreedy), greedy on 20 circle cases
OLD_LOOP_NET = dict(success_rate=0.0, collision_rate=0.95, timeout_rate=0.05, average_return=-0.4652161536367818,
                    discomfort_frequency=0.1763157894736842, discomfort_min_separation=0.044749985435115755)


@pytest.mark.parametrize("scenario", ["circle", "square"])
def test_orca_baseline_gives_the_old_loops_numbers(scenario):
    m, traj = evaluate_orca(CrowdConfig(scenario=scenario), episodes=40, record_episode=3)
    for key, value in OLD_LOOP_ORCA[scenario].items():
        tol = 1e-5 if key in ("average_return", "discomfort_min_separation") else 0.0
        assert getattr(m, key) == pytest.approx(value, abs=tol, rel=0), key
    assert traj is not None and traj.robot_positions.shape[1] == 2
    assert traj.outcome in ("success", "collision", "timeout")


def test_orca_baseline_is_batch_size_invariant():
    m1, _ = evaluate_orca(CrowdConfig(), episodes=24, batch=24)
    m2, _ = evaluate_orca(CrowdConfig(), episodes=24, batch=10)  # 10 + 10 + 4 (6 spare sub-envs)
    assert m1 == m2


def test_trained_style_actor_gives_the_old_loops_numbers():
    """The run's actor (QValueActor + ε-greedy, deterministic) on the run's test env."""
    from crowdrl.training.config import PlanningConfig, RunConfig
    from crowdrl.training.factories import make_actor, make_env, make_exploration
    from crowdrl.training.variants import make_network

    run = RunConfig(planning=PlanningConfig(enabled=False))  # the greedy QValueActor
    torch.manual_seed(0)
    net = make_network(run, strategy=make_strategy(run.exploration))
    env = make_env(run, split="test", num_envs=20, seed=0)
    policy = make_exploration(env, make_actor(run, env, net), make_strategy(run.exploration))
    m, _ = evaluate(env, policy, num_episodes=20)
    for key, value in OLD_LOOP_NET.items():
        assert getattr(m, key) == pytest.approx(value, abs=0, rel=0), key
    m7, _ = evaluate(make_env(run, split="test", num_envs=7, seed=0), policy, num_episodes=20)
    assert m7 == m


def test_episode_records_end_each_row_at_its_first_done():
    """Hand-made rollout: row 0 ends at t=1 (success), row 1 at t=3 (timeout); later steps ignored."""
    from tensordict import TensorDict

    done = torch.tensor([[0, 1, 0, 1], [0, 0, 0, 1]], dtype=torch.bool).unsqueeze(-1)
    nxt = TensorDict({
        "done": done,
        "reward": torch.tensor([[0.1, 0.25, 9.0, 9.0], [0.0, -0.1, 0.0, 0.05]]).unsqueeze(-1),
        "event": torch.tensor([[0, SUCCESS, 0, COLLISION], [0, 0, 0, TIMEOUT]]).unsqueeze(-1),
        "discomfort_count": torch.tensor([[1, 0, 5, 5], [0, 2, 0, 0]]).unsqueeze(-1),
        "min_separation": torch.tensor([[0.1, 0.5, 0.0, 0.0], [1.0, 0.15, 1.0, 1.0]]).unsqueeze(-1),
    }, batch_size=[2, 4])
    rec = episode_records(TensorDict({"next": nxt}, batch_size=[2, 4]), max_steps=6)
    assert rec["events"].tolist() == [SUCCESS, TIMEOUT]
    assert rec["lengths"].tolist() == [2, 4]
    assert rec["rewards"].shape == (2, 6)
    assert rec["rewards"][0].tolist() == pytest.approx([0.1, 0.25, 0, 0, 0, 0])
    assert rec["discomfort_steps"].tolist() == [1, 1]
    assert rec["discomfort_separation_sum"].tolist() == pytest.approx([0.1, 0.15])


def test_evaluate_rejects_bad_arguments():
    env = CrowdNavEnv(num_envs=2, split="test", robot_kinematics="holonomic")
    policy = OrcaRobotPolicy(env.config)
    with pytest.raises(ValueError, match="num_episodes"):
        evaluate(env, policy, num_episodes=0)
    with pytest.raises(ValueError, match="record_episode"):
        evaluate(env, policy, num_episodes=5, record_episode=9)
    with pytest.raises(TypeError, match="CrowdNavEnv"):
        evaluate(object(), policy, num_episodes=1)  # type: ignore[arg-type]


def test_demo_script_trains_tests_and_compares_with_orca(tmp_path):
    """`make demo`'s script end to end on the smoke budget: run folder, files, the ORCA comparison."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "experiments" / "demo.py"
    proc = subprocess.run([sys.executable, str(script), f"out={tmp_path / 'run'}", "preset=smoke", "logger=csv",
                           "train.test_episodes=6"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    files = {p.name for p in (tmp_path / "run").iterdir()}
    assert {"learning_curves.png", "test_case0.png", "test_case0.gif", "test_case0.trajectory.json", "eval.json",
            "demo.json", "config.yaml"} <= files
    result = json.loads((tmp_path / "run" / "demo.json").read_text())
    assert result["test_cases"] == 6 and result["agent"]["episodes"] == 6 and result["orca"]["episodes"] == 6
    assert result["beats_orca"] == (result["agent"]["success_rate"] > result["orca"]["success_rate"])
    assert "ORCA (same cases)" in proc.stdout and "ORCA on success rate" in proc.stdout


def test_demo_takes_its_folder_as_one_out_key_like_the_other_commands(tmp_path):

    from crowdrl_testing.cli import run_cli

    for args in (["out="], [f"out={tmp_path / 'a'}", f"out={tmp_path / 'b'}"]):
        proc = run_cli("demo.py", *args, "preset=smoke")  # refusals, in this process
        assert proc.returncode == 2 and "out: give one run folder" in proc.stderr, proc.stderr[-2000:]
    assert not any(tmp_path.iterdir())


def test_a_run_group_parses_its_label_and_folders_and_names_what_is_wrong(tmp_path):
    from crowdrl.evaluation.report import parse_run_group

    (tmp_path / "s0").mkdir()
    (tmp_path / "s1").mkdir()
    label, runs = parse_run_group(f" ε-greedy = {tmp_path / 's0'}, {tmp_path / 's1'} ,")
    assert label == "ε-greedy" and runs == [tmp_path / "s0", tmp_path / "s1"]
    for bad in ("no-equals-sign", "=a,b", "label=", "label= , "):
        with pytest.raises(ValueError, match="LABEL=RUN"):
            parse_run_group(bad)
    with pytest.raises(ValueError, match=r"'x': .*s2 does not exist"):
        parse_run_group(f"x={tmp_path / 's0'},{tmp_path / 's2'}")
