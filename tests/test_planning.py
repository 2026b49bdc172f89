"""SG-D3QN's online planning: the crowd predictors, the planner's scores against a brute-force
look-ahead through the simulator, its batching, its config keys and its training."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from crowdrl_testing.cli import run_cli  # refusals, in this process
from crowdrl.evaluation.report import read_eval_record
from crowdrl.envs import CrowdNavEnv, robot_centric
from crowdrl.models import SGD3QNEncoder, make_q_actor, make_q_network
from crowdrl.models.predictor import ConstantVelocityPredictor, CrowdStatePredictor, predictor_loss
from crowdrl.policies import OnlinePlanner
from crowdrl.sim.crowd import observe, step
from crowdrl.sim.kinematics import action_table, decode_action
from crowdrl.training import ConfigError, validate

GAMMA = 0.9 ** 0.25


def _scene(num_envs: int = 8, seed: int = 3, steps: int = 4, num_humans: int = 10) -> CrowdNavEnv:
    """An env a few random steps into its episodes (humans moving)."""
    env = CrowdNavEnv("circle", num_envs=num_envs, num_humans=num_humans, seed=seed)
    env.rollout(steps, break_when_any_done=False)
    return env


def _net(seed: int = 0) -> nn.Module:
    torch.manual_seed(seed)
    return make_q_network("sgd3qn").eval()


# ----------------------------------------------------------------------------- predictors

def test_constant_velocity_predictor_moves_each_human_by_its_velocity():
    humans = torch.tensor([[[1.0, 2.0, 0.5, -1.0, 0.3], [0.0, 0.0, 0.0, 0.0, 0.0]]])
    mask = torch.tensor([[True, False]])
    out = ConstantVelocityPredictor(0.25)(torch.zeros(1, 9), humans, mask)
    assert torch.equal(out, torch.tensor([[[1.125, 1.75, 0.5, -1.0, 0.3], [0.0, 0.0, 0.0, 0.0, 0.0]]]))


def test_node_embeddings_row_zero_is_the_encoders_output():
    enc = SGD3QNEncoder()
    robot, humans = torch.randn(5, 9), torch.randn(5, 6, 5)
    mask = torch.rand(5, 6) > 0.3
    mask[:, 0] = True
    for m in (None, mask):
        nodes = enc.node_embeddings(robot, humans, m)
        assert nodes.shape == (5, 7, 32)
        torch.testing.assert_close(nodes[:, 0], enc(robot, humans, m), rtol=0, atol=1e-6)
    assert torch.all(enc.node_embeddings(robot, humans, mask)[:, 1:][~mask] == 0)


def _transitions(num_envs: int = 16, steps: int = 6):
    env = CrowdNavEnv("circle", num_envs=num_envs, seed=5)
    r = env.rollout(steps, break_when_any_done=False).reshape(-1)
    return r["robot"], r["humans"], r["humans_mask"], r["next", "humans"]


def test_learned_predictor_loss_falls_on_a_fixed_batch():
    torch.manual_seed(0)
    robot, humans, mask, next_humans = _transitions()
    predictor = CrowdStatePredictor()
    opt = torch.optim.Adam(predictor.parameters(), lr=1e-3)
    losses = []
    for _ in range(60):
        opt.zero_grad()
        loss = predictor_loss(predictor, robot, humans, next_humans, mask)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0], losses[::10]


def test_the_predictor_loss_ignores_absent_humans():
    robot, humans, mask, next_humans = _transitions(4, 2)
    mask = mask.clone()
    mask[:, -3:] = False
    predictor = CrowdStatePredictor()
    garbage = next_humans.clone()
    garbage[:, -3:] = 1e3
    assert predictor_loss(predictor, robot, humans, garbage, mask) == predictor_loss(predictor, robot, humans,
                                                                                      next_humans, mask)


def test_the_predictor_update_compiled_and_functional_equal_autograd(monkeypatch):
    """PredictorLoss: the functional gradients (what compiles) equal loss.backward() with and
    without a mask, and the compiled step gives the same loss and gradients in one graph."""
    import crowdrl.models.sgd3qn as sgd3qn
    from crowdrl.training.predictor_loss import PredictorLoss

    monkeypatch.setattr(sgd3qn, "PAIRWISE", sgd3qn.PairwiseKernels("eager"))  # traced by the outer graph anyway
    torch.manual_seed(0)
    robot, humans, mask, next_humans = _transitions()
    mask = mask.clone()
    mask[::2, -2:] = False
    predictor = CrowdStatePredictor()
    eager = PredictorLoss(predictor)

    def backward_grads(m):
        loss = eager.loss_and_grad(robot, humans, next_humans, m)
        return loss, {k: p.grad.clone() for k, p in predictor.named_parameters()}

    for m in (None, mask):
        ref_loss, ref = backward_grads(m)
        params = {k: v.detach() for k, v in predictor.named_parameters()}
        grads, loss = eager.gradients(params, robot, humans, next_humans, m)
        torch.testing.assert_close(loss, ref_loss, rtol=1e-6, atol=1e-7)
        # every parameter learns but the attention logits' output biases (softmax ignores a shift) and
        # the robot's embedding (human nodes do not attend the robot: humans do not see it)
        assert set(grads) == set(ref)
        zero = {k for k in ref if float(ref[k].abs().max()) == 0}
        assert zero <= {"graph.gat0.w_a.2.bias", "graph.gat1.w_a.2.bias"} | {k for k in ref if k.startswith("graph.w_r.")}
        for k in ref:
            torch.testing.assert_close(grads[k], ref[k], rtol=1e-5, atol=1e-7)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    compiled = PredictorLoss(predictor, compile=True)
    for _ in range(2):
        ref_loss, ref = backward_grads(None)
        loss = compiled.loss_and_grad(robot, humans, next_humans)
        torch.testing.assert_close(loss, ref_loss, rtol=1e-5, atol=1e-6)
        for k, p in predictor.named_parameters():
            torch.testing.assert_close(p.grad, ref[k], rtol=1e-4, atol=1e-6)
    counters = torch._dynamo.utils.counters
    assert counters["stats"]["unique_graphs"] == 1 and not counters["graph_break"], dict(counters["graph_break"])


# ----------------------------------------------------------------------------- the planner

class PerfectPredictor(nn.Module):
    """The simulator's own next human states for one known batch of states."""

    def __init__(self, humans: Tensor, next_humans: Tensor) -> None:
        super().__init__()
        self.humans, self.next_humans = humans, next_humans
        self.calls = 0

    def forward(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        assert torch.equal(humans, self.humans), "depth 1 predicts from the root states only"
        self.calls += 1
        return self.next_humans


def _crowded(env: CrowdNavEnv) -> None:
    """Put a human 0.75 m ahead of each robot, walking at it: some candidate actions collide."""
    s = env.state
    ahead = torch.stack((torch.cos(s.robot_heading), torch.sin(s.robot_heading)), -1)
    pos, vel = s.human_position.clone(), s.human_velocity.clone()
    pos[:, 0] = s.robot_position + 0.75 * ahead
    vel[:, 0] = -0.8 * ahead
    env.state = s.replace(human_position=pos, human_velocity=vel)


def test_scores_equal_a_brute_force_look_ahead_through_the_simulator():
    """With the simulator's next human states as the prediction, every candidate's score is
    ½(r + γ̄·(1 − terminated)·max Q(s′) + Q(s, a)) with r, terminated and s′ from sim.step itself."""
    env = _scene(num_envs=6)
    _crowded(env)
    cfg, state = env.config, env.state
    robot, humans = observe(cfg, state)
    next_state, _ = step(cfg, state, torch.zeros(6, 2), state.robot_heading)  # humans ignore the robot
    _, next_humans = observe(cfg, next_state)
    net = _net()
    oracle = PerfectPredictor(humans, next_humans)
    planner = OnlinePlanner(net, oracle, cfg, gamma=GAMMA, depth=1, width=10)
    plan = planner.plan(robot, humans, state.human_mask)
    assert oracle.calls == 1

    with torch.no_grad():
        q = net(*robot_centric(robot, humans))
        assert torch.equal(plan.candidates, q.topk(10, dim=-1).indices)
        table, collided = action_table(), 0
        for b in range(6):
            one = state.index(slice(b, b + 1))
            for j in range(10):
                a = plan.candidates[b, j : j + 1]
                velocity, heading = decode_action("unicycle", a, one.robot_heading, table)
                after, res = step(cfg, one, velocity, heading)
                q_next = net(*robot_centric(*observe(cfg, after))).amax(-1)
                want = 0.5 * (res.reward + GAMMA * torch.where(res.terminated, 0.0, q_next) + q[b, a])
                torch.testing.assert_close(plan.scores[b, j], want[0], rtol=0, atol=2e-5)
                collided += int(res.event[0] == 2)
    assert collided > 0, "the scene should make some candidates collide (the no-bootstrap branch)"
    assert torch.equal(plan.action, plan.candidates.gather(-1, plan.scores.argmax(-1, keepdim=True)).squeeze(-1))


def test_width_one_depth_one_is_the_greedy_q_actor():
    env = _scene(num_envs=32)
    td = env.reset()
    td.update(dict(zip(("robot_rc", "humans_rc"), robot_centric(td["robot"], td["humans"]))))
    net = _net()
    greedy = make_q_actor("sgd3qn", env.action_spec, in_keys=("robot_rc", "humans_rc"), net=net)
    planner = OnlinePlanner(net, CrowdStatePredictor(), env.config, gamma=GAMMA, depth=1, width=1)
    with torch.no_grad():
        want = greedy(td.clone())["action"]
    got = planner(td.clone())
    assert torch.equal(got["action"], want)
    assert got["action"].shape == want.shape and got["action"].dtype == want.dtype


@pytest.mark.parametrize("predictor", ["learned", "const_vel"])
@pytest.mark.parametrize("depth,width", [(1, 10), (2, 3)])
def test_the_plan_of_a_state_does_not_depend_on_the_batch(predictor, depth, width):
    env = _scene(num_envs=24)
    cfg = env.config
    robot, humans = observe(cfg, env.state)
    mask = env.state.human_mask
    torch.manual_seed(1)
    pred = CrowdStatePredictor() if predictor == "learned" else ConstantVelocityPredictor(cfg.time_step)
    planner = OnlinePlanner(_net(), pred, cfg, gamma=GAMMA, depth=depth, width=width)
    full = planner.plan(robot, humans, mask)
    part = planner.plan(robot[5:11], humans[5:11], mask[5:11])
    one = planner.plan(robot[7], humans[7], mask[7])  # no batch dim at all
    assert torch.equal(full.action[5:11], part.action)
    assert torch.equal(full.candidates[5:11], part.candidates)
    torch.testing.assert_close(full.scores[5:11], part.scores, rtol=0, atol=1e-6)
    assert one.action.shape == () and int(one.action) == int(full.action[7])


def test_deeper_planning_runs_through_the_one_rollout_path():
    from crowdrl.evaluation import evaluate

    env = CrowdNavEnv("circle", num_envs=4, split="test", num_humans=4)
    planner = OnlinePlanner(_net(), ConstantVelocityPredictor(0.25), env.config, gamma=GAMMA, depth=2, width=4)
    metrics, _ = evaluate(env, planner, num_episodes=4)
    assert metrics.episodes == 4


def test_the_planner_refuses_bad_arguments():
    cfg = CrowdNavEnv("circle").config
    for kwargs in ({"depth": 0}, {"width": 0}, {"width": 82}, {"gamma": 0.0}):
        with pytest.raises(ValueError):
            OnlinePlanner(_net(), ConstantVelocityPredictor(0.25), cfg, **{"gamma": GAMMA, **kwargs})


# ----------------------------------------------------------------------------- config and training

@pytest.mark.parametrize("key,value,message", [("depth", 0, "planning.depth"), ("width", 0, "planning.width"),
                                               ("width", 82, "planning.width"),
                                               ("predictor", "oracle", "planning.predictor"),
                                               ("lr", -1.0, "planning.lr")])
def test_bad_planning_values_are_refused_naming_the_key(key, value, message):
    with pytest.raises(ConfigError, match=message):
        validate({"planning": {"enabled": True, key: value}})


def test_planning_off_leaves_the_fingerprint_of_a_run_without_it():
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.compat import stored_config
    from crowdrl.training.config import to_dict

    assert validate({}).planning.enabled is True  # the default, as upstream (one set of defaults)
    run = validate({"planning": {"enabled": False}})
    assert validate(stored_config({}), resources=False).planning.enabled is False  # a stored config without the key
    cfg = to_dict(run)
    without = {k: v for k, v in cfg.items() if k != "planning"}  # a checkpoint written before the key existed
    assert config_fingerprint(cfg) == config_fingerprint(without)
    assert config_fingerprint(to_dict(validate({"planning": {"enabled": True}}))) != config_fingerprint(cfg)


EXACT = {"logger": {"name": "csv", "progress_bar": False, "render": False}, "preset": "smoke",
         "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 288, "buffer_size": 1000, "batch_size": 16,
                   "warmup_frames": 32, "updates_per_frame": 0.25, "target_update_frames": 64, "val_every_frames": 96,
                   "val_episodes": 4, "checkpoint_every_frames": 64, "test_episodes": 4, "save_buffer": True,
                   "compile_loss": False},
         "exploration": {"anneal_frames": 288}, "env": {"num_humans": 4},
         "planning": {"enabled": True, "width": 5}}


