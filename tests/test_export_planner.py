"""The exported online planner (crowdrl.export, issue #53): one ONNX graph from the world-frame observation to
the planner's action, equal to the torch planner's on every step of test episodes; evaluate.py evaluates an
.onnx file through onnxruntime on the same cases and record layout; a bad .onnx file or key is refused in one
line naming it, nothing written; eval.planning_depth=0 evaluates a planning checkpoint greedily on Q."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdrl_testing.cli import run_cli  # refusals, in this process

onnx = pytest.importorskip("onnx")
onnxruntime = pytest.importorskip("onnxruntime")

from crowdrl_testing import fresh_network  # noqa: E402
from crowdrl.evaluation.report import read_eval_record  # noqa: E402
from crowdrl.export import FORMAT_VERSION, PLANNER_INPUTS, export_onnx, read_exported  # noqa: E402
from crowdrl.agents import compare_on_test_cases  # noqa: E402
from crowdrl.onnx_policy import OnnxPolicy  # noqa: E402
from crowdrl.training import CheckpointError  # noqa: E402
from crowdrl.training.checkpoint import config_fingerprint, save_checkpoint  # noqa: E402
from crowdrl.training.config import to_dict  # noqa: E402
from crowdrl.training.validation import validate  # noqa: E402
from crowdrl.training.acting import make_predictor_of  # noqa: E402
from crowdrl.training.facts import RunFacts  # noqa: E402
from crowdrl.agents import evaluate_spec  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "src" / "crowdrl" / "onnx_example.py"
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
PRETRAINED = ROOT / "pretrained" / "sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s1"

# untrained networks and predictors (random weights: many near-ties, a harder test than a trained agent's)
CASES = {
    "sgd3qn-learned": {"env": {"num_humans": 5}},
    "sgd3qn-variable": {"env": {"num_humans": 6, "min_humans": 2}},
    "depth2-safety": {"env": {"num_humans": 4}, "planning": {"depth": 2, "width": 3, "safety_horizon": 2}},
    "depth2-progress-bias": {"env": {"num_humans": 4}, "planning": {"depth": 2, "width": 3, "progress_bias": 1.0}},
    "sarl-const_vel": {"encoder": {"name": "sarl"}, "env": {"num_humans": 5}, "planning": {"predictor": "const_vel"}},
    "lstm_rl": {"encoder": {"name": "lstm_rl"}, "env": {"num_humans": 4}},
}


def planning_folder(folder: Path, overrides: dict, seed: int = 0) -> Path:
    """A run folder holding ``checkpoints/best.pt`` of a fresh planning config (network and predictor)."""
    planning = {"enabled": True, **overrides.get("planning", {})}
    run = validate({**overrides, "planning": planning, "train": {"compile_acting": False}})
    torch.manual_seed(seed)
    config = to_dict(run)
    payload = {"net": fresh_network(run).state_dict(), "config": config, "frames": 0, "val": {}}
    predictor = make_predictor_of(run.planning, RunFacts.of(run))
    if any(True for _ in predictor.parameters()):
        payload["predictor"] = predictor.state_dict()
    save_checkpoint(folder / "checkpoints" / "best.pt", payload, config_fingerprint(config))
    return folder


@pytest.fixture(scope="module")
def planner_model(tmp_path_factory) -> tuple[Path, Path]:
    """(the run folder, its exported planner) of a default SG-D3QN planning config at 5 humans."""
    base = tmp_path_factory.mktemp("planner")
    folder = planning_folder(base / "run", CASES["sgd3qn-learned"])
    export_onnx(folder, base / "planner.onnx")
    return folder, base / "planner.onnx"


@pytest.mark.parametrize("case", list(CASES))
def test_the_exported_planner_acts_as_the_torch_planner_on_every_step(tmp_path, case):
    """12 test cases played to the end by the torch planner: the exported model's action on every step's
    observation is the torch planner's (a difference by float rounding, the scores tying within 1e-4, is
    counted and bounded); both evaluations give the same record."""
    folder = planning_folder(tmp_path / "run", CASES[case])
    info = export_onnx(folder, tmp_path / "policy.onnx")
    assert info.planner and not info.planning_dropped and info.metadata["crowdrl.policy"] == "planner"
    assert read_exported(info.path).run.planning.progress_bias == CASES[case].get("planning", {}).get("progress_bias", 0)
    r = compare_on_test_cases(folder, info.path, episodes=12, batch=12)
    assert r["steps"] > 12 and r["differ"] == 0, r
    assert r["rounding"] <= max(1, r["steps"] // 500), r
    if r["rounding"] == 0:
        assert r["onnx"]["success_rate"] == r["torch"]["success_rate"]
        assert r["onnx"]["average_return"] == pytest.approx(r["torch"]["average_return"], abs=1e-5)
    assert [i.name for i in onnxruntime.InferenceSession(str(info.path)).get_inputs()] == list(PLANNER_INPUTS)


@pytest.mark.skipif(not (PRETRAINED / "best.pt").exists(), reason="needs the shipped pretrained agent")
def test_a_shipped_agents_exported_planner_acts_as_its_torch_planner(tmp_path):
    """The shipped agent, 20 circle cases to the end: every step's action identical."""
    info = export_onnx(PRETRAINED, tmp_path / "agent.onnx")
    r = compare_on_test_cases(PRETRAINED, info.path, episodes=20, batch=20)
    assert r["steps"] > 500 and r["identical"] == r["steps"], r
    assert r["onnx"]["success_rate"] == r["torch"]["success_rate"]
    m = info.metadata
    assert (m["crowdrl.format_version"], m["crowdrl.observation"], m["crowdrl.planning_depth"],
            m["crowdrl.planning_width"], m["crowdrl.num_humans"]) == (str(FORMAT_VERSION), "world", "1", "10", "10")


