"""Learning pipeline: n-step targets, config validation, checkpoints, resume, Hydra runs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import DQNLoss

from crowdrl_testing import fresh_network
from crowdrl_testing.cli import run_cli  # refusals, in this process
from crowdrl.evaluation.report import read_eval_record
from crowdrl.models import make_q_actor
from crowdrl.training import CheckpointError, ConfigError, NStepReturn, load_checkpoint, nstep_transitions, validate
from crowdrl.training.checkpoint import save_checkpoint
from crowdrl.training.loss import D3QNLoss
from crowdrl.training.config import RunConfig

ROOT = Path(__file__).resolve().parents[1]
TRAIN = [sys.executable, str(ROOT / "experiments" / "train.py")]


def _toy_batch():
    """One env, 6 steps: a collision (terminated) at t=2 and a timeout (truncated) at t=4."""
    T = 6
    r = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    term = torch.tensor([[0, 0, 1, 0, 0, 0]]).bool()
    trunc = torch.tensor([[0, 0, 0, 0, 1, 0]]).bool()
    obs = torch.arange(T, dtype=torch.float32).view(1, T, 1)
    return TensorDict({
        "obs": obs, "action": torch.zeros(1, T, dtype=torch.long),
        "next": {"obs": obs + 0.5, "reward": r.unsqueeze(-1), "terminated": term.unsqueeze(-1),
                 "truncated": trunc.unsqueeze(-1), "done": (term | trunc).unsqueeze(-1)},
    }, [1, T])


def test_nstep_never_bootstraps_through_a_termination():
    g = 0.5
    out = nstep_transitions(_toy_batch(), 3, g, ["obs"])
    # hand-computed: t=0 sees 1, 2, 3 and the collision; t=3 sees 4, 5 and the timeout (bootstraps)
    assert out["next", "reward"].view(-1).tolist() == [1 + g * 2 + g * g * 3, 2 + g * 3, 3, 4 + g * 5, 5, 6]
    assert out["steps_to_next_obs"].view(-1).tolist() == [3, 2, 1, 2, 1, 1]
    assert out["next", "terminated"].view(-1).tolist() == [True, True, True, False, False, False]
    assert out["next", "obs"].view(-1).tolist() == [2.5, 2.5, 2.5, 4.5, 4.5, 5.5]


def _nstep_rollout(g: float):
    from crowdrl.envs import CrowdNavEnv, RobotCentric
    from torchrl.envs import TransformedEnv

    torch.manual_seed(0)
    env = TransformedEnv(CrowdNavEnv("circle", num_envs=1, num_humans=3), RobotCentric())
    actor = make_q_actor("sgd3qn", env.base_env.action_spec)
    roll = env.rollout(4, break_when_any_done=False)  # [1, 4]
    roll["next", "reward"] = torch.tensor([[[1.0], [2.0], [3.0], [4.0]]])
    roll["next", "terminated"] = torch.tensor([[[False], [True], [False], [False]]])
    roll["next", "done"] = roll["next", "terminated"].clone()
    keys = ["robot_rc", "humans_rc"]
    trans = nstep_transitions(roll.select(*keys, "action", *[("next", k) for k in (*keys, "reward", "done", "terminated")]),
                              3, g, keys).reshape(-1)
    return env, actor, trans


def test_nstep_target_in_d3qn_loss_matches_hand_computation():
    """The full D3QN target of an n-step transition: r_n + γ^m (1 - terminated) Q_target(s', argmax Q(s'))."""
    g = 0.9
    _, actor, trans = _nstep_rollout(g)
    net = actor.module[0].module
    loss = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=g)
    with torch.no_grad():
        for p in loss.target_net.parameters():
            p.add_(0.01 * torch.randn_like(p))  # a target network that differs from the online one
        q_next_online = net(trans["next", "robot_rc"], trans["next", "humans_rc"])
        q_next_target = loss.target_net(trans["next", "robot_rc"], trans["next", "humans_rc"])
        q_now = net(trans["robot_rc"], trans["humans_rc"]).gather(-1, trans["action"].view(-1, 1)).squeeze(-1)
    boot = q_next_target.gather(-1, q_next_online.argmax(-1, keepdim=True)).squeeze(-1)
    # t=0: 1 + .9*2, collision at t=1 -> no bootstrap; t=2: 3 + .9*4, then bootstrap with .9^2
    expected_target = torch.tensor([1 + g * 2, 2.0, 3 + g * 4 + g ** 2 * boot[2], 4 + g * boot[3]])
    expected = ((q_now - expected_target) ** 2).mean()
    got = loss(trans)["loss"]
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    loss.update_target()
    for a, b in zip(loss.target_net.parameters(), net.parameters()):
        assert torch.equal(a, b)


def _assert_same_loss_and_grads(losses, net, trans, rtol: float, atol: float, grad_rtol: float) -> None:
    """Both losses give the same value on ``trans`` and the same gradients on ``net``'s parameters."""
    results = []
    for loss in losses:
        net.zero_grad()
        value = loss(trans.clone())["loss"]
        value.backward()
        results.append((value.detach(), [p.grad.clone() for p in net.parameters()]))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=rtol, atol=atol)
    for a, b in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(a, b, rtol=grad_rtol, atol=atol)


