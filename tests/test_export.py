"""ONNX export (crowdrl.export, experiments/export.py) of greedy Q policies (the planner's export:
tests/test_export_planner.py) and the numpy + onnxruntime example (crowdrl/onnx_example.py, run in a checkout
by experiments/onnx_example.py): the exported model acts as the library's greedy actor, the example runs
where torch and crowdrl cannot be imported, bad arguments exit 2 naming the argument."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

onnx = pytest.importorskip("onnx")
onnxruntime = pytest.importorskip("onnxruntime")

from crowdrl_testing import fresh_network  # noqa: E402
from crowdrl_testing.cli import run_cli  # noqa: E402
from crowdrl.envs.robot_centric import robot_centric  # noqa: E402
from crowdrl.export import ENTITY_INPUTS, INPUTS, export_onnx  # noqa: E402
from crowdrl.sim.kinematics import action_table  # noqa: E402
from crowdrl.training.checkpoint import config_fingerprint, save_checkpoint  # noqa: E402
from crowdrl.training.config import sees_obstacles, to_dict  # noqa: E402
from crowdrl.training.validation import validate  # noqa: E402
from crowdrl.training.factories import make_actor, make_env  # noqa: E402
from crowdrl.training.pipeline import TEST_SEED  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXPORT = [sys.executable, str(ROOT / "experiments" / "export.py")]
EXAMPLE = ROOT / "src" / "crowdrl" / "onnx_example.py"  # shipped in the package, run by its path
SHORTCUT = ROOT / "experiments" / "onnx_example.py"  # the checkout's way to run it
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src")}

# a default run, the crowd sizes that vary (the mask is read), the other encoders, a noisy head
CASES = {
    "sgd3qn": {},
    "sgd3qn-variable": {"env": {"num_humans": 6, "min_humans": 2}},
    "sarl-variable": {"encoder": {"name": "sarl"}, "env": {"num_humans": 6, "min_humans": 2}},
    "mp_rgl": {"encoder": {"name": "mp_rgl"}, "env": {"num_humans": 5}},
    "lstm_rl-variable": {"encoder": {"name": "lstm_rl"}, "env": {"num_humans": 6, "min_humans": 2}},
    "noisy": {"exploration": {"name": "noisy"}, "env": {"num_humans": 5}},
    # trained among obstacles: entity tokens (humans, then the observed edges)
    "sgd3qn-room": {"env": {"scenario": "room", "num_humans": 5}},
    "lstm_rl-doorway": {"encoder": {"name": "lstm_rl"}, "env": {"scenario": "doorway", "num_humans": 4}},
}


def make_run_folder(folder: Path, overrides: dict, seed: int = 0) -> Path:
    """A run folder holding ``checkpoints/best.pt`` of a fresh network of ``overrides``' config (greedy Q
    actor unless ``overrides`` say otherwise: planning is the schema's default)."""
    run = validate({"planning": {"enabled": False}, **overrides})
    torch.manual_seed(seed)
    config = to_dict(run)
    save_checkpoint(folder / "checkpoints" / "best.pt", {"net": fresh_network(run).state_dict(), "config": config,
                                                          "frames": 0, "val": {}}, config_fingerprint(config))
    return folder