def test_evaluate_py_evaluates_an_onnx_file_with_the_checkpoints_record_layout(planner_model, tmp_path):
    folder, model = planner_model
    out = tmp_path / "eval"
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "evaluate.py"), f"checkpoint={model}",
                           "eval.episodes=6", "eval.record_episode=null", f"hydra.run.dir={out}"], env=ENV,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = read_eval_record(out / "eval.json")
    want, _ = evaluate_spec(checkpoint=folder, episodes=6, record_episode=None)
    assert sorted(got) == sorted(want)
    assert got["policy"] == want["policy"] + "+onnx" == "sgd3qn+egreedy+planning+onnx"
    for key in ("success_rate", "collision_rate", "timeout_rate", "episodes", "scenario", "checkpoint_frames"):
        assert got[key] == want[key], key
    assert got["average_return"] == pytest.approx(want["average_return"], abs=1e-5)


def _damaged(model: Path, tmp_path: Path, how: str) -> tuple[Path, str]:
    """A copy of ``model`` damaged ``how``, and the words its refusal names."""
    path = tmp_path / f"{how}.onnx"
    if how == "truncated":
        data = model.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        return path, "truncated"
    m = onnx.load(str(model))
    entry = {p.key: p for p in m.metadata_props}
    if how == "newer":
        entry["crowdrl.format_version"].value = str(FORMAT_VERSION + 1)
        words = f"format version {FORMAT_VERSION + 1} is newer than this crowdrl reads"
    elif how == "layout":
        entry["crowdrl.observation"].value = "lidar"
        words = "observation layout 'lidar'"
    else:  # inputs of another layout than the metadata says
        entry["crowdrl.observation"].value = "robot_centric"
        words = "differ from its observation layout 'robot_centric'"
    onnx.save(m, str(path))
    return path, words


@pytest.mark.parametrize("how", ["truncated", "newer", "layout", "inputs"])
def test_a_bad_onnx_file_is_refused_naming_the_file_and_what_differs(planner_model, tmp_path, how):
    path, words = _damaged(planner_model[1], tmp_path, how)
    with pytest.raises(CheckpointError, match=str(path).replace(".", r"\.")) as err:
        read_exported(path)
    assert words in str(err.value)


def test_evaluate_py_refuses_a_bad_onnx_file_in_one_line_writing_nothing(planner_model, tmp_path):
    path, _ = _damaged(planner_model[1], tmp_path, "newer")
    out = tmp_path / "eval"
    proc = run_cli("evaluate.py", f"checkpoint={path}", "eval.episodes=2", f"hydra.run.dir={out}")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert f"checkpoint: {path}: format version {FORMAT_VERSION + 1} is newer" in proc.stderr
    assert not out.exists()


def test_planning_depth_0_evaluates_greedily_and_bad_planning_keys_are_refused(planner_model):
    folder, model = planner_model
    record, _ = evaluate_spec(checkpoint=folder, episodes=4, record_episode=None, planning={"depth": 0})
    assert record["policy"] == "sgd3qn+egreedy" and record["planning_depth"] == 0
    for planning, words in (({"depth": -1}, "eval.planning_depth: must be an integer >= 0 (0: planning off"),
                            ({"depth": 0, "width": 3}, "eval.planning_width: planning is off (eval.planning_depth=0)"),
                            ({"width": 0}, "eval.planning_width:")):
        with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
            evaluate_spec(checkpoint=folder, episodes=2, planning=planning)
    with pytest.raises(ValueError, match=r"eval.planning_depth: .*planning is fixed at export \(planning_depth=1"):
        evaluate_spec(checkpoint=model, episodes=2, planning={"depth": 0})


def test_planning_depth_0_exports_the_greedy_q_policy_loudly(planner_model, tmp_path):
    folder, _ = planner_model
    work = tmp_path / "work"
    work.mkdir()
    proc = run_cli("export.py", f"checkpoint={folder}", "out=greedy.onnx", "planning_depth=0", cwd=work)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "NOTE: GREEDY Q ONLY: planning_depth=0 drops the online planner" in proc.stdout
    exported = read_exported(work / "greedy.onnx")
    assert not exported.plans and exported.layout == "robot_centric"
    assert exported.metadata["crowdrl.planning"].startswith("dropped (planning_depth=0)")
    greedy, _ = evaluate_spec(checkpoint=folder, episodes=4, record_episode=None, planning={"depth": 0})
    got, _ = evaluate_spec(checkpoint=work / "greedy.onnx", episodes=4, record_episode=None)
    assert got["policy"] == "sgd3qn+egreedy+onnx" and got["success_rate"] == greedy["success_rate"]


