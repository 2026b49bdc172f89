"""Counterfactual experience: exact against the env, its update arrangements, its config keys."""

from __future__ import annotations

import json
import math

import pytest
import torch
from torchrl.envs import TransformedEnv

from crowdrl.envs import CrowdNavEnv, RobotCentric
from crowdrl.models.qnet import make_q_network
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import COLLISION, SUCCESS
from crowdrl.training import ConfigError, validate
from crowdrl.training.checkpoint import config_fingerprint
from crowdrl.training.config import to_dict
from crowdrl.training.counterfactual import CounterfactualExperience
from crowdrl.training.facts import obs_keys
from crowdrl.training.loss import WEIGHT_KEY, D3QNLoss

CASES = [  # scenario, crowd, steps: fixed and variable crowds, open space and walls (circle's robots, heading
    # straight through the centre, all meet a human there: its steps end in collisions, the others' in goals too)
    ("circle", {"num_humans": 5}, 60),
    ("square", {"num_humans": 4, "min_humans": 1}, 60),
    ("corridor", {"num_humans": 4}, 60),
    ("circle", {"num_humans": 4, "human_model": "social_force"}, 60),  # any humans that ignore the robot
    # a mixed crowd: the restored env keeps each human's model
    ("square", {"num_humans": 5, "min_humans": 2, "human_model": "mixed", "social_force_share": 0.4,
                "linear_share": 0.3}, 60),
    # a network that reads the lidar scan (encoder.lidar): the scan from the new pose, walls and a varying crowd
    ("corridor", {"num_humans": 4, "lidar_rays": 36}, 60),
    ("square", {"num_humans": 4, "min_humans": 1, "lidar_rays": 24}, 60),
]


def _env(scenario: str, crowd: dict, batch: int) -> TransformedEnv:
    cfg = CrowdConfig(scenario=scenario, **crowd)
    base = CrowdNavEnv(scenario, num_envs=batch, num_humans=cfg.num_humans, config=cfg, seed=3, split="train")
    return TransformedEnv(base, RobotCentric(entities=cfg.obstacles_shape[0] > 0))


