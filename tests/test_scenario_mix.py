"""One batch of several scenarios (``ScenarioMixEnv``, ``env.mix``): each scenario's rows play exactly what a
single-scenario env of the same stream plays, resets included; padded obstacle rows take no part in a network's
attention; bad mixes are refused naming the key; a snapshot resumes the mix exactly."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule

from crowdrl.envs import CrowdNavEnv
from crowdrl.envs.mix import ScenarioMixEnv, mix_rows
from crowdrl.sim.config import SCENARIOS, CrowdConfig

SCENES = ("circle", "corridor", "doorway", "room", "square")
ROWS = {"circle": 2, "corridor": 1, "doorway": 2, "room": 1, "square": 1}
OWN_KEYS = ("robot", "humans", "humans_mask", "episode_id", "event", "step_count", "episode_reward")


def _configs(num_humans: int = 4) -> dict[str, CrowdConfig]:
    return {s: CrowdConfig(scenario=s, num_humans=num_humans) for s in SCENES}


def _policy() -> TensorDictModule:
    """A deterministic function of the state: the same state gets the same action in any env."""
    def act(robot: torch.Tensor, steps: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
        code = (robot[:, 0] * 1000).round().long() + 7 * steps.squeeze(-1) + 13 * ids.squeeze(-1)
        return code.remainder(81)
    return TensorDictModule(act, in_keys=["robot", "step_count", "episode_id"], out_keys=["action"])


def test_each_scenarios_rows_play_its_own_stream_exactly():
    mix = ScenarioMixEnv({s: c for s, c in _configs().items()}, ROWS, seed=3, split="train")
    roll = mix.rollout(120, _policy(), break_when_any_done=False)  # collector-style partial resets
    assert bool(roll["next", "done"].any())
    for name, rows in mix.slices.items():
        alone = CrowdNavEnv(name, num_envs=ROWS[name], num_humans=4, seed=3, split="train")
        own = alone.rollout(120, _policy(), break_when_any_done=False)
        for key in OWN_KEYS:
            assert torch.equal(roll[rows].get(("next", key)), own.get(("next", key))), (name, key)
        assert torch.equal(roll[rows].get(("next", "reward")), own.get(("next", "reward"))), name
        if "obstacles" in own.keys():
            k = own.get("obstacles").shape[-2]
            assert torch.equal(roll[rows].get("obstacles")[..., :k, :], own.get("obstacles"))
            assert not bool(roll[rows].get("obstacles_mask")[..., k:].any())
        else:
            assert not bool(roll[rows].get("obstacles_mask").any())
        assert bool((roll[rows].get("scenario") == SCENARIOS.index(name)).all())


def test_loaded_episodes_are_the_cases_of_each_scenario():
    mix = ScenarioMixEnv(_configs(), ROWS, seed=0, split="test")
    ids = torch.arange(10, 10 + mix.num_envs)
    mix.load_episodes(ids)
    td = mix.reset()
    assert torch.equal(td["episode_id"].flatten(), ids)
    for name, rows in mix.slices.items():
        alone = CrowdNavEnv(name, num_envs=ROWS[name], num_humans=4, seed=0, split="test")
        alone.load_episodes(ids[rows])
        assert torch.equal(alone.reset()["robot"], td["robot"][rows]), name


def test_a_snapshot_resumes_the_mix_step_for_step():
    mix = ScenarioMixEnv(_configs(), ROWS, seed=1)
    mix.rollout(30, _policy(), break_when_any_done=False)
    snap = mix.snapshot()
    after = mix.rollout(40, _policy(), break_when_any_done=False, auto_reset=False, tensordict=mix.current())
    again = ScenarioMixEnv(_configs(), ROWS, seed=1)
    again.restore(snap)
    resumed = again.rollout(40, _policy(), break_when_any_done=False, auto_reset=True)  # the reset continues them
    assert torch.equal(after["robot"], resumed["robot"])
    assert torch.equal(after["next", "robot"], resumed["next", "robot"])
    assert torch.equal(after["next", "episode_id"], resumed["next", "episode_id"])
    with pytest.raises(ValueError, match="rows"):
        ScenarioMixEnv(_configs(), {**ROWS, "circle": 3}).restore(snap)
    with pytest.raises(ValueError, match="scenario-mix snapshot"):
        again.restore({"format": CrowdNavEnv.SNAPSHOT_FORMAT})


def test_padded_obstacle_tokens_take_no_part_in_attention():
    from crowdrl.envs import RobotCentric
    from crowdrl.envs.robot_centric import ENTITY_DIM
    from crowdrl.models import make_q_network

    torch.manual_seed(0)
    net = make_q_network("sgd3qn", human_dim=ENTITY_DIM)
    alone = CrowdNavEnv("doorway", num_envs=3, num_humans=4, seed=0)
    td = RobotCentric(entities=True)(alone.reset())
    q = net(td["robot_rc"], td["entities_rc"], td["entities_mask"])
    pad = 5
    tokens = torch.cat((td["entities_rc"], torch.zeros(3, pad, td["entities_rc"].shape[-1])), 1)
    mask = torch.cat((td["entities_mask"], torch.zeros(3, pad, dtype=torch.bool)), 1)
    torch.testing.assert_close(net(td["robot_rc"], tokens, mask), q, rtol=0, atol=1e-6)


@pytest.mark.parametrize("mix, words", [
    ({"circle": 1, "atrium": 1}, "env.mix: unknown scenario 'atrium'"),
    ({"circle": -1, "doorway": 1}, "env.mix.circle: a proportion must be a finite number >= 0"),
    ({"circle": 0, "doorway": 0}, "env.mix: every proportion is 0"),
    ({"circle": 1, "doorway": 0.001}, "env.mix: scenario 'doorway' gets no row"),
])
def test_bad_mixes_are_refused_naming_the_key(mix, words):
    with pytest.raises(ValueError, match=words.replace(".", r"\.").replace("(", r"\(")):
        mix_rows(mix, 16)


def test_rows_follow_the_proportions():
    assert mix_rows({"circle": 1, "square": 1, "corridor": 1, "doorway": 1, "room": 1}, 64) == \
        {"circle": 13, "square": 13, "corridor": 13, "doorway": 13, "room": 12}
    assert mix_rows({"circle": 3, "doorway": 1}, 8) == {"circle": 6, "doorway": 2}
    assert sum(mix_rows({"circle": 0.3, "room": 0.7, "square": 0.0}, 10).values()) == 10


def test_configs_that_differ_beyond_the_scenario_are_refused():
    configs = {"circle": CrowdConfig(scenario="circle", num_humans=4), "doorway": CrowdConfig(scenario="doorway",
                                                                                                num_humans=5)}
    with pytest.raises(ValueError, match="num_humans"):
        ScenarioMixEnv(configs, {"circle": 1, "doorway": 1})


MIXED = {"preset": "smoke", "seed": 0,
         "env": {"scenario": "doorway", "num_humans": 3, "mix": {"circle": 1, "doorway": 1, "room": 1}},
         "logger": {"name": "csv", "progress_bar": False, "render": False},
         "planning": {"enabled": True, "width": 3},
         "train": {"num_envs": 6, "steps_per_batch": 8, "total_frames": 144, "warmup_frames": 48, "batch_size": 16,
                   "buffer_size": 1000, "updates_per_frame": 0.25, "val_every_frames": 48, "val_episodes": 3,
                   "checkpoint_every_frames": 48, "test_episodes": 3, "save_buffer": True, "compile_acting": False,
                   "compile_loss": False}}


def test_a_killed_mixed_run_resumes_bit_identically_and_evaluates_on_each_scenario(tmp_path):
    """The recommended learner (counterfactual experience, Polyak targets, planning) on a mix of open space,
    a doorway and a room: the networks read entity tokens, the buffer holds the padded maps, a run killed at
    frame 96 resumes to the same weights and logs as one never stopped, it tests on env.scenario and evaluates
    on any scenario of the mix alone."""
    from crowdrl_testing import train_until_killed
    from crowdrl.agents import evaluate_spec
    from crowdrl.evaluation.report import read_eval_record
    from crowdrl.training import validate
    from crowdrl.training.checkpoint import load_checkpoint
    from crowdrl.training.pipeline import run_training

    run = validate(MIXED)
    assert run.train.counterfactual.mode != "off" and run.train.target_tau < 1
    run_training(run, tmp_path / "ref")
    train_until_killed(run, tmp_path / "run", frame=96)
    run_training(run, tmp_path / "run")
    ref, got = (load_checkpoint(tmp_path / d / "checkpoints" / "last.pt") for d in ("ref", "run"))
    assert all(torch.equal(ref["loss"][k], got["loss"][k]) for k in ref["loss"])
    test = read_eval_record(tmp_path / "ref" / "eval.json")
    assert test["scenario"] == "doorway" and test["train_scenario"] == "mix"  # tested on one, trained on the mix
    assert read_eval_record(tmp_path / "ref" / "eval.json") == read_eval_record(tmp_path / "run" / "eval.json")
    import json

    vals = [json.loads(line) for line in (tmp_path / "ref" / "scalars.jsonl").read_text().splitlines()
            if json.loads(line)["kind"] == "val"]
    for row in vals:  # each scenario's validation cases (one each of the 3), and the mix's rate their mean
        rates = [row[f"val/{name}/success_rate"] for name in ("circle", "doorway", "room")]
        assert row["val/success_rate"] == pytest.approx(sum(rates) / 3)
    header = (tmp_path / "ref" / "scalars.csv").read_text().splitlines()[0]
    assert "val/doorway/success_rate" in header
    for scenario in ("circle", "room", "corridor"):  # corridor: a scenario it never saw, read through the same tokens
        record, _ = evaluate_spec(checkpoint=tmp_path / "ref", scenario=scenario, episodes=3, record_episode=None)
        assert record["scenario"] == scenario and record["episodes"] == 3 and record["train_scenario"] == "mix"
    pytest.importorskip("onnxruntime")
    from crowdrl.agents import compare_on_test_cases
    from crowdrl.export import export_onnx

    info = export_onnx(tmp_path / "ref", tmp_path / "mix.onnx")  # the planner whole, reading the edges
    assert info.planner and info.metadata["crowdrl.observation"] == "world_obstacles"
    for scenario in ("circle", "doorway"):
        r = compare_on_test_cases(tmp_path / "ref", info.path, scenario=scenario, episodes=3, batch=3)
        assert r["steps"] > 3 and r["differ"] == 0, (scenario, r)


def test_env_mix_selects_every_scenario_and_a_mix_is_one_override_away():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_defaults import _compose
    from crowdrl.training import validate
    from crowdrl.training.config import sees_obstacles, trained_scenarios

    run = validate(_compose("env=mix", "preset=smoke", "train.num_envs=10", "train.val_episodes=10"))
    assert set(trained_scenarios(run)) == set(SCENES) and run.env.scenario == "circle" and sees_obstacles(run)
    run = validate(_compose("env=doorway", "+env.mix={doorway: 2, circle: 1}", "preset=smoke"))
    assert run.env.mix == {"doorway": 2.0, "circle": 1.0}
    assert validate(_compose("env=circle", "preset=smoke")).env.mix == {}  # off by default
    run = validate(_compose("env=mix", "env.mix.room=0", "preset=smoke", "train.num_envs=8"))
    assert "room" not in trained_scenarios(run)


def test_a_mix_is_neutral_in_the_fingerprint_when_off():
    from crowdrl.training import validate
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict

    cfg = to_dict(validate({}))
    without = {**cfg, "env": {k: v for k, v in cfg["env"].items() if k != "mix"}}
    assert config_fingerprint(cfg) == config_fingerprint(without)
    assert config_fingerprint(to_dict(validate({"env": {"mix": {"circle": 1, "square": 1}}}))) != config_fingerprint(cfg)


def test_reproduce_plans_a_mix_and_refuses_one_its_budget_cannot_hold(tmp_path):
    """``reproduce.py train_scenario=mix``: every run trains on ``env=mix``; a budget whose envs cannot give each
    scenario a row is refused before anything is trained or written, naming env.mix."""
    from crowdrl.reproduction.plan import PlanError, check_runs, make_plan, run_overrides

    cfg = {"budget": "demo", "variants": ["egreedy"], "seeds": [0], "train_scenario": "mix",
           "scenarios": list(SCENES), "out": str(tmp_path / "mix")}
    plan = make_plan(cfg)
    assert "env=mix" in run_overrides(plan, plan.methods[0])
    check_runs(plan)
    with pytest.raises(PlanError, match=r"env\.mix: scenario '\w+' gets no row of the 4 envs"):
        check_runs(make_plan({**cfg, "budget": "smoke"}))
    with pytest.raises(PlanError, match="train_scenario: unknown 'atrium'.*mix"):
        make_plan({**cfg, "train_scenario": "atrium"})
    assert not (tmp_path / "mix").exists()