@pytest.mark.parametrize("scenario, planning", [("corridor", {}), ("room", {"depth": 2, "width": 3, "safety_horizon": 2})])
def test_a_planner_trained_among_obstacles_exports_with_the_edges_and_acts_as_torch(tmp_path, scenario, planning):
    """A planner trained among obstacles reads the observed edges: its model takes them (``world_obstacles``)
    and acts as the torch planner on every step, among the walls and in open space (one masked edge fed)."""
    folder = planning_folder(tmp_path / "run", {"env": {"scenario": scenario, "num_humans": 4}, "planning": planning})
    proc = run_cli("export.py", f"checkpoint={folder}", f"out={tmp_path / 'p.onnx'}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    model = read_exported(tmp_path / "p.onnx")
    assert model.plans and model.layout == "world_obstacles" and model.inputs[3:] == ("obstacles", "obstacles_mask")
    for where in (scenario, "circle"):
        r = compare_on_test_cases(folder, model.path, scenario=where, episodes=6, batch=6)
        assert r["steps"] > 6 and r["differ"] == 0 and r["rounding"] <= max(1, r["steps"] // 500), (where, r)
    example = subprocess.run([sys.executable, str(EXAMPLE), str(model.path), "--json"], env=ENV, capture_output=True,
                             text=True, timeout=120)  # the numpy-only example feeds it a wall with a gap
    assert example.returncode == 0, example.stderr[-2000:]
    assert json.loads(example.stdout)["policy"] == "planner"


@pytest.mark.parametrize("planning, words", [({"width": 0}, "planning_width: must lie in 1..81"),
                                             ({"depth": -1}, "planning_depth: must be an integer >= 0"),
                                             ({"depth": 0, "safety_horizon": 2}, "planning_safety_horizon: planning is off")])
def test_export_refuses_bad_planner_settings_naming_the_key_writing_nothing(planner_model, tmp_path, planning, words):
    with pytest.raises(ValueError, match=words):
        export_onnx(planner_model[0], tmp_path / "out" / "p.onnx", planning=planning)
    assert not (tmp_path / "out").exists()


def test_the_example_runs_the_exported_planner_without_torch(planner_model, tmp_path):
    """torch and crowdrl blocked: the example runs the planner on its scene, the torch planner's action."""
    folder, model = planner_model
    blocked = tmp_path / "blocked"
    blocked.mkdir()
    for name in ("torch", "crowdrl", "tensordict", "torchrl"):
        (blocked / f"{name}.py").write_text(f"raise ImportError('{name} is blocked in this test')\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(model), "--json"], env={**env, "PYTHONPATH": str(blocked)},
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["policy"] == "planner" and result["planning"].startswith("on: the online planner")

    from crowdrl.policies import OnlinePlanner
    from crowdrl.training.checkpoint import load_trained_network, load_trained_predictor
    from crowdrl.training.config import crowd_config

    run, net, data = load_trained_network(folder)
    planner = OnlinePlanner(net, load_trained_predictor(run, data, folder), crowd_config(run), gamma=run.train.gamma,
                            depth=run.planning.depth, width=run.planning.width)
    robot = torch.tensor([[0.0, -4.0, 0.0, 0.5, 0.3, 0.0, 4.0, 1.0, np.pi / 2]])
    humans = torch.tensor([[[0.3, -2.5, 0.0, -0.8, 0.3], [-1.5, -1.0, 0.6, 0.0, 0.3], [2.0, 1.0, 0.0, 0.0, 0.3]]])
    assert result["action"] == int(planner.plan(robot, humans, torch.ones(1, 3, dtype=torch.bool)).action)
    newer, _ = _damaged(model, tmp_path, "newer")
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(newer)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "crowdrl.format_version: 3 is newer than this example reads" in proc.stderr


def test_the_onnx_policy_refuses_another_crowd_size_for_a_fixed_n_model(tmp_path):
    folder = planning_folder(tmp_path / "run", CASES["lstm_rl"])
    info = export_onnx(folder, tmp_path / "lstm.onnx", check=False)
    with pytest.raises(ValueError, match=r"eval.num_humans: .*lstm.onnx takes exactly 4 rows"):
        evaluate_spec(checkpoint=info.path, episodes=2, num_humans=6)
    assert isinstance(OnnxPolicy(info.path), OnnxPolicy)


def test_act_time_planning_keys_combine_with_humans_that_see_the_robot():
    """A counterfactual-trained agent at depth 2 among humans that see the robot: the planner keys are checked
    against the run as it trained, so the test's visible humans do not trip a training-only check (they did)."""
    agent = Path(__file__).resolve().parents[1] / "pretrained" / "sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s0"
    record, _ = evaluate_spec(checkpoint=agent, episodes=2, record_episode=None, robot_visible=True,
                              planning={"depth": 2})
    assert (record["planning_depth"], record["robot_visible"]) == (2, True)
