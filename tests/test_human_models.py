"""The humans' models (``CrowdConfig.human_model``: orca, social_force, linear) and a robot they can see
(``robot_visible``): the oracles on fixed seeds, the keys' validation, and what a run keeps of them."""

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdrl.evaluation.report import read_eval_record
from crowdrl.sim import crowd
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.humans import human_velocities
from crowdrl.sim.rng import episode_keys
from crowdrl.sim.scenarios import initial_states
from crowdrl_testing import crowd_scene_state, random_crowd_scene

ROOT = Path(__file__).resolve().parents[1]


def _agreement(*args: str) -> dict:
    """``experiments/human_model_agreement.py <args> --json``'s output (its ``main``, in this process)."""
    import contextlib
    import io

    import human_model_agreement

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        human_model_agreement.main([*args, "--json"])
    return json.loads(out.getvalue())


@pytest.mark.parametrize("args", [("--model", "orca", "--robot-visible", "--seed", "11"),
                                  ("--model", "social_force", "--seed", "12"),
                                  ("--model", "social_force", "--robot-visible", "--seed", "13")])
def test_the_batched_models_agree_with_their_references_on_fresh_scenes(args):
    pytest.importorskip("pyrvo" if "orca" in args else "socialforce")
    out = _agreement(*args, "--scenes", "90")
    assert out["agents"] == sum(r["agents"] for r in out["rows"]) > 500
    assert out["within"] >= 0.999 * out["agents"], out["rows"]
    assert out["meta"]["tolerance"] == 1e-4


def _scenes(seed: int, kind: str, n_scenes: int = 40) -> list[dict]:
    gen = np.random.default_rng(seed)
    scenes = [random_crowd_scene(gen, kind) for _ in range(4 * n_scenes)]
    n = len(scenes[0]["positions"])
    return [s for s in scenes if len(s["positions"]) == n][:n_scenes]


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_a_visible_robot_changes_the_humans_near_it_and_only_then(model):
    state = crowd_scene_state(_scenes(0, "dense"))
    N = state.num_humans
    blind, _ = human_velocities(CrowdConfig(num_humans=N, human_model=model), state)
    seen, _ = human_velocities(CrowdConfig(num_humans=N, human_model=model, robot_visible=True), state)
    assert seen.shape == blind.shape == (state.batch_size, N, 2)
    assert (seen - blind).norm(dim=-1).amax() > 0.05  # the robot stands at a few cm from a human
    far = state.replace(robot_position=torch.full_like(state.robot_position, 1e4))  # out of everyone's reach
    seen_far, _ = human_velocities(CrowdConfig(num_humans=N, human_model=model, robot_visible=True), far)
    assert (seen_far - blind).abs().amax() < 1e-6


@pytest.mark.parametrize("model", ["orca", "social_force"])
def test_a_visible_robot_in_a_variable_crowd_sees_the_present_humans_only(model):
    cfg = CrowdConfig(num_humans=8, min_humans=2, human_model=model, robot_visible=True)
    state = initial_states(cfg, episode_keys("train", 3, torch.arange(16)))
    state = state.replace(robot_velocity=torch.tensor([[0.0, 0.8]]).repeat(16, 1))
    state = state.replace(human_velocity=torch.rand(16, 8, 2, generator=torch.Generator().manual_seed(0)) - 0.5)
    velocities, _ = human_velocities(cfg, state)
    absent = ~state.human_mask
    assert absent.any() and torch.equal(velocities[absent], state.human_velocity[absent])
    for b in range(16):  # the present humans move as the same humans in a fixed crowd of their size
        n = int(state.human_mask[b].sum())
        one = state.index(slice(b, b + 1))
        one = one.replace(**{k: getattr(one, k)[:, :n] for k in ("human_position", "human_velocity", "human_goal",
                                                                 "human_goal_steps", "human_mask")})
        fixed, _ = human_velocities(CrowdConfig(num_humans=n, human_model=model, robot_visible=True), one)
        torch.testing.assert_close(velocities[b, :n], fixed[0], rtol=0, atol=1e-6)