def test_the_td_target_is_the_plain_double_dqn_target():
    """The planner selects actions only: the loss of a sampled batch does not change when the
    predictor (hence every plan) changes."""
    from crowdrl.training.acting import make_acting
    from crowdrl.training.facts import RunFacts
    from crowdrl.training.trainer import Trainer

    trainer = Trainer(validate(EXACT), Path("/nonexistent-never-written"))
    trainer.buffer.extend(trainer.env.rollout(8, trainer.policy, break_when_any_done=False)
                          .select(*trainer.stored_keys))
    sample = trainer.buffer.sample()
    for key in ("robot", "humans", ("next", "humans")):
        assert key in sample.keys(True), f"the buffer must keep {key} for the predictor"
    # a fixed crowd: no mask, for the predictor as for the planner acting; a varying one keeps it
    assert "humans_mask" not in sample.keys()
    varying = validate({**EXACT, "env": {"num_humans": 4, "min_humans": 3}})
    facts = RunFacts.of(varying)
    assert "humans_mask" in facts.replay_keys(make_acting(varying.planning, facts, train=varying.train,
                                                          encoder=varying.encoder.name, learn=True))
    before = trainer.learner.loss(sample)["loss"]
    with torch.no_grad():
        for p in trainer.predictor.parameters():
            p.add_(torch.randn_like(p))
    assert torch.equal(trainer.learner.loss(sample)["loss"], before)