def test_d3qn_loss_equals_torchrl_double_dqn_loss():
    """Our loss is torchrl's DQNLoss(double, delayed, l2) with n-step discounts: same value and gradients."""
    g = 0.9
    env, actor, trans = _nstep_rollout(g)
    net = actor.module[0].module
    ref = DQNLoss(actor, delay_value=True, double_dqn=True, loss_function="l2", action_space=env.base_env.action_spec)
    ref.make_value_estimator(gamma=g)
    ours = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=g)
    with torch.no_grad():  # the same perturbed target network in both
        for p_ref, p_ours in zip(ref.target_value_network_params.values(True, True), ours.target_net.parameters()):
            p_ref.add_(0.01 * torch.randn_like(p_ref))
            p_ours.copy_(p_ref)
    _assert_same_loss_and_grads((ref, ours), net, trans, rtol=1e-6, atol=1e-7, grad_rtol=1e-5)


@pytest.mark.parametrize("head", ["plain", "noisy", "dropout"])
def test_compiled_update_equals_eager_and_compiles_once(head, monkeypatch):
    """``compile=True`` (target, forwards and backward as one compiled graph) gives the eager
    loss and gradients for every head variant, and a changing dropout p or fresh noise between
    batches neither breaks the graph nor recompiles it."""
    import crowdrl.models.sgd3qn as sgd3qn
    from crowdrl.exploration.dropout import add_action_dropout, set_dropout_p
    from crowdrl.exploration.noisy import noisify_head, reset_noise
    from crowdrl.models import make_q_network

    monkeypatch.setattr(sgd3qn, "PAIRWISE", sgd3qn.PairwiseKernels("eager"))  # traced by the outer graph anyway
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    g = 0.9
    _, _, trans = _nstep_rollout(g)
    torch.manual_seed(1)
    net = make_q_network("sgd3qn")
    if head == "noisy":
        noisify_head(net.head, 0.5)
    if head == "dropout":
        add_action_dropout(net.head, 0.5)
    eager = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=g)
    compiled = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=g, compile=True)
    with torch.no_grad():
        for p in eager.target_net.parameters():
            p.add_(0.01 * torch.randn_like(p))  # a target network that differs from the online one
    compiled.target_net.load_state_dict(eager.target_net.state_dict())
    counters = torch._dynamo.utils.counters
    for step in range(3):
        if head == "noisy":
            reset_noise(net)
            reset_noise(eager.target_net)
            compiled.target_net.load_state_dict(eager.target_net.state_dict())
        if head == "dropout":
            set_dropout_p(net, 0.5 - 0.1 * step)
        results = []
        for loss in (eager, compiled):
            out = loss.loss_and_grad(trans.clone())
            results.append((out, [p.grad.clone() for p in net.parameters()]))
        (ref, ref_grads), (got, got_grads) = results
        for key in ("loss", "q_mean", "td_error_abs"):
            torch.testing.assert_close(got[key], ref[key], rtol=1e-5, atol=1e-6)
        for a, b in zip(got_grads, ref_grads):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
        if step == 0:
            graphs = counters["stats"]["unique_graphs"]
    assert graphs == 1 and counters["stats"]["unique_graphs"] == 1, dict(counters["stats"])
    assert not counters["graph_break"], dict(counters["graph_break"])