def test_linear_humans_walk_straight_to_the_goal_at_their_preferred_speed_and_ignore_everyone():
    cfg = CrowdConfig(scenario="square", human_model="linear")
    state = initial_states(cfg, episode_keys("train", 0, torch.arange(8)))
    velocities, infeasible = human_velocities(cfg, state)
    to_goal = state.human_goal - state.human_position
    speed = velocities.norm(dim=-1)
    assert not infeasible.any()
    torch.testing.assert_close(speed, torch.full_like(speed, cfg.human_v_pref))  # goals lie > 0.25 m away
    torch.testing.assert_close(velocities / speed.unsqueeze(-1), to_goal / to_goal.norm(dim=-1, keepdim=True))
    seen, _ = human_velocities(CrowdConfig(scenario="square", human_model="linear", robot_visible=True), state)
    assert torch.equal(seen, velocities)
    near = state.replace(human_position=state.human_goal - torch.tensor([0.1, 0.0]))  # lands on the goal
    landed, _ = human_velocities(cfg, near)
    torch.testing.assert_close(near.human_position + landed * cfg.time_step, state.human_goal)


@pytest.mark.parametrize("model", ["social_force", "linear"])
def test_episodes_with_other_humans_step_reproducibly(model):
    cfg = CrowdConfig(human_model=model, robot_visible=True)
    runs = []
    for _ in range(2):
        state = initial_states(cfg, episode_keys("test", 5, torch.arange(6)))
        for _ in range(20):
            state, result = crowd.step(cfg, state, torch.tensor([[0.3, 0.8]]).repeat(6, 1))
        runs.append(state.human_position)
    assert torch.equal(*runs) and torch.isfinite(runs[0]).all()
    orca = initial_states(CrowdConfig(), episode_keys("test", 5, torch.arange(6)))
    for _ in range(20):
        orca, _ = crowd.step(CrowdConfig(), orca, torch.tensor([[0.3, 0.8]]).repeat(6, 1))
    assert not torch.allclose(orca.human_position, runs[0])  # the model is used


@pytest.mark.parametrize("kwargs, key", [
    ({"human_model": "sfm"}, "human_model"),
    ({"robot_visible": "yes"}, "robot_visible"),
    ({"sf_tau": 0.0}, "sf_tau"),
    ({"sf_v0": -2.1}, "sf_v0"),
    ({"sf_sigma": math.nan}, "sf_sigma"),
    ({"sf_tau": math.inf}, "sf_tau"),
    ({"sf_substeps": 0}, "sf_substeps"),
    ({"sf_substeps": 2.0}, "sf_substeps"),
    ({"human_model": "social_force", "scenario": "doorway"}, "human_model"),
])
def test_bad_keys_are_refused_naming_them(kwargs, key):
    with pytest.raises(ValueError, match=rf"^{key}"):
        CrowdConfig(**kwargs)


def test_humans_react_to_the_robot_only_when_they_see_it_and_look_at_others():
    assert not CrowdConfig().humans_react_to_robot
    assert CrowdConfig(robot_visible=True).humans_react_to_robot
    assert CrowdConfig(human_model="social_force", robot_visible=True).humans_react_to_robot
    assert not CrowdConfig(human_model="linear", robot_visible=True).humans_react_to_robot
    assert not CrowdConfig(human_model="social_force").humans_react_to_robot


def test_the_reference_simulator_refuses_humans_it_does_not_simulate():
    pytest.importorskip("pyrvo")
    from crowdrl_testing.reference import ReferenceCrowdSim

    for cfg in (CrowdConfig(robot_visible=True), CrowdConfig(human_model="linear")):
        state = initial_states(cfg, episode_keys("test", 0, torch.arange(1)))
        with pytest.raises(ValueError, match="robot_visible"):
            ReferenceCrowdSim.from_state(cfg, state, 0)