def test_a_killed_planning_run_resumed_is_bit_identical_and_tests_with_the_planner(tmp_path):
    """Killed mid-update at frame 224, resumed: the same Q weights, predictor weights and
    optimizer states, test metrics and logged rows as the run never stopped; best.pt carries the
    predictor and the test goes through the planner."""
    from crowdrl_testing import train_until_killed
    from crowdrl.training.checkpoint import load_checkpoint
    from crowdrl.agents import evaluate_spec
    from crowdrl.training.pipeline import run_training

    run = validate(EXACT)
    run_training(run, tmp_path / "ref")
    train_until_killed(run, tmp_path / "run", frame=224)
    run_training(run, tmp_path / "run")

    ref, got = (load_checkpoint(tmp_path / d / "checkpoints" / "last.pt") for d in ("ref", "run"))
    for part in ("loss", "predictor"):
        assert ref[part].keys() == got[part].keys()
        assert all(torch.equal(ref[part][k], got[part][k]) for k in ref[part]), part
    assert ref["predictor_optimizer"]["state"].keys() == got["predictor_optimizer"]["state"].keys()
    rows = [[{k: v for k, v in json.loads(line).items() if not k.startswith("time/")}
             for line in (tmp_path / d / "scalars.jsonl").read_text().splitlines()] for d in ("ref", "run")]
    assert rows[0] == rows[1]
    assert any("train/predictor_loss" in r for r in rows[0])
    eval_ref = read_eval_record(tmp_path / "ref" / "eval.json")
    assert eval_ref == read_eval_record(tmp_path / "run" / "eval.json")

    best = load_checkpoint(tmp_path / "ref" / "checkpoints" / "best.pt")
    assert "predictor" in best
    record, _ = evaluate_spec(checkpoint=tmp_path / "ref", episodes=4)
    assert record["policy"].endswith("+planning")
    assert record["success_rate"] == eval_ref["success_rate"]  # the same planner as the run's own test