def _toward_goal(robot: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Full speed with the rotation nearest to the goal's bearing, a random action one time in ten:
    episodes that reach their goals and episodes that collide."""
    bearing = torch.atan2(robot[:, 6] - robot[:, 1], robot[:, 5] - robot[:, 0]) - robot[:, 8]
    bearing = torch.remainder(bearing + math.pi, 2 * math.pi) - math.pi
    rotation = ((bearing.clamp(-math.pi / 6, math.pi / 6) + math.pi / 6) / (math.pi / 3) * 15).round().long()
    greedy = 1 + 5 * rotation + 4
    random = torch.randint(0, 81, greedy.shape, generator=gen)
    return torch.where(torch.rand(greedy.shape, generator=gen) < 0.1, random, greedy)


@pytest.mark.parametrize("scenario, crowd, steps", CASES,
                         ids=[c[0] + ("-" + c[1]["human_model"] if "human_model" in c[1] else "")
                              + ("-lidar" if "lidar_rays" in c[1] else "") for c in CASES])
def test_counterfactual_transitions_equal_the_env_stepping_each_alternative(scenario, crowd, steps):
    """Restore the env before a step, take each alternative action: reward, termination and every
    observation the network reads equal what the one-step model built from the real transition."""
    torch.manual_seed(0)
    B, k = 16, 4
    env = _env(scenario, crowd, B)
    cfg = env.base_env.config
    keys = obs_keys(cfg, lidar=cfg.lidar_rays > 0)
    part = CounterfactualExperience(cfg, make_q_network("sarl"), keys, actions="random", k=k,
                                    entities=cfg.obstacles_shape[0] > 0)
    gen = torch.Generator().manual_seed(1)
    td = env.reset()
    compared, events = 0, torch.zeros(4, dtype=torch.int64)
    for _ in range(steps):
        snap = env.base_env.snapshot()
        td["action"] = _toward_goal(td["robot"], gen)
        real = env.step(td.clone())
        alternatives = torch.randint(0, 81, (B, k), generator=gen)
        alternatives[:, 0] = td["action"]  # the taken action too: the model must give back the real step
        fake = part.transitions(real, alternatives)
        assert fake.batch_size == (B, k)
        for j in range(k):
            env.base_env.restore(snap)
            again = env.reset()
            again["action"] = alternatives[:, j]
            out = env.step(again)["next"]
            got = fake[:, j]
            torch.testing.assert_close(got["next", "reward"], out["reward"], atol=1e-5, rtol=0)
            assert torch.equal(got["next", "terminated"], out["terminated"])
            for key in keys:
                torch.testing.assert_close(got["next", key], out[key], atol=1e-5, rtol=0)
                torch.testing.assert_close(got[key], real[key])
            compared += B
            events += torch.bincount(out["event"].reshape(-1), minlength=4)
        env.base_env.restore(snap)
        again = env.reset()
        again["action"] = td["action"]
        _, td = env.step_and_maybe_reset(again)
    assert compared == steps * B * k
    assert events[COLLISION] > 0 and (scenario == "circle" or events[SUCCESS] > 0)  # ends of both kinds compared


def test_topk_all_and_random_alternatives():
    torch.manual_seed(0)
    env = _env("circle", {"num_humans": 3}, 8)
    cfg, keys = env.base_env.config, obs_keys(env.base_env.config)
    net = make_q_network("sarl")
    td = env.rollout(3, break_when_any_done=False)[:, -1]
    top = CounterfactualExperience(cfg, net, keys, k=5).alternatives(td)
    q = net(*(td[k] for k in keys))
    assert torch.equal(top, q.topk(5, dim=-1).indices)
    every = CounterfactualExperience(cfg, net, keys, actions="all").alternatives(td)
    assert every.shape == (8, 81) and torch.equal(every[3], torch.arange(81))
    part = CounterfactualExperience(cfg, net, keys, actions="random", k=7, seed=5)
    state = part.state_dict()
    drawn = part.alternatives(td)
    assert all(len(set(row.tolist())) == 7 for row in drawn)  # distinct per state
    part.load_state_dict(state)
    assert torch.equal(part.alternatives(td), drawn)  # the generator's state restores the draw


def _sample(batch: int = 6):
    torch.manual_seed(0)
    env = _env("circle", {"num_humans": 3}, batch)
    td = env.rollout(4, break_when_any_done=False)[:, -1]
    td["steps_to_next_obs"] = torch.ones(batch, 1, dtype=torch.int64)
    return env.base_env.config, obs_keys(env.base_env.config), td


def test_second_update_yields_the_real_batch_then_the_counterfactual_one():
    cfg, keys, td = _sample()
    part = CounterfactualExperience(cfg, make_q_network("sarl"), keys, k=5)
    batches = list(part.batches(td))
    assert [name for name, _ in batches] == ["real", "counterfactual"]
    assert batches[0][1] is td and batches[1][1].batch_size == (6, 5)
    assert set(part.scalars()) == {"counterfactual_collision_rate", "counterfactual_goal_rate", "counterfactual_reward"}


def test_merged_loss_is_the_weighted_sum_of_the_two_means():
    cfg, keys, td = _sample()
    net = make_q_network("sarl")
    loss = D3QNLoss(net, keys, gamma=0.97)
    part = CounterfactualExperience(cfg, net, keys, mode="merged", k=5, weight=0.3)
    (name, merged), = list(part.batches(td))
    assert name == "merged" and merged.batch_size == (6, 6)
    torch.testing.assert_close(merged[WEIGHT_KEY].sum(), torch.tensor(1.0))
    fake = CounterfactualExperience(cfg, net, keys, k=5).counterfactual_batch(td)
    expected = 0.7 * loss(td)["loss"] + 0.3 * loss(fake)["loss"]
    torch.testing.assert_close(loss(merged)["loss"], expected)


# compiled: make test-slow (~30 s of compilation); the compiled grouped path is checked in make test by the merged
# row-by-row test below
@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_grouped_batch_gives_the_flat_batch_loss_and_gradients(compiled):
    """A ``[B, k]`` counterfactual batch encodes each state once; its loss and gradients equal those
    of the same ``B·k`` transitions laid out flat (each state repeated), eager and compiled."""
    cfg, keys, td = _sample()
    net = make_q_network("sarl")
    torch.manual_seed(3)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    part = CounterfactualExperience(cfg, net, keys, actions="random", k=5, seed=2)
    grouped = part.counterfactual_batch(td)
    flat = grouped.reshape(-1).clone()  # the states materialised, one row per transition
    assert flat.batch_size == (30,)
    loss = D3QNLoss(net, keys, gamma=0.97, compile=compiled)
    loss.update_target()
    out = loss.loss_and_grad(grouped)
    grads = {k: p.grad.clone() for k, p in net.named_parameters()}
    ref = loss.loss_and_grad(flat)
    torch.testing.assert_close(out["loss"], ref["loss"], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(out["q_mean"], ref["q_mean"], rtol=1e-5, atol=1e-7)
    for k, p in net.named_parameters():
        torch.testing.assert_close(grads[k], p.grad, rtol=1e-4, atol=1e-6)


def _reference_loss(net, target_net, keys, batch, gamma):
    """The double-DQN loss of a ``[B, g]`` batch computed row by row from the two networks, every
    transition laid out flat (no grouping, no chunking): what :class:`D3QNLoss` must equal."""
    B, g = batch.batch_size
    flat = batch.reshape(-1)
    with torch.no_grad():
        nxt = [flat.get(("next", key)) for key in keys]
        best = net(*nxt).argmax(-1, keepdim=True)
        boot = target_net(*nxt).gather(-1, best).squeeze(-1)
        steps = flat.get("steps_to_next_obs").reshape(-1).to(boot.dtype)
        y = (flat.get(("next", "reward")).reshape(-1) + gamma ** steps * boot
             * (~flat.get(("next", "terminated")).reshape(-1)))
    q = net(*(flat.get(key) for key in keys)).gather(-1, flat.get("action").reshape(-1, 1).long()).squeeze(-1)
    per = (q - y).pow(2)
    weight = flat.get(WEIGHT_KEY, None)
    return per.mean() if weight is None else (weight.reshape(-1) * per).sum()


@pytest.mark.parametrize("mode, compiled", [("second_update", False), ("merged", False), ("merged", True),
                                            # the same compiled graph as merged's without weights: make test-slow
                                            pytest.param("second_update", True, marks=pytest.mark.slow)])
def test_counterfactual_update_equals_the_row_by_row_loss_and_gradients(mode, compiled):
    """The update on a counterfactual batch (``second_update``'s ``[B, 5]``, ``merged``'s ``[B, 6]``:
    states encoded once, bootstrap states evaluated in chunks) gives the loss and gradients of the same
    transitions computed row by row, eager and compiled, with a target network that differs."""
    cfg, keys, td = _sample()
    torch.manual_seed(4)
    net = make_q_network("sgd3qn")
    loss = D3QNLoss(net, keys, gamma=0.97, compile=compiled)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    part = CounterfactualExperience(cfg, net, keys, mode=mode, k=5, weight=0.4)
    name, batch = list(part.batches(td))[-1]
    assert batch.batch_size == (6, 5 if mode == "second_update" else 6)
    out = loss.loss_and_grad(batch)
    grads = {k: p.grad.clone() for k, p in net.named_parameters()}
    for p in net.parameters():
        p.grad = None
    expected = _reference_loss(net, loss.target_net, keys, batch, 0.97)
    expected.backward()
    torch.testing.assert_close(out["loss"], expected.detach(), rtol=1e-5, atol=1e-7)
    for k, p in net.named_parameters():
        torch.testing.assert_close(grads[k], p.grad, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("compile_acting", [False, True])
def test_the_top_k_forward_is_compiled_with_the_acting_network(compile_acting):
    """With ``train.compile_acting`` the alternatives are ranked by the network through ``torch.compile`` (its own
    parameters; compiled outputs equal eager's: test_training's compiled-acting test), else by the network itself.
    Nothing is compiled here."""
    from crowdrl.compile import CompiledModule
    from crowdrl.training.facts import RunFacts
    from crowdrl.training.factories import make_update_part

    run = validate({"train": {"compile_acting": compile_acting, "counterfactual": {"mode": "second_update"}}},
                   resources=False)
    net = make_q_network(run.encoder.name)
    part = make_update_part(run.train, net, RunFacts.of(run))
    if compile_acting:
        assert isinstance(part.q, CompiledModule) and part.q.module is net
    else:
        assert part.q is net


def test_config_keys_are_checked_naming_the_key():
    for key, value, words in (("mode", "sometimes", "train.counterfactual.mode"),
                              ("actions", "best", "train.counterfactual.actions"),
                              ("k", 0, "train.counterfactual.k"), ("k", 82, "train.counterfactual.k"),
                              ("weight", 1.5, "train.counterfactual.weight")):
        with pytest.raises(ConfigError, match=words):
            validate({"train": {"counterfactual": {"mode": "merged", key: value}}}, resources=False)


def test_humans_that_react_to_the_robot_are_refused_naming_the_key():
    with pytest.raises(ConfigError, match="train.counterfactual.mode.*env.robot_visible"):
        validate({"env": {"robot_visible": True}, "train": {"counterfactual": {"mode": "second_update"}}},
                 resources=False)
    validate({"env": {"robot_visible": True, "human_model": "linear"},  # linear humans ignore everyone
              "train": {"counterfactual": {"mode": "second_update"}}}, resources=False)
    with pytest.raises(ValueError, match="visible robot"):
        CounterfactualExperience(CrowdConfig(robot_visible=True), make_q_network("sarl"), ["robot_rc", "humans_rc"])


def test_off_keeps_the_fingerprint_of_runs_recorded_before_the_key():
    """Off (and hard target copies) is what a run recorded before the keys trained: its fingerprint is theirs,
    though today's defaults are the recommended learner (on, Polyak)."""
    off = to_dict(validate({"train": {"counterfactual": {"mode": "off"}, "target_tau": 1.0}}, resources=False))
    older = {**off, "train": {k: v for k, v in off["train"].items() if k not in ("counterfactual", "target_tau")}}
    assert config_fingerprint(off) == config_fingerprint(older)
    on = to_dict(validate({"train": {"counterfactual": {"mode": "second_update"}, "target_tau": 1.0}}, resources=False))
    assert config_fingerprint(on) != config_fingerprint(off)
    assert config_fingerprint(to_dict(validate({}, resources=False))) not in (config_fingerprint(on),
                                                                             config_fingerprint(off))


def test_reproduce_names_the_setting_in_its_manifest_and_gives_it_to_every_run(tmp_path):
    from omegaconf import OmegaConf

    from crowdrl.cli.reproduce import PlanError, make_plan, run_overrides
    from crowdrl.resources import config_dir

    cfg = OmegaConf.to_container(OmegaConf.load(config_dir() / "reproduce.yaml"))
    cfg.pop("hydra")
    cfg.pop("defaults")  # its typed schema, reproduce_schema
    cfg["out"] = str(tmp_path)
    plan = make_plan(cfg)  # the budget's learner: the recommended one, stated to every run
    assert plan.manifest()["counterfactual"] == {"mode": "second_update", "actions": "topk", "k": 5, "weight": 0.5}
    assert {"train.counterfactual.mode=second_update", "train.target_tau=0.005"} <= set(run_overrides(plan, plan.methods[0]))
    plain = make_plan({**cfg, "train_learner": "plain"})  # the tables recorded before issue 50
    assert plain.manifest()["counterfactual"]["mode"] == "off" and plain.manifest()["levers"]["target_tau"] == 1.0
    overrides = run_overrides(plain, plain.methods[0])
    assert "train.counterfactual.mode=off" in overrides and "train.target_tau=1.0" in overrides
    assert [o for o in overrides if "counterfactual" in o] == ["train.counterfactual.mode=off"]
    paper = make_plan({**cfg, "budget": "paper"})  # preset=paper's learner: hard copies
    assert paper.manifest()["counterfactual"]["mode"] == "second_update" and paper.manifest()["levers"]["target_tau"] == 1.0
    plan = make_plan({**cfg, "counterfactual": {"mode": "second_update", "k": 3}})
    assert plan.manifest()["counterfactual"] == {"mode": "second_update", "actions": "topk", "k": 3, "weight": 0.5}
    assert "train.counterfactual.k=3" in run_overrides(plan, plan.methods[0])
    with pytest.raises(PlanError, match="^train_learner: unknown 'best'; allowed: paper, plain, recommended"):
        make_plan({**cfg, "train_learner": "best"})
    # the lidar scan (issue 49): stated to every run and in the manifest; off, the runs' commands are as before it
    assert not any("lidar" in o for o in run_overrides(plain, plain.methods[0]))
    assert plain.manifest()["lidar"] == {"encoder": "off", "rays": 0}
    scan = make_plan({**cfg, "lidar": "conv", "lidar_rays": 36})
    assert {"encoder.lidar=conv", "env.lidar_rays=36"} <= set(run_overrides(scan, scan.methods[0]))
    assert scan.manifest()["lidar"] == {"encoder": "conv", "rays": 36}
    with pytest.raises(PlanError, match="^lidar: unknown 'cnn'"):
        make_plan({**cfg, "lidar": "cnn"})
    with pytest.raises(PlanError, match="^lidar_rays: must be an integer in 1..1024 when lidar=mlp, got 0"):
        make_plan({**cfg, "lidar": "mlp", "lidar_rays": 0})
    with pytest.raises(PlanError, match="counterfactual"):
        make_plan({**cfg, "counterfactual": {"modes": "merged"}})


def test_reproduce_gives_the_stability_levers_to_every_run_and_names_them_in_its_manifest(tmp_path):
    from omegaconf import OmegaConf

    from crowdrl.cli.reproduce import PlanError, check_manifest, check_runs, make_plan, run_overrides
    from crowdrl.resources import config_dir

    cfg = OmegaConf.to_container(OmegaConf.load(config_dir() / "reproduce.yaml"))
    cfg.pop("hydra")
    cfg.pop("defaults")
    cfg.update(out=str(tmp_path), budget="smoke", variants=["egreedy"])
    off = make_plan({**cfg, "train_learner": "plain"})
    from crowdrl.reproduction.plan import LEVERS_OFF
    from crowdrl.training.config import LEVER_KEYS, TrainConfig

    assert set(LEVERS_OFF) == set(LEVER_KEYS) and all(hasattr(TrainConfig, k) for k in LEVER_KEYS)
    assert [o for o in run_overrides(off, off.methods[0]) if o.startswith("train.") and "counterfactual" not in o
            and "test_episodes" not in o] == ["train.target_tau=1.0"]  # every lever off: hard copies stated
    assert off.manifest()["levers"] == {"target_tau": 1.0, "huber_delta": None, "grad_clip_norm": None,
                                        "lr_end": None, "q_layer_norm": False}
    on = make_plan({**cfg, "train_learner": "plain", "train": {"target_tau": 0.005, "huber_delta": 1.0, "q_layer_norm": True}})
    overrides = run_overrides(on, on.methods[0])
    assert {"train.target_tau=0.005", "train.huber_delta=1.0", "train.q_layer_norm=true"} <= set(overrides)
    check_runs(on)  # train.py takes them
    assert on.manifest()["levers"]["target_tau"] == 0.005
    # a folder made without levers (its manifest predates the key) refuses a call that turns one on
    manifest = off.manifest()
    manifest.pop("levers")
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    check_manifest(off)
    with pytest.raises(PlanError, match="levers"):
        check_manifest(on)
    with pytest.raises(PlanError, match="train.target_tau"):  # out of range: train's own check, naming the key
        check_runs(make_plan({**cfg, "train": {"target_tau": 0.0}}))
    with pytest.raises(PlanError, match="target_taus"):
        make_plan({**cfg, "train": {"target_taus": 0.5}})


def _tiny_run(total_frames: int, mode: str = "second_update", exploration: str = "egreedy", **train):
    return validate({
        "preset": "smoke", "encoder": {"name": "sarl"}, "env": {"num_humans": 4},
        "logger": {"name": "csv", "progress_bar": False, "render": False},
        "planning": {"enabled": False}, "exploration": {"name": exploration},
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": total_frames, "warmup_frames": 32,
                  "batch_size": 16, "buffer_size": 1000, "updates_per_frame": 0.25, "target_update_frames": 32,
                  "val_every_frames": 64, "val_episodes": 2, "checkpoint_every_frames": 32, "test_episodes": 2,
                  "compile_acting": False, "compile_loss": False, "save_buffer": True,
                  "counterfactual": {"mode": mode, "actions": "random", "k": 3}, **train}}, resources=False)


