"""experiments/diagnose_timeouts.py: a checkpoint's timed-out validation episodes, described."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from crowdrl_testing import fresh_network
from crowdrl.training.config import RunConfig
from crowdrl.training.loss import D3QNLoss

ROOT = Path(__file__).resolve().parents[1]
AGENT = ROOT / "pretrained" / "sgd3qn-planning-re3-demo-s0" / "best.pt"


def _script():
    import diagnose_timeouts

    return diagnose_timeouts


def test_online_state_dict_rebuilds_the_online_network():
    torch.manual_seed(0)
    net = fresh_network(RunConfig())
    loss = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=0.9)
    with torch.no_grad():
        for p in loss.target_net.parameters():
            p.add_(1.0)  # the target differs: only the online weights may come back
    fresh = fresh_network(RunConfig())
    fresh.load_state_dict(D3QNLoss.online_state_dict(loss.state_dict()))
    for (name, a), b in zip(net.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), name


def test_describe_a_timed_out_episode_that_stops_behind_the_goal():
    """A hand-made rollout: episode 0 reaches the goal at step 2, episode 1 stands 0.7 m past the goal,
    facing away from it, until the time limit (3 steps)."""
    from tensordict import TensorDict

    B, T = 2, 3
    robot = torch.zeros(B, T, 9)
    robot[..., 4], robot[..., 7] = 0.3, 1.0
    robot[:, :, 5:7] = torch.tensor([0.0, 4.0])  # goal
    robot[0, :, 0:2] = torch.tensor([[0.0, 3.0], [0.0, 3.9], [0.0, 3.9]])
    robot[1, :, 0:2] = torch.tensor([0.0, 4.7])
    robot[1, :, 8] = math.pi / 2  # heading +y: the goal (at -y) is behind
    event = torch.tensor([[0, 1, 1], [0, 0, 3]])[..., None]
    q = torch.zeros(B, T, 81)
    q[1, -1, 0], q[1, -1, 5] = 0.40, 0.42
    ro = TensorDict({"robot": robot, "action_value": q,
                     "next": TensorDict({"robot": robot, "event": event}, [B, T])}, [B, T])
    out = _script().describe(ro)
    assert (out["episodes"], out["success"], out["collision"], out["timeout"]) == (2, 1, 0, 1)
    assert math.isclose(out["timeout_goal_distance_median"], 0.7, rel_tol=1e-5)
    assert math.isclose(out["timeout_closest_median"], 0.7, rel_tol=1e-5)
    assert out["timeout_stood_still"] == 1.0 and out["timeout_goal_behind"] == 1.0
    assert math.isclose(out["timeout_q_gap_to_stop_median"], 0.02, rel_tol=1e-4)


def test_a_pretrained_agent_is_diagnosed_with_and_without_its_planner(capsys):
    rows = _script().main([str(AGENT), "--episodes", "6", "--json"])
    assert [r["planning"] for r in rows] == [True, False]
    for r in rows:
        assert r["success"] + r["collision"] + r["timeout"] == r["episodes"] == 6
    assert json.loads(capsys.readouterr().out)["rows"] == rows