@pytest.mark.slow  # ~30 s (two train.py processes); make test-slow
def test_a_smoke_training_with_planning_through_hydra(tmp_path):
    """train.py with planning on (preset=smoke, const_vel predictor): it trains and tests."""
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root / "src")}
    proc = subprocess.run([sys.executable, str(root / "experiments" / "train.py"), "preset=smoke", "logger=csv",
                           "logger.render=false", "planning.enabled=true", "planning.predictor=const_vel",
                           "planning.depth=2", "planning.width=3", f"hydra.run.dir={tmp_path / 'run'}"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((tmp_path / "run" / "status.json").read_text())["state"] == "completed"
    bad = run_cli("train.py", "preset=smoke", "planning.width=100", f"hydra.run.dir={tmp_path / 'bad'}")
    assert bad.returncode == 2 and "planning.width" in bad.stderr


def test_planning_is_an_axis_of_reproduce(tmp_path):
    """reproduce.py planning=true: a folder of runs without planning is refused (the manifest
    records planning), and a non-boolean value is named (refusals: in this process)."""
    import json

    cmd = ["reproduce.py", "budget=smoke", "variants=[egreedy]", "seeds=[0]", "episodes=4"]
    bad = run_cli(*cmd, "planning=maybe", f"out={tmp_path / 'a'}")
    assert bad.returncode == 2 and bad.stderr.strip().startswith("reproduce.py: planning"), bad.stderr[-800:]
    out = tmp_path / "b"
    out.mkdir()
    import crowdrl

    plain = {"format": 1, "crowdrl_version": crowdrl.__version__, "budget": "smoke", "train_scenario": "circle",
             "episodes": 4}
    (out / "manifest.json").write_text(json.dumps(plain))
    mixed = run_cli(*cmd, "planning=true", f"out={out}")
    assert mixed.returncode == 2 and "planning" in mixed.stderr and "other settings" in mixed.stderr, mixed.stderr[-800:]
    # planning is reproduce.py's default, so the plain folder is refused without the key too, and
    # a planning folder is refused to a plain run (the key is compared whichever way it is missing)
    default = run_cli(*cmd, f"out={out}")
    assert default.returncode == 2 and "planning: folder False vs now True" in default.stderr, default.stderr[-800:]
    (out / "manifest.json").write_text(json.dumps({**plain, "planning": True}))
    plain_run = run_cli(*cmd, "planning=false", f"out={out}")
    assert plain_run.returncode == 2 and "planning: folder True vs now False" in plain_run.stderr, \
        plain_run.stderr[-800:]