def test_functional_gradients_equal_autograd_backward():
    """The function the compiled update compiles (``torch.func.grad_and_value`` of the objective,
    through the pairwise kernels' custom autograd function) gives ``loss.backward()``'s gradients
    when run eagerly: the compiled path's eager fallback is the same update."""
    g = 0.9
    _, actor, trans = _nstep_rollout(g)
    net = actor.module[0].module
    loss = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=g)
    ref = loss.loss_and_grad(trans)
    ref_grads = {k: p.grad.clone() for k, p in net.named_parameters()}
    b = loss.batch(trans, 81)
    grads, value, (q_mean, td_abs) = loss.gradients({k: v.detach() for k, v in loss.online_params().items()},
                                                    loss.target_params(), b)
    torch.testing.assert_close(value, ref["loss"], rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(q_mean, ref["q_mean"], rtol=1e-6, atol=1e-7)
    assert grads.keys() == ref_grads.keys()
    for k in grads:
        torch.testing.assert_close(grads[k], ref_grads[k], rtol=1e-5, atol=1e-7)


def test_d3qn_loss_rejects_out_of_range_actions():
    g = 0.9
    _, actor, trans = _nstep_rollout(g)
    loss = D3QNLoss(actor.module[0].module, ["robot_rc", "humans_rc"], gamma=g)
    trans["action"][0] = 81
    with pytest.raises(ValueError, match="actions must lie in 0..80"):
        loss(trans)
    with pytest.raises(KeyError, match="humans_rc"):
        loss(trans.exclude("humans_rc"))


def test_nstep_transform_flattens_into_the_buffer():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4, transform=NStepReturn(2, 0.5, ["obs"]))
    rb.extend(_toy_batch())
    assert len(rb) == 6
    assert set(rb.sample()["steps_to_next_obs"].view(-1).tolist()) <= {1, 2}


def test_nstep_rejects_bad_n():
    with pytest.raises(ValueError, match="n-step"):
        NStepReturn(0, 0.9, ["obs"])


# --------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    "override, word",
    [
        ({"encoder": {"name": "transformer"}}, "encoder.name"),
        ({"exploration": {"name": "boltzmann"}}, "exploration.name"),
        ({"env": {"scenario": "maze"}}, "env.scenario"),
        ({"env": {"num_humans": 0}}, "env.num_humans"),
        ({"train": {"total_frames": 0}}, "train.total_frames"),
        ({"train": {"total_frames": -5}}, "train.total_frames"),
        ({"train": {"n_step": 0}}, "train.n_step"),
        ({"train": {"batch_size": 500, "buffer_size": 100}}, "train.batch_size"),
        ({"train": {"lerning_rate": 0.1}}, "lerning_rate"),
        ({"train": {"lr": "fast"}}, "lr"),
        ({"logger": {"mode": "cloud"}}, "logger.mode"),
    ],
)
def test_bad_config_fails_naming_the_key(override, word):
    with pytest.raises(ConfigError, match=word.replace(".", r"\.")):
        validate(override)


def test_unknown_encoder_lists_the_allowed_ones():
    with pytest.raises(ConfigError, match=r"encoder\.name: .*allowed: lstm_rl, mp_rgl, sarl, sgd3qn"):
        validate({"encoder": {"name": "nope"}})


def test_default_config_is_valid():
    run = validate({})
    assert isinstance(run, RunConfig) and run.train.gamma == pytest.approx(0.974, abs=1e-3)


# --------------------------------------------------------------------------- checkpoints
def test_truncated_or_foreign_checkpoint_is_rejected(tmp_path):
    path = tmp_path / "c.pt"
    save_checkpoint(path, {"x": 1}, "abc")
    assert load_checkpoint(path, "abc")["x"] == 1
    with pytest.raises(CheckpointError, match="another configuration"):
        load_checkpoint(path, "def")
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")