def test_the_run_config_takes_the_keys_and_a_run_at_their_defaults_keeps_its_fingerprint():
    from crowdrl.training import validate
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import ConfigError, to_dict
    from crowdrl.training.config import crowd_config

    # the learner the keys were recorded with (visible robots need it: no counterfactual)
    plain = {"train": {"counterfactual": {"mode": "off"}, "target_tau": 1.0}}
    now = to_dict(validate(plain, resources=False))
    new_keys = ("human_model", "robot_visible", "sf_tau", "sf_v0", "sf_sigma", "sf_substeps")
    before = {**now, "env": {k: v for k, v in now["env"].items() if k not in new_keys}}
    assert config_fingerprint(now) == config_fingerprint(before)
    # the social-force parameters count only for social-force humans
    assert config_fingerprint(to_dict(validate({"env": {"sf_tau": 0.3}, **plain}, resources=False))) == config_fingerprint(now)
    changed = [to_dict(validate({"env": e, **plain}, resources=False)) for e in (
        {"human_model": "social_force"}, {"robot_visible": True}, {"human_model": "linear"},
        {"human_model": "social_force", "sf_tau": 0.3})]
    prints = {config_fingerprint(c) for c in changed} | {config_fingerprint(now)}
    assert len(prints) == 5
    run = validate({"env": {"human_model": "social_force", "robot_visible": True, "sf_substeps": 4}, **plain}, resources=False)
    cfg = crowd_config(run)
    assert (cfg.human_model, cfg.robot_visible, cfg.sf_substeps) == ("social_force", True, 4)
    for env, key in (({"human_model": "helbing"}, "env.human_model"), ({"sf_sigma": 0.0}, "env.sf_sigma"),
                     ({"scenario": "room", "human_model": "social_force"}, "env.human_model")):
        with pytest.raises(ConfigError, match=rf"^{key}"):
            validate({"env": env}, resources=False)


def test_the_gymnasium_ids_take_the_keys():
    import gymnasium as gym

    import crowdrl  # noqa: F401  (registers the ids)

    env = gym.make("crowdrl/SquareCrossing-v0", human_model="social_force", robot_visible=True).unwrapped
    assert (env.config.human_model, env.config.robot_visible) == ("social_force", True)
    env.reset(seed=0)
    for _ in range(3):
        obs, *_ = env.step(40)
    assert np.isfinite(obs["humans"]).all()
    with pytest.raises(ValueError, match="^human_model"):
        gym.make("crowdrl/CircleCrossing-v0", human_model="rvo")


def _cli(script: str, *args: str) -> subprocess.CompletedProcess:
    """``experiments/<script> args`` in this process (:func:`crowdrl_testing.cli.run_cli`)."""
    from crowdrl_testing.cli import run_cli

    return run_cli(script, *args)