@pytest.mark.parametrize("mode", ["second_update", "merged"])
def test_a_stopped_run_resumes_exactly_and_logs_the_counterfactual_scalars(tmp_path, mode):
    from crowdrl.training import Trainer
    from crowdrl.training.checkpoint import load_checkpoint

    def train(run, folder):
        trainer = Trainer(run, folder)
        try:
            trainer.train()
        finally:
            trainer.close()

    train(_tiny_run(128, mode), tmp_path / "straight")
    train(_tiny_run(64, mode), tmp_path / "resumed")
    train(_tiny_run(128, mode), tmp_path / "resumed")  # continues from last.pt at 64 frames
    straight, resumed = (load_checkpoint(tmp_path / d / "checkpoints" / "last.pt") for d in ("straight", "resumed"))
    assert straight["counters"]["updates"] == resumed["counters"]["updates"] > 0
    assert all(torch.equal(straight["loss"][k], resumed["loss"][k]) for k in straight["loss"])
    assert torch.equal(straight["update_part"]["generator"], resumed["update_part"]["generator"])
    import json
    rows = [json.loads(line) for line in (tmp_path / "straight" / "scalars.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if r["kind"] == "train" and "train/counterfactual_collision_rate" in r]
    assert train_rows and all(0 <= r["train/counterfactual_collision_rate"] <= 1 for r in train_rows)
    assert all(("train/loss_counterfactual" in r) == (mode == "second_update") for r in train_rows)


def test_look_ahead_refuses_actions_not_shaped_states_by_candidates():
    from crowdrl.sim.kinematics import action_table
    from crowdrl.sim.lookahead import look_ahead

    cfg = CrowdConfig()
    with pytest.raises(ValueError, match=r"actions must be shaped \[M, w\]"):
        look_ahead(cfg, action_table(), torch.zeros(3, 9), torch.zeros(3, 2, 5), torch.zeros(3, 2, 5),
                   torch.zeros(3, dtype=torch.int64))


@pytest.mark.parametrize("exploration, mode", [("icm", "second_update"), ("re3", "merged")])
def test_an_intrinsic_bonus_with_n_step_returns_trains_with_counterfactual_experience(tmp_path, exploration, mode):
    """Issue 52 (D2): with n > 1 the bonus reads the one-step successor (``one_step_next``); the counterfactual
    transitions (one step) hold theirs there too, so the first update no longer fails with a KeyError."""
    from crowdrl.training import Trainer
    from crowdrl.training.variants import ONE_STEP_KEY

    trainer = Trainer(_tiny_run(64, mode, exploration, n_step=2, save_buffer=False), tmp_path / "run")
    try:
        trainer.train()
        sample = trainer.buffer.sample()
        batch = trainer.learner.part.counterfactual_batch(sample)
        assert torch.equal(batch.get((ONE_STEP_KEY, "robot_rc")), batch.get(("next", "robot_rc")))
    finally:
        trainer.close()
    assert trainer.counters.updates > 0