# --------------------------------------------------------------------------- end to end (Hydra)
def _env():
    return {**os.environ, "WANDB_MODE": "offline", "PYTHONPATH": str(ROOT / "src")}


def _rows(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "scalars.jsonl").read_text().splitlines()]


SMOKE = ["preset=smoke", "logger=csv", "logger.render=false", "train.total_frames=512", "train.checkpoint_every_frames=64",
         "train.save_buffer=true"]


@pytest.mark.slow  # ~1 min; the fast suite kills and resumes runs through reproduce.py (tests/test_reproduce.py)
def test_killed_run_resumes_with_same_counters_and_no_lost_rows(tmp_path):
    ref_dir, run_dir = tmp_path / "ref", tmp_path / "run"
    subprocess.run(TRAIN + SMOKE + [f"hydra.run.dir={ref_dir}"], check=True, env=_env(), capture_output=True,
                   timeout=300)
    proc = subprocess.Popen(TRAIN + SMOKE + [f"hydra.run.dir={run_dir}"], env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = run_dir / "checkpoints" / "last.pt"
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if ckpt.exists() and load_checkpoint(ckpt)["counters"]["frames"] >= 192:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed; make it longer"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    stored = load_checkpoint(ckpt)["counters"]
    killed_at = stored["frames"]
    before = [r for r in _rows(run_dir) if r["frames"] <= killed_at]
    assert json.loads((run_dir / "status.json").read_text())["state"] == "running"

    subprocess.run(TRAIN + SMOKE + [f"resume={run_dir}", f"hydra.run.dir={tmp_path / 'scratch'}"], check=True,
                   env=_env(), capture_output=True, timeout=300)
    status = json.loads((run_dir / "status.json").read_text())
    ref = json.loads((ref_dir / "status.json").read_text())
    assert status["state"] == "completed"
    assert (status["frames"], status["updates"]) == (ref["frames"], ref["updates"]) == (512, status["updates"])
    weights, ref_weights = (load_checkpoint(d / "checkpoints" / "last.pt")["loss"] for d in (run_dir, ref_dir))
    assert all(torch.equal(weights[k], ref_weights[k]) for k in ref_weights), "with its buffer, resume is exact"
    metrics = [read_eval_record(d / "eval.json") for d in (run_dir, ref_dir)]
    assert metrics[0] == metrics[1]
    after = _rows(run_dir)
    assert after[: len(before)] == before, "rows written before the kill must survive unchanged"
    frames = [r["frames"] for r in after if r["kind"] == "val"]
    assert frames == sorted(set(frames)), "no duplicated validation rows after the resume"
    assert not (tmp_path / "scratch").exists(), "a resume must not leave an empty run folder behind"
    # the timers count the whole run: the seconds before the kill (kept in the checkpoint) and after it
    assert stored["update_s"] > 0 and stored["collect_s"] > 0
    assert status["timers_s"]["update"] > stored["update_s"] and status["timers_s"]["collect"] > stored["collect_s"]
    resumed = [r for r in after if r["kind"] == "train" and r["frames"] > killed_at]
    assert resumed and all(r["time/update_s"] > stored["update_s"] for r in resumed)


def test_bad_config_exits_with_a_message_and_leaves_no_run_folder(tmp_path):
    out = tmp_path / "bad"
    proc = run_cli("train.py", "preset=smoke", "encoder.name=transformer", f"hydra.run.dir={out}")
    assert proc.returncode == 2
    assert "encoder.name" in proc.stderr and "sgd3qn" in proc.stderr
    assert not out.exists()


def test_bench_train_reports_rates_and_ratios():
    """`experiments/bench_train.py` runs on a tiny budget and reports consistent figures (its --json)."""
    proc = run_cli("bench_train.py", "--updates", "2", "--batches", "1", "--num-envs", "4", "--warmup-frames", "128",
                   "--loss", "eager", "--lidar", "off", "conv", "--lidar-rays", "24", "--json")  # in this process
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["meta"]["num_envs"] == 4
    first, second = out["rows"]
    for r in (first, second):
        assert r["loss"] == "eager" and r["collect_frames_per_s"] > 0 and r["update_ms"] > 0
        assert r["update_ms"] == pytest.approx(sum(r["update_breakdown_ms"].values()))
        assert r["paper_budget_hours"] > 500_000 * r["update_ms"] / 1e3 / 3600
    assert (first["lidar"], second["lidar"], out["meta"]["lidar_rays"]) == ("off", "conv", 24)
    assert second["matmul_mflop_per_update"] > first["matmul_mflop_per_update"]  # the scan's network adds work
    assert first["update_cost_vs_first"] == 1.0
    assert second["update_cost_vs_first"] == pytest.approx(second["update_ms"] / first["update_ms"])
    # matmul MACs per sample, by hand from the architecture (N = 10 humans, 11 nodes):
    # w_r 9*64+64*32, w_h 10*(5*64+64*32), gat0 rows+cols 2*11*32*64 and A@H 11*11*32, gat1 robot
    # row 32*64, cols 11*32*64 and A@H 11*32, head 32*128+3*128*128+128*1+128*81
    macs = 2624 + 23680 + 2 * 22528 + 3872 + 2048 + 22528 + 352 + 63744
    forward = 2 * macs * 100  # FLOP per pass at batch 100
    backward = 2 * forward - 2 * 100 * (9 * 64 + 10 * 5 * 64)  # no gradient w.r.t. the observations
    assert first["matmul_mflop_per_update"] == pytest.approx((3 * forward + backward) / 1e6)
    assert first["matmul_gflop_per_s"] == pytest.approx(first["matmul_mflop_per_update"] / first["update_ms"])


def test_compiled_acting_equals_eager_and_shares_the_parameters():
    """``train.compile_acting``: the same actions and Q to float rounding as the eager actor, from
    the network's live parameters (an in-place update reaches the compiled actor) and its live
    noise (a noisy head, resampled between calls). With planning, so that the Q network runs at
    two batch shapes (the states and the look-ahead candidates)."""
    from crowdrl.exploration.noisy import reset_noise
    from crowdrl.training import factories
    from crowdrl.training.acting import make_predictor_of
    from crowdrl.training.facts import RunFacts

    torch.manual_seed(0)
    runs = {c: validate({"train": {"num_envs": 4, "compile_acting": c}, "exploration": {"name": "noisy"},
                         "planning": {"enabled": True, "predictor": "const_vel"}}) for c in (False, True)}
    env = factories.make_env(runs[False])
    net = fresh_network(runs[False], 81)
    predictor = make_predictor_of(runs[False].planning, RunFacts.of(runs[False]))
    actors = {c: factories.make_actor(run, env, net, predictor) for c, run in runs.items()}
    td = env.reset()
    with torch.no_grad():
        for _ in range(2):
            out = {c: actor(td.clone()) for c, actor in actors.items()}
            torch.testing.assert_close(out[True]["action_value"], out[False]["action_value"], rtol=1e-5, atol=1e-6)
            assert torch.equal(out[True]["action"], out[False]["action"])
            for p in net.parameters():  # a training step in place: the compiled actor must see it
                p.add_(0.05 * torch.randn_like(p))
            reset_noise(net)  # and fresh noise
    assert not torch.equal(out[True]["action_value"], actors[True](td.clone())["action_value"])


def test_compiled_module_draws_dropout_from_torchs_generator():
    from crowdrl.compile import CompiledModule

    net = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.Dropout(0.5), torch.nn.Linear(16, 3)).train()
    fast, x = CompiledModule(net, what="a dropout net"), torch.randn(8, 5)
    torch.manual_seed(1)
    eager = [net(x) for _ in range(3)]
    torch.manual_seed(1)
    compiled = [fast(x) for _ in range(3)]
    for a, b in zip(compiled, eager):
        torch.testing.assert_close(a, b)
    assert not torch.equal(eager[0], eager[1])  # dropout is on: the draws differ from call to call