def load_example():
    spec = importlib.util.spec_from_file_location("onnx_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """(the run folder, its exported model) of a default SG-D3QN config."""
    base = tmp_path_factory.mktemp("export")
    folder = make_run_folder(base / "run", {})
    export_onnx(folder, base / "policy.onnx")
    return folder, base / "policy.onnx"


@pytest.mark.parametrize("case", list(CASES))
def test_the_exported_model_acts_as_the_library_actor_on_test_cases(tmp_path, case):
    """1000 observations of the test stream (100 test cases x 10 steps, test seed 0): the same greedy
    actions as the library's Q actor, Q within 1e-4, and each action's row of the action table."""
    folder = make_run_folder(tmp_path / "run", CASES[case])
    info = export_onnx(folder, tmp_path / "policy.onnx")
    from crowdrl.training.pipeline import load_trained_network

    run, net, _ = load_trained_network(folder)
    env = make_env(run, split="test", num_envs=100, seed=TEST_SEED)
    actor = make_actor(run, env, net)
    with torch.no_grad():
        td = env.rollout(10, actor, break_when_any_done=False).reshape(-1)
    assert td.shape == (1000,)
    session = onnxruntime.InferenceSession(str(info.path), providers=["CPUExecutionProvider"])
    inputs = ENTITY_INPUTS if sees_obstacles(run) else INPUTS
    q, action, command = session.run(None, {k: td.get(k).numpy() for k in inputs})
    lib_q, lib_action = td.get("action_value").numpy(), td.get("action").numpy()
    np.testing.assert_allclose(q, lib_q, atol=1e-4, rtol=0)
    differ = np.flatnonzero(action != lib_action)
    rows = np.arange(len(lib_q))
    gaps = np.abs(lib_q[rows, lib_action] - lib_q[rows, action])[differ]
    assert (gaps < 1e-5).all(), f"{len(differ)} greedy actions differ, not on ties: Q gaps {gaps[:5]}"
    assert len(differ) <= 2, f"{len(differ)} greedy actions differ (near-ties)"
    np.testing.assert_array_equal(command, action_table(1.0).numpy()[action])
    rows = session.get_inputs()[1].shape[1]
    if sees_obstacles(run):
        assert session.get_inputs()[1].shape[2] == 10 and "entities_rc [B,N+K,10]" in info.metadata["crowdrl.inputs"]
    fixed = run.env.num_humans + (env.base_env.config.num_obstacle_tokens if sees_obstacles(run) else 0)
    assert rows == (fixed if case.startswith("lstm_rl") else "entities" if sees_obstacles(run) else "humans")


def test_the_example_transform_equals_the_librarys():
    example = load_example()
    g = torch.Generator().manual_seed(1)
    robot = torch.randn(64, 9, generator=g, dtype=torch.float64) * 4
    robot[:, 8] = (torch.rand(64, generator=g, dtype=torch.float64) * 2 - 1) * 3 * torch.pi  # any heading
    robot[:2, 8] = torch.tensor([torch.pi, -torch.pi])  # the wrap's edges
    humans = torch.randn(64, 7, 5, generator=g, dtype=torch.float64) * 4
    want = robot_centric(robot, humans)
    got = example.robot_centric(robot.numpy(), humans.numpy())
    for w, x in zip(want, got):
        np.testing.assert_allclose(x, w.numpy(), atol=1e-12, rtol=0)


@pytest.mark.parametrize("script", [EXAMPLE, SHORTCUT], ids=["packaged", "checkout-shortcut"])
def test_the_example_runs_where_torch_and_crowdrl_cannot_be_imported(exported, tmp_path, script):
    """Modules named torch, crowdrl, tensordict and torchrl that raise ImportError come first on the
    path: the example (the packaged file, or the checkout's shortcut to it) imports only numpy and
    onnxruntime, and acts as the library does."""
    folder, model = exported
    blocked = tmp_path / "blocked"
    blocked.mkdir()
    for name in ("torch", "crowdrl", "tensordict", "torchrl"):
        (blocked / f"{name}.py").write_text(f"raise ImportError('{name} is blocked in this test')\n")
    driver = (
        "import runpy, sys\n"
        "for name in ('torch', 'crowdrl'):\n"
        "    try:\n"
        "        __import__(name)\n"
        "    except ImportError:\n"
        "        pass\n"
        "    else:\n"
        "        raise SystemExit(f'{name} could be imported')\n"
        f"sys.argv = [{str(script)!r}, {str(model)!r}, '--json']\n"
        f"runpy.run_path({str(script)!r}, run_name='__main__')\n"
        "assert 'torch' not in sys.modules and 'crowdrl' not in sys.modules\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-c", driver], env={**env, "PYTHONPATH": str(blocked)}, cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])

    # the same scene through the library: its transform, its greedy actor
    from crowdrl.training.pipeline import load_trained_network

    example = load_example()
    robot = torch.tensor([0.0, -4.0, 0.0, 0.5, 0.3, 0.0, 4.0, 1.0, np.pi / 2])
    humans = torch.tensor([[0.3, -2.5, 0.0, -0.8, 0.3], [-1.5, -1.0, 0.6, 0.0, 0.3], [2.0, 1.0, 0.0, 0.0, 0.3]])
    assert "robot = np.array([0.0, -4.0, 0.0, 0.5, 0.3, 0.0, 4.0, 1.0, math.pi / 2])" in EXAMPLE.read_text()
    _, net, _ = load_trained_network(folder)
    with torch.no_grad():
        q = net(*robot_centric(robot[None], humans[None]))
    assert result["action"] == int(q.argmax()) and abs(result["q"] - float(q.max())) < 1e-4
    speed, rotation = action_table(1.0)[result["action"]].tolist()
    assert (result["speed"], result["rotation"]) == pytest.approx((speed, rotation))
    heading = np.pi / 2 + rotation
    assert result["velocity_world"] == pytest.approx([speed * np.cos(heading), speed * np.sin(heading)])
    feeds = example.observation(robot.numpy(), humans.numpy())
    assert feeds["humans_mask"].all() and feeds["robot_rc"].dtype == np.float32


def test_the_example_refuses_a_model_trained_among_obstacles_naming_the_inputs_it_builds(tmp_path):
    folder = make_run_folder(tmp_path / "run", CASES["sgd3qn-room"])
    export_onnx(folder, tmp_path / "room.onnx", check=False)
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(tmp_path / "room.onnx")], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "model:" in proc.stderr and "entities_rc" in proc.stderr
    assert "this example builds the inputs of a planner" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_planning_checkpoint_exports_its_q_policy_alone_with_planning_depth_0_and_says_so(tmp_path):
    """planning_depth=0: the greedy Q policy of a planning checkpoint (its planner: tests/test_export_planner.py),
    printed and labelled in the metadata as acting differently."""
    folder = make_run_folder(tmp_path / "run", {"planning": {"enabled": True}, "env": {"num_humans": 5}})
    work = tmp_path / "work"
    work.mkdir()
    proc = run_cli("export.py", f"checkpoint={folder}", "out=policy.onnx", "planning_depth=0", cwd=work)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "GREEDY Q ONLY: planning_depth=0 drops the online planner" in proc.stdout
    assert f"run it without torch: python {EXAMPLE} " in proc.stdout  # the example's path, wherever crowdrl is
    assert sorted(p.name for p in work.iterdir()) == ["policy.onnx"], "no Hydra folder or log beside it"
    meta = {p.key: p.value for p in onnx.load(work / "policy.onnx").metadata_props}
    assert meta["crowdrl.planning"].startswith("dropped (planning_depth=0): the checkpoint acts with online planning")
    assert meta["crowdrl.policy"] == "greedy_q" and meta["crowdrl.observation"] == "robot_centric"
    assert meta["crowdrl.encoder"] == "sgd3qn" and json.loads(meta["crowdrl.config"])["planning"]["enabled"]
    assert export_onnx(folder, tmp_path / "again.onnx", check=False, planning={"depth": 0}).planning_dropped


class _Payload:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


@pytest.mark.parametrize("bad", ["missing", "corrupt", "unsafe", "out", "format", "unread key", "check", "exists"])
def test_bad_arguments_exit_2_naming_the_argument(exported, tmp_path, bad):
    folder, _ = exported
    args, words = [f"checkpoint={folder}", f"out={tmp_path / 'p.onnx'}"], []
    if bad == "missing":
        args[0], words = f"checkpoint={tmp_path / 'nope.pt'}", ["checkpoint: no checkpoint at", "nope.pt"]
    elif bad == "corrupt":
        (tmp_path / "bad.pt").write_bytes((folder / "checkpoints" / "best.pt").read_bytes()[:2000])
        args[0], words = f"checkpoint={tmp_path / 'bad.pt'}", ["checkpoint:", "bad.pt", "truncated or corrupt"]
    elif bad == "unsafe":
        torch.save({"format": 1, "net": _Payload(tmp_path / "marker")}, tmp_path / "evil.pt")
        args[0], words = f"checkpoint={tmp_path / 'evil.pt'}", ["checkpoint:", "evil.pt was refused"]
    elif bad == "out":
        (tmp_path / "file").write_text("")
        args[1], words = f"out={tmp_path / 'file' / 'p.onnx'}", ["out: cannot write", "is a file, not a folder"]
    elif bad == "check":  # not a bool: was taken as true (the typed schema refuses it)
        args.append("check=maybe")
        words = ["export.py: check:", "'maybe' is not a valid bool"]
    elif bad == "exists":  # was overwritten silently
        (tmp_path / "p.onnx").write_text("mine")
        words = ["out:", "p.onnx exists; pass overwrite=true"]
    elif bad == "format":
        args.append("format=tflite")
        words = ["format: got 'tflite'; allowed: onnx"]
    else:  # a misspelt key added with + would otherwise be silently ignored
        args.append("+opsett=18")
        words = ["opsett: not read by export.py (unknown key); allowed: checkpoint, out, format, opset, check, overwrite"]
    proc = run_cli("export.py", *args, cwd=tmp_path)  # in this process: the real one is tests/test_one_line_errors.py's
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert all(w in proc.stderr for w in words), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    if bad == "exists":
        assert (tmp_path / "p.onnx").read_text() == "mine"
    else:
        assert not (tmp_path / "p.onnx").exists()
    assert not (tmp_path / "marker").exists()


def test_export_traces_the_compiled_attention_kernel_as_plain_torch(exported, tmp_path, monkeypatch):
    """With the compiled pairwise kernels (the library's default outside tests), tracing calls the
    kernel's plain function: torch.jit cannot trace a torch.compile'd one."""
    from crowdrl.models import sgd3qn

    folder, reference = exported
    monkeypatch.setattr(sgd3qn, "PAIRWISE", sgd3qn.PairwiseKernels("compiled"))
    info = export_onnx(folder, tmp_path / "policy.onnx", check=False)  # no torch forward: nothing compiles
    feeds = load_example().observation(np.array([0.0, -4.0, 0.0, 0.5, 0.3, 0.0, 4.0, 1.0, 1.5]),
                                       np.array([[0.3, -2.5, 0.0, -0.8, 0.3], [1.0, 1.0, 0.0, 0.0, 0.3]]))
    got, want = (onnxruntime.InferenceSession(str(p), providers=["CPUExecutionProvider"]).run(["q_values"], feeds)[0]
                 for p in (info.path, reference))
    np.testing.assert_array_equal(got, want)


def test_lstm_rls_order_of_humans_with_ties_is_the_same_in_onnx():
    """ONNX has no stable sort: the export sorts with TopK, whose ties keep the lower index first."""
    import io
    import warnings

    from crowdrl.models.lstm_rl import sort_far_to_near

    class Order(torch.nn.Module):
        def forward(self, humans, mask):
            return sort_far_to_near(humans, mask)[0]

    humans = torch.zeros(1, 6, 5)
    humans[0, :, 0] = torch.tensor([1.0, 2.0, 1.0, 2.0, 1.0, 3.0])  # equal distances
    humans[0, :, 4] = torch.arange(6.0)  # tags the rows
    mask = torch.tensor([[True, True, False, True, True, False]])  # the absent: all at infinity
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(Order(), (humans, mask), buf, input_names=["humans", "mask"], dynamo=False)
    got = onnxruntime.InferenceSession(buf.getvalue(), providers=["CPUExecutionProvider"]).run(
        None, {"humans": humans.numpy(), "mask": mask.numpy()})[0]
    np.testing.assert_array_equal(got, sort_far_to_near(humans, mask)[0].numpy())


@pytest.mark.parametrize("value", ["0", "abc", "-0.25", "nan", None])
def test_the_example_refuses_bad_metadata_or_a_non_model_in_one_line(exported, tmp_path, capsys, value):
    """A time step of "0" or "abc" in the model's metadata (or a text file given as the model): exit 2
    naming the field (or the model), not a ZeroDivisionError or onnxruntime's traceback."""
    import onnx

    path = tmp_path / "p.onnx"
    if value is None:
        path.write_text("not a model\n")
    else:
        model = onnx.load(str(exported[1]))
        (entry,) = [m for m in model.metadata_props if m.key == "crowdrl.time_step"]
        entry.value = value
        onnx.save(model, str(path))
    with pytest.raises(SystemExit) as stop:
        load_example().main([str(path)])
    err = capsys.readouterr().err
    assert stop.value.code == 2
    expected = ("not an ONNX model" if value is None
                else f"crowdrl.time_step: must be a finite number of seconds > 0, got {value!r}")
    assert expected in err and "Traceback" not in err, err


def test_the_example_refuses_non_finite_states_and_runs_with_no_human_in_view(exported):
    """Issue 52 (D13): a NaN or inf state is refused naming the field (not NaN Q values and action 0); with no
    human in view the example passes one absent row (not onnxruntime's Reshape error), which the model ignores."""
    example = load_example()
    robot = np.array([0.0, -4.0, 0.0, 0.5, 0.3, 0.0, 4.0, 1.0, np.pi / 2])
    humans = np.array([[0.3, -2.5, 0.0, -0.8, 0.3], [-1.5, -1.0, 0.6, 0.0, 0.3]])
    for field, value in ((2, np.nan), (8, np.inf), (5, -np.inf)):
        bad = robot.copy()
        bad[field] = value
        with pytest.raises(ValueError, match=f"robot: {example.ROBOT_FIELDS[field]} not finite"):
            example.observation(bad, humans)
    bad = humans.copy()
    bad[1, 4] = np.inf
    with pytest.raises(ValueError, match=r"humans: row\(s\) \[1\] not finite \(NaN or inf; row 1: radius\)"):
        example.observation(robot, bad)
    with pytest.raises(ValueError, match="humans: must be rows of the 5 values"):
        example.observation(robot, np.zeros(7))
    session = onnxruntime.InferenceSession(str(exported[1]), providers=["CPUExecutionProvider"])
    alone = example.observation(robot, np.zeros((0, 5)))
    assert alone["humans_rc"].shape == (1, 1, 5) and not alone["humans_mask"].any()
    q, action, command = session.run(None, alone)
    assert np.isfinite(q).all() and np.isfinite(command).all()
    padded = example.observation(robot, [], slots=4)  # more absent rows, whatever they hold: the same answer
    padded["humans_rc"][:] = np.random.default_rng(0).normal(size=padded["humans_rc"].shape)
    np.testing.assert_allclose(session.run(None, padded)[0], q, atol=1e-6, rtol=0)