def test_evaluate_py_takes_the_humans_model_in_one_override_and_refuses_a_bad_one(tmp_path):
    proc = _cli("evaluate.py", "policy=orca", "eval.episodes=2", "eval.record_episode=null",
                "eval.human_model=social_force", "eval.robot_visible=true", f"hydra.run.dir={tmp_path / 'ok'}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    record = read_eval_record(tmp_path / "ok" / "eval.json")
    assert (record["human_model"], record["robot_visible"]) == ("social_force", True)
    proc = _cli("evaluate.py", "policy=orca", "eval.episodes=2", "eval.record_episode=null", "eval.human_model=mixed",
                "eval.social_force_share=0.5", "eval.linear_share=0.25", f"hydra.run.dir={tmp_path / 'mixed'}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    record = read_eval_record(tmp_path / "mixed" / "eval.json")
    assert (record["human_model"], record["social_force_share"], record["linear_share"]) == ("mixed", 0.5, 0.25)
    for args, named in ((["env=room", "eval.human_model=social_force"], "eval.human_model"),
                        (["eval.robot_visible=maybe"], "eval.robot_visible"),
                        (["eval.human_model=mixed", "eval.linear_share=1.5"], "eval.linear_share"),
                        (["eval.social_force_share=0.2"], "eval.social_force_share")):
        proc = _cli("evaluate.py", "policy=orca", "eval.episodes=2", *args, f"hydra.run.dir={tmp_path / 'bad'}")
        assert proc.returncode == 2 and named in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-2000:]
        assert not (tmp_path / "bad").exists()


def test_a_pretrained_agent_is_evaluated_among_other_humans():
    from crowdrl.agents import evaluate_spec

    agent = ROOT / "pretrained" / "sgd3qn-planning-re3-demo-s0"
    plain, _ = evaluate_spec(checkpoint=agent, episodes=3, batch=3)
    linear, _ = evaluate_spec(checkpoint=agent, episodes=3, batch=3, human_model="linear", robot_visible=True)
    assert "human_model" not in plain and (linear["human_model"], linear["robot_visible"]) == ("linear", True)
    assert linear["min_separation"] != plain["min_separation"]


def test_a_social_force_agent_is_refused_among_obstacles_naming_the_keys(tmp_path):
    """A checkpoint trained among social-force humans, evaluated in an obstacle scenario where that model does not
    run, is refused naming ``env=`` and the way out (``eval.human_model``); with ORCA humans it runs there."""
    from crowdrl.training.checkpoint import config_fingerprint, load_checkpoint, save_checkpoint
    from crowdrl.training.compat import stored_config
    from crowdrl.training.config import to_dict
    from crowdrl.agents import evaluate_spec
    from crowdrl.training.validation import validate

    data = load_checkpoint(ROOT / "pretrained" / "sgd3qn-planning-re3-demo-s0" / "best.pt")
    config = {**data["config"], "env": {**data["config"]["env"], "human_model": "social_force"}}
    payload = {k: v for k, v in data.items() if k not in ("format", "fingerprint")} | {"config": config}
    save_checkpoint(tmp_path / "best.pt", payload,
                    config_fingerprint(to_dict(validate(stored_config(config), resources=False))))
    with pytest.raises(ValueError, match=r"^env=corridor: .*env.human_model=social_force.*eval.human_model="):
        evaluate_spec(checkpoint=tmp_path / "best.pt", scenario="corridor", episodes=2, batch=2)
    record, _ = evaluate_spec(checkpoint=tmp_path / "best.pt", scenario="corridor", episodes=2, batch=2,
                              human_model="orca")
    assert (record["scenario"], record["human_model"]) == ("corridor", "orca")


def test_train_py_refuses_a_bad_humans_key_naming_it_and_writes_nothing(tmp_path):
    proc = _cli("train.py", "preset=smoke", "env.human_model=helbing", f"hydra.run.dir={tmp_path / 'r'}")
    assert proc.returncode != 0 and "env.human_model" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "r").exists()


def test_compiled_social_force_equals_the_eager_model():
    """``orca_backend="compiled"`` steps social-force humans with the compiled, scenes-last form: the same
    velocities as the eager function (which agrees with the package to the last bit) up to float rounding,
    in a variable crowd with a visible robot (masks, a pedestrian without a destination)."""
    cfg = dict(num_humans=6, min_humans=2, human_model="social_force", robot_visible=True, sf_substeps=2)
    state = initial_states(CrowdConfig(**cfg), episode_keys("train", 5, torch.arange(24)))
    state = state.replace(human_velocity=torch.rand(24, 6, 2, generator=torch.Generator().manual_seed(1)) - 0.5,
                          robot_velocity=torch.tensor([[0.3, 0.6]]).repeat(24, 1))
    eager, _ = human_velocities(CrowdConfig(**cfg), state)
    compiled, _ = human_velocities(CrowdConfig(**cfg, orca_backend="compiled"), state)
    assert not torch.equal(eager, state.human_velocity)  # the humans moved
    torch.testing.assert_close(compiled, eager, atol=1e-5, rtol=0)
