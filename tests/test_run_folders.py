"""Run folders never lie (docs/reliability.md): a refused run changes nothing in a folder and removes only what
it created; one writer per folder (and per reproduce.py out=), locked before the first write; a
finished run stays finished; default folders are unique; seeds stay within 0..2**63-1; settings
that would exhaust memory, bad evaluate.py input and non-finite weights or simulator inputs are
refused by name; JSON records are strict and files get open()'s mode."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from crowdrl_testing.cli import run_cli
from crowdrl.training.config import ConfigError, RunConfig

from crowdrl.training.validation import validate

ROOT = Path(__file__).resolve().parents[1]
TRAIN = [sys.executable, str(ROOT / "experiments" / "train.py")]
ENV = {**os.environ, "WANDB_MODE": "offline"}


def folder_state(folder: Path) -> dict[str, str]:
    """Every file and folder below ``folder``, a file by the hash of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(folder.rglob("*"))}


def train(*args: str, timeout: int = 300, real_process: bool = False) -> subprocess.CompletedProcess:
    """train.py with ``args``: in this process (a refusal or a finished run's report), or a real one (training)."""
    if not real_process:
        return run_cli("train.py", *args)
    return subprocess.run([*TRAIN, *args], env=ENV, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    """A finished smoke run of seed 0 made by train.py (copy it before changing it)."""
    run = tmp_path_factory.mktemp("runs") / "s0"
    proc = train("preset=smoke", "logger=csv", "logger.render=false", "seed=0", f"hydra.run.dir={run}", real_process=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (run.parent / "output.txt").write_text(proc.stdout + proc.stderr)
    return run


def test_a_runs_console_output_names_its_folder_first_and_shows_no_nan_or_colour_codes(finished_run):
    """Issue 53 item 6: the run folder is printed before training starts; a smoke run whose test reached no goal
    printed "nav time nan s"; torchrl's INFO line showed raw ANSI codes in a pipe."""
    output = (finished_run.parent / "output.txt").read_text()
    lines = output.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("run folder: "))
    test = next(i for i, line in enumerate(lines) if line.startswith("test ("))
    assert first < test - 1 and str(finished_run.resolve()) in lines[first]
    assert "\033[" not in output and "\x1b" not in output and not re.search(r"\bnan\b", output), output[-2000:]


@pytest.mark.parametrize("kind", ["user_files", "empty"])
def test_a_config_error_leaves_an_existing_folder_as_it_was(tmp_path, kind):
    """`train.lr=-1 hydra.run.dir=u`: u (the user's train.log and .hydra/mine.txt, or an empty
    folder the user made) is neither deleted nor written to."""
    user = tmp_path / "u"
    user.mkdir()
    if kind == "user_files":
        (user / ".hydra").mkdir()
        (user / ".hydra" / "mine.txt").write_text("mine")
        (user / "train.log").write_text("my log")
    before = folder_state(user)
    proc = train("train.lr=-1", f"hydra.run.dir={user}")
    assert proc.returncode == 2 and "train.lr" in proc.stderr, proc.stderr[-2000:]
    assert user.is_dir() and folder_state(user) == before


def test_a_config_error_removes_only_the_folders_the_run_created(tmp_path):
    """The folders Hydra created for a refused run are removed, deepest first, up to one that existed."""
    from crowdrl.training import run_folder

    made = tmp_path / "new" / "a" / "b"
    run_folder.note_new_folders(made)
    made.mkdir(parents=True)
    run_folder.discard_new_folders(made)
    assert not (tmp_path / "new").exists() and tmp_path.is_dir()

    kept = tmp_path / "k" / "c"
    run_folder.note_new_folders(kept)
    kept.mkdir(parents=True)
    (kept / "x.txt").write_text("written by someone else meanwhile")
    run_folder.discard_new_folders(kept)  # not empty: left alone
    assert (kept / "x.txt").read_text().startswith("written")


def test_a_second_run_into_a_locked_folder_is_refused_before_any_write(finished_run, tmp_path):
    """The first run holds the lock; a second start (seed 5) into its folder writes no config.yaml,
    no .hydra/ file: the folder is byte for byte as it was."""
    from crowdrl.training.pipeline import lock_run_dir

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = folder_state(run)
    holder = lock_run_dir(run)  # what the first, still running, writer holds
    try:
        proc = train("preset=smoke", "logger=csv", "seed=5", f"hydra.run.dir={run}", real_process=True)  # another process
    finally:
        holder.release()
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert folder_state(run) == before
    assert "another process" in proc.stderr  # the lock is the first check, before the fingerprint's


def test_run_training_calls_prepare_only_once_the_lock_is_held(tmp_path):
    from crowdrl.training.pipeline import RunFolderBusy, lock_run_dir, run_training

    holder = lock_run_dir(tmp_path)
    called = []
    with pytest.raises(RunFolderBusy):
        run_training(validate(RunConfig()), tmp_path, prepare=lambda: called.append(1))
    holder.release()
    assert not called and [p.name for p in tmp_path.iterdir()] == [".lock"]


def test_a_refused_fresh_start_into_another_run_changes_nothing(finished_run, tmp_path):
    """`seed=1 hydra.run.dir=<a seed-0 run>`: refused (rc 2) with config.yaml and .hydra/* unchanged."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = folder_state(run)
    proc = train("preset=smoke", "logger=csv", "seed=1", f"hydra.run.dir={run}")
    assert proc.returncode == 2 and "another configuration" in proc.stderr, proc.stderr[-2000:]
    assert folder_state(run) == before


@pytest.mark.parametrize("kind", ["user_files", "empty"])
def test_a_folder_not_made_by_crowdrl_is_refused_unless_empty(tmp_path, kind):
    from crowdrl.training.pipeline import run_training
    from crowdrl.training.run_folder import RunFolderRefused, check_run_folder

    folder = tmp_path / "mine"
    folder.mkdir()
    if kind == "empty":
        check_run_folder(folder)  # an empty folder is fine
        return
    (folder / "notes.txt").write_text("mine")
    (folder / "config.yaml").write_text("seed: 3\n")
    before = folder_state(folder)
    with pytest.raises(RunFolderRefused, match="no crowdrl run folder"):
        run_training(validate(RunConfig()), folder)
    assert folder_state(folder) == before


@pytest.mark.parametrize("how", ["resume", "run_dir"])
def test_a_finished_run_started_again_reports_complete_and_changes_nothing(finished_run, tmp_path, how):
    """`resume=<finished run>` and `hydra.run.dir=<finished run>`: rc 0, "completed", no second test
    row in scalars.jsonl, status.json and summary.json untouched."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    before = folder_state(run)
    args = [f"resume={run}"] if how == "resume" else ["preset=smoke", "logger=csv", "seed=0", f"hydra.run.dir={run}"]
    proc = train(*args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [json.loads(line) for line in (run / "scalars.jsonl").read_text().splitlines()]
    assert sum(r["kind"] == "test" for r in rows) == 1
    assert folder_state(run) == before
    assert "holds a completed run" in proc.stdout and "success" in proc.stdout


def test_default_folders_of_every_entry_point_carry_a_unique_part():
    """Evaluations (and demo runs) started in the same second never share a folder."""
    from hydra import compose, initialize_config_dir

    import crowdrl.cli.evaluate  # noqa: F401  registers evaluate's typed schema (evaluate_schema)
    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()
    dirs = []
    for _ in range(2):
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            cfg = compose(config_name="evaluate", return_hydra_config=True)
        dirs.append(str(cfg.hydra.run.dir))
    assert all(re.fullmatch(r"runs/eval-\d{8}-\d{6}-[0-9a-f]{6}", d) for d in dirs), dirs
    assert dirs[0] != dirs[1]
    import demo
    first, second = demo.default_out(RunConfig()), demo.default_out(RunConfig())
    assert first != second and re.fullmatch(r"demo-\d{8}-\d{6}-circle-s0-[0-9a-f]{6}", first.name), first


def test_seeds_beyond_int64_are_refused_naming_the_key():
    big = 2**63
    with pytest.raises(ConfigError, match=r"^seed: must lie in 0\.\.2\*\*63-1"):
        validate(RunConfig(seed=big))
    assert validate(RunConfig(seed=big - 1)).seed == big - 1
    from crowdrl.agents import evaluate_spec

    with pytest.raises(ValueError, match=r"^eval\.seed: must lie in 0\.\.2\*\*63-1"):
        evaluate_spec(policy="orca", seed=5 + 2**64, episodes=1)


def test_the_gymnasium_face_refuses_seeds_it_would_reduce_modulo_2_64():
    from crowdrl.gym_env import CrowdNavGymEnv

    env = CrowdNavGymEnv()
    for seed in (2**63, 5 + 2**64, -1):
        with pytest.raises(ValueError, match=r"0\.\.2\*\*63-1"):
            env.reset(seed=seed)
    env.reset(seed=2**63 - 1)


# ----------------------------------------------------------------------------- resource bounds (defect 5)


def _compose(*overrides: str):
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from crowdrl.training.resolvers import register_resolvers

    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    register_resolvers()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.mark.parametrize("override, key", [("planning.depth=7", "planning.depth"),
                                           ("train.buffer_size=10000000000", "train.buffer_size")])
def test_settings_that_exhaust_memory_are_refused_at_once_naming_the_key(override, key):
    import time

    cfg = _compose(override)
    start = time.perf_counter()
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)}.*GiB.*available.*lower {re.escape(key)}"):
        validate(cfg)
    assert time.perf_counter() - start < 1.0


def test_train_py_refuses_a_planner_that_cannot_fit_with_exit_code_2(tmp_path):
    proc = train("planning.depth=7", f"hydra.run.dir={tmp_path / 'r'}")
    assert proc.returncode == 2 and "planning.depth" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("preset", ["smoke", "demo", "episodes", "paper"])
@pytest.mark.parametrize("encoder", ["sgd3qn", "sarl", "lstm_rl", "mp_rgl"])
def test_every_preset_passes_the_resource_checks(preset, encoder, monkeypatch):
    """On a machine with 16 GiB available (faked: the test does not depend on this machine's free memory)."""
    from crowdrl.training import resources

    monkeypatch.setattr(resources, "available_memory", lambda device="cpu": 16 * 2**30)
    run = validate(_compose(f"preset={preset}", f"encoder={encoder}"))
    assert run.planning.enabled  # conf/config.yaml plans by default: the planner's bound is checked too


def test_the_resource_checks_compare_with_the_memory_available(monkeypatch):
    from crowdrl.training import resources

    run = validate(_compose("preset=demo"))
    need = resources.buffer_bytes(run) + resources.planner_bytes(run)
    monkeypatch.setattr(resources, "available_memory", lambda device="cpu": need)
    validate(run)  # exactly enough
    monkeypatch.setattr(resources, "available_memory", lambda device="cpu": resources.buffer_bytes(run))
    with pytest.raises(ConfigError, match=r"^planning\.depth/planning\.width: the planner expands 10000 states per "
                                          r"step .*B = 1000.* of up to 10 humans"):
        validate(run)
    saved = dataclasses.replace(run, train=dataclasses.replace(run.train, save_buffer=True))
    monkeypatch.setattr(resources, "available_memory", lambda device="cpu": 2 * resources.buffer_bytes(run))
    with pytest.raises(ConfigError, match=r"^train\.buffer_size: .*x3 with train\.save_buffer=true.*save_buffer=false"):
        validate(saved)
    monkeypatch.setattr(resources, "available_memory", lambda device="cpu": None)  # unknown: no refusal
    validate(saved)
    with_planning = validate(_compose("preset=demo", "planning.depth=2"))
    assert resources.planned_states(with_planning) == 1000 * (10 + 100)
    assert resources.planned_states(validate(_compose("preset=demo", "planning.enabled=false"))) == 0


@pytest.mark.parametrize("overrides", [["planning.enabled=false"], ["planning.enabled=true"],
                                       ["planning.enabled=false", "env.min_humans=5", "env.max_humans=20"],
                                       ["planning.enabled=false", "learner=plain"], ["learner=plain"],
                                       ["env.lidar_rays=16"], ["env.lidar_rays=16", "encoder.lidar=mlp"],
                                       ["env=corridor", "env.num_humans=5", "env.lidar_rays=16", "encoder.lidar=conv"]])
def test_transition_bytes_is_what_the_replay_buffer_stores(overrides):
    """The estimate behind train.buffer_size's bound, against a real buffer's stored transition (the keys the
    trainer stores: the networks', the predictor's, the counterfactual experience's)."""
    from crowdrl.models import make_q_network
    from crowdrl.training.resources import transition_bytes
    from crowdrl.training.acting import make_acting
    from crowdrl.training.facts import RunFacts
    from crowdrl.training.factories import make_buffer, make_env, make_update_part

    run = validate(_compose("preset=smoke", "train.num_envs=2", *overrides))
    facts = RunFacts.of(run)
    batch = make_env(run).rollout(3, break_when_any_done=False)
    buffer = make_buffer(run.train, facts)
    part = make_update_part(run.train, make_q_network(run.encoder.name), facts)
    acting = make_acting(run.planning, facts, train=run.train, encoder=run.encoder.name, learn=True)
    buffer.extend(batch.select(*facts.replay_keys(acting, part)))
    one = buffer.storage[0]
    assert transition_bytes(run) == sum(v.numel() * v.element_size() for v in one.values(True, True))


# ----------------------------------------------------------------------------- smaller (defect 9)


def test_run_dir_is_refused_naming_the_key_but_null_still_loads():
    with pytest.raises(ConfigError, match=r"^run_dir: is not used .*hydra\.run\.dir"):
        validate(RunConfig(run_dir="runs/x"))
    assert validate({"run_dir": None, "seed": 3}).seed == 3  # the config.yaml of older run folders
    repo_sets_it = subprocess.run(["git", "grep", "-nE", r"run_dir[:=] *[^ n]", "--", "conf"], cwd=ROOT,
                                  capture_output=True, text=True)
    assert repo_sets_it.stdout == ""


def _strict(text: str):
    def refuse(name: str):
        raise ValueError(f"bare {name} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_json_records_are_strict_with_null_for_undefined_metrics(tmp_path):
    from crowdrl.evaluation.report import markdown_table, write_records
    from crowdrl.files import dumps_json

    assert dumps_json({"a": float("nan"), "b": [float("inf"), 1.5, (float("-inf"),)]}, indent=None) == \
        '{"a": null, "b": [null, 1.5, [null]]}'
    record = {"success_rate": 0.0, "collision_rate": 1.0, "timeout_rate": 0.0, "navigation_time": float("nan"),
              "average_return": -0.25, "discomfort_frequency": 0.0, "min_separation": float("inf"),
              "episodes": 2, "seed": 0, "scenario": "circle", "policy": "x"}
    json_path, _ = write_records(tmp_path, [record])
    back = _strict(json_path.read_text())["records"][0]
    assert back["navigation_time"] is None and back["min_separation"] is None
    assert "| – |" in markdown_table([back])  # the readers take null as undefined


def test_a_runs_json_files_are_strict_and_read_back(finished_run):
    from crowdrl.training.pipeline import completed_summary

    for name in ("status.json", "summary.json", "eval.json"):
        _strict((finished_run / name).read_text())
    assert completed_summary(finished_run)["test"]["metrics"]["episodes"] == 8


def test_the_scalar_log_is_strict_json_lines_through_a_resume_truncation(tmp_path):
    """A non-finite scalar (a loss that blew up, an undefined mean) is ``null`` in ``scalars.jsonl``,
    in the rows a resume keeps too; ``scalars.csv`` leaves its cell empty."""
    from crowdrl.training.scalars import ScalarLog

    log = ScalarLog(tmp_path)
    log.log({"frames": 1, "train/loss": float("nan"), "train/q": 1.5})
    log.log({"frames": 2, "train/loss": float("inf"), "train/q": 2.5})
    assert log.truncate_after(1) == 1
    log.log({"frames": 3, "train/loss": float("-inf")})
    log.close()
    rows = [_strict(line) for line in (tmp_path / "scalars.jsonl").read_text().splitlines()]
    assert rows == [{"frames": 1, "train/loss": None, "train/q": 1.5}, {"frames": 3, "train/loss": None}]
    assert (tmp_path / "scalars.csv").read_text().splitlines() == ["frames,train/loss,train/q", "1,,1.5", "3,,"]


def test_atomic_writes_leave_the_mode_a_plain_open_would(tmp_path):
    from crowdrl.files import atomic_write_bytes

    old = os.umask(0o022)
    try:
        atomic_write_bytes(tmp_path / "a.json", b"{}")
        open(tmp_path / "plain.json", "w").close()
        assert (tmp_path / "a.json").stat().st_mode & 0o777 == (tmp_path / "plain.json").stat().st_mode & 0o777 == 0o644
        os.umask(0o027)
        atomic_write_bytes(tmp_path / "b.json", b"{}")
        assert (tmp_path / "b.json").stat().st_mode & 0o777 == 0o640
        (tmp_path / "a.json").chmod(0o600)  # an existing file keeps its mode, as open(path, "w") leaves it
        atomic_write_bytes(tmp_path / "a.json", b"[]")
        assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o600 and (tmp_path / "a.json").read_bytes() == b"[]"
    finally:
        os.umask(old)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json", "plain.json"]  # no temp file left


def test_a_writer_that_fails_leaves_the_old_file_and_no_temp_file(tmp_path):
    from crowdrl.files import atomic_write_with

    path = tmp_path / "table.csv"
    path.write_text("old")

    def half_then_fail(tmp):
        tmp.write_text("half a ta")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write_with(path, half_then_fail, suffix=".csv")
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["table.csv"]
    seen = []
    atomic_write_with(path, lambda tmp: (seen.append(tmp.suffix), tmp.write_text("new")), suffix=".csv")
    assert path.read_text() == "new" and seen == [".csv"] and [p.name for p in tmp_path.iterdir()] == ["table.csv"]


def test_the_raw_simulator_refuses_non_finite_inputs_naming_them():
    import math

    import torch

    from crowdrl.sim import crowd
    from crowdrl.sim.config import CrowdConfig
    from crowdrl.sim.orca import OrcaParams, orca_velocities
    from crowdrl.sim.rng import episode_keys
    from crowdrl.sim.scenarios import initial_states

    cfg = CrowdConfig()
    state = initial_states(cfg, episode_keys("train", 0, torch.arange(2)))
    for bad in (math.nan, math.inf):
        with pytest.raises(ValueError, match="^robot_velocity holds NaN or infinite"):
            crowd.step(cfg, state, torch.tensor([[bad, 0.0], [0.0, 0.0]]))
    with pytest.raises(ValueError, match="^robot_heading holds NaN or infinite"):
        crowd.step(cfg, state, torch.zeros(2, 2), torch.tensor([0.0, math.nan]))
    with pytest.raises(ValueError, match=r"^state\.robot_goal holds NaN"):
        crowd.step(cfg, state.replace(robot_goal=torch.full_like(state.robot_goal, math.nan)), torch.zeros(2, 2))
    crowd.step(cfg, state, torch.zeros(2, 2))  # finite: fine
    p = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    r = torch.full((1, 3), 0.3)
    kw = dict(params=OrcaParams(time_step=0.25, neighbor_dist=10.0, max_neighbors=10, time_horizon=5.0))
    assert orca_velocities(p, torch.zeros_like(p), torch.zeros_like(p), r, r, **kw).isfinite().all()
    for name in ("positions", "velocities", "pref_velocities"):
        args = {"positions": p, "velocities": torch.zeros_like(p), "pref_velocities": torch.zeros_like(p)}
        args[name] = args[name].clone()
        args[name][0, 1, 0] = math.inf
        with pytest.raises(ValueError, match=f"^{name} holds NaN or infinite"):
            orca_velocities(args["positions"], args["velocities"], args["pref_velocities"], r, r, **kw)
    with pytest.raises(ValueError, match="^max_speed holds NaN"):
        orca_velocities(p, torch.zeros_like(p), torch.zeros_like(p), r, torch.full((1, 3), math.nan), **kw)


# ----------------------------------------------------------------------------- evaluate.py (defect 8)

@pytest.mark.parametrize("args, named", [(["threads=0"], "threads"), (["+eval.episods=5"], "eval.episods"),
                                         (["+encoder=sarl"], "encoder"), (["env=circle", "env.num_humans=20"],
                                                                          "env.num_humans")])
def test_evaluate_py_refuses_bad_threads_and_unread_keys_naming_them(tmp_path, args, named):
    proc = run_cli("evaluate.py", "policy=orca", "eval.episodes=2", *args, f"hydra.run.dir={tmp_path / 'e'}")
    assert proc.returncode == 2 and named in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "e").exists()  # the folder Hydra made for the refused evaluation is gone


def test_a_refused_evaluation_leaves_a_folder_that_existed_as_it_was(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's")
    before = {p.relative_to(mine): p.read_bytes() for p in mine.rglob("*") if p.is_file()}
    proc = run_cli("evaluate.py", "policy=orca", "eval.episodes=2", "threads=0", f"hydra.run.dir={mine}")
    assert proc.returncode == 2 and "threads" in proc.stderr
    assert {p.relative_to(mine): p.read_bytes() for p in mine.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]


def test_a_checkpoint_with_non_finite_weights_is_refused_naming_it_and_the_parameter(finished_run, tmp_path):
    import torch

    from crowdrl.training.checkpoint import CheckpointError
    from crowdrl.agents import evaluate_spec

    for entry, value, stem, said in (("net", float("nan"), "nan", "Q network's"),
                                     ("predictor", float("inf"), "inf", "crowd predictor's")):
        data = torch.load(finished_run / "checkpoints" / "best.pt", weights_only=False)
        name = next(k for k, v in data[entry].items() if v.is_floating_point())
        data[entry][name] = data[entry][name].clone().fill_(value)
        torch.save(data, tmp_path / f"{stem}.pt")
        with pytest.raises(CheckpointError, match=rf"{stem}\.pt: the {said} '{re.escape(name)}' holds \d+ non-finite"):
            evaluate_spec(checkpoint=tmp_path / f"{stem}.pt", episodes=2)


# ----------------------------------------------------------------------------- reproduce.py


def _reproduce_module():
    import reproduce

    return reproduce


def _plan(reproduce, out: Path, **over):
    cfg = {"budget": "smoke", "encoders": ["sgd3qn"], "variants": ["egreedy"], "seeds": [0], "train_scenario": "circle",
           "scenarios": ["circle"], "episodes": 2, "jobs": 1, "launcher": "local", "threads": 1, "reps": 100,
           "out": str(out), "planning": True, **over}
    return reproduce.make_plan(cfg)


def test_a_second_reproduce_py_on_the_same_out_is_refused_before_it_writes(tmp_path):
    from crowdrl.training.pipeline import lock_run_dir

    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_text("{}")  # what the first one wrote already
    holder = lock_run_dir(out)  # the first reproduce.py, still running
    before = folder_state(out)
    try:
        proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "reproduce.py"), "budget=smoke",
                               "variants=[egreedy]", "seeds=[0]", "episodes=2", f"out={out}"],
                              env=ENV, capture_output=True, text=True, timeout=300, cwd=ROOT)
    finally:
        holder.release()
    assert proc.returncode == 2 and "another reproduce.py" in proc.stderr, proc.stderr[-2000:]
    assert folder_state(out) == before


def test_reproduce_py_checks_every_run_and_seed_before_training(tmp_path, monkeypatch):
    from crowdrl.training import resources

    reproduce = _reproduce_module()
    with pytest.raises(reproduce.PlanError, match=r"^seeds: must be distinct integers in 0\.\.2\*\*63-1"):
        _plan(reproduce, tmp_path / "o", seeds=[0, 2**63])
    plan = _plan(reproduce, tmp_path / "o")
    reproduce.check_runs(plan)
    monkeypatch.setattr(resources, "available_memory", lambda device="cpu": 1000)
    with pytest.raises(reproduce.PlanError, match=r"^the egreedy runs \(.*\): train\.buffer_size: "):
        reproduce.check_runs(plan)
    assert not (tmp_path / "o").exists()


# ----------------------------------------------------------------------------- issue 52: nothing a user owns is overwritten


def test_reproduce_py_writes_only_into_an_out_folder_it_made(tmp_path):
    """D4: out= a folder that holds files but no manifest.json (not made by reproduce.py) is refused naming `out`;
    a new or empty one, one a call stopped between its lock and its manifest, and one an earlier reproduce.py
    made (its manifest.json) are written into, the last one resumed."""
    reproduce = _reproduce_module()
    out = tmp_path / "out"
    plan = _plan(reproduce, out)
    reproduce.check_out(plan)  # missing
    out.mkdir()
    reproduce.check_out(plan)  # empty
    (out / ".lock").write_text("")
    reproduce.check_out(plan)  # stopped after its lock, before its manifest
    (out / "table.md").write_text("the user's table")
    with pytest.raises(reproduce.PlanError, match=r"^out: .*/out holds files \(table\.md\) but is no reproduce\.py "
                                                  r"folder \(no manifest\.json\); give a new or empty folder$"):
        reproduce.check_out(plan)
    assert sorted(p.name for p in out.iterdir()) == [".lock", "table.md"]
    made = _plan(reproduce, tmp_path / "made")
    reproduce.check_out(made)
    reproduce.check_manifest(made)  # what its first call writes (under its lock), then its table
    (made.out / "table.md").write_text("an earlier call's table")
    reproduce.check_out(made)  # reproduce.py's own: resumed
    reproduce.check_manifest(made)
    (tmp_path / "file").write_text("x")
    with pytest.raises(reproduce.PlanError, match=r"^out: .*/file is a file, not a folder"):
        reproduce.check_out(_plan(reproduce, tmp_path / "file"))


@pytest.mark.parametrize("out", ["", "  "])
def test_reproduce_py_refuses_an_empty_out_naming_it(out):
    """D4b: `out=` (e.g. `out=$DIR` with DIR unset) would make the current directory the results folder."""
    reproduce = _reproduce_module()
    with pytest.raises(reproduce.PlanError, match=r"^out: is empty; give the folder"):
        reproduce.make_plan({"budget": "smoke", "variants": ["egreedy"], "seeds": [0], "out": out})


def test_check_folder_refuses_a_file_or_a_folder_without_its_marker(tmp_path):
    """The one rule of every command that writes: a new or empty folder, or one carrying the command's marker."""
    from crowdrl.training.run_folder import RunFolderRefused, check_folder

    check_folder(tmp_path / "new")
    (tmp_path / "f").write_text("x")
    with pytest.raises(RunFolderRefused, match="f is a file, not a folder"):
        check_folder(tmp_path / "f")
    folder = tmp_path / "d"
    folder.mkdir()
    check_folder(folder)
    for i in range(7):
        (folder / f"r{i}.json").write_text("{}")
    with pytest.raises(RunFolderRefused, match=r"holds files \(r0\.json, r1\.json, r2\.json, r3\.json, r4\.json, \.\.\.\); "):
        check_folder(folder)  # no markers: any file
    with pytest.raises(RunFolderRefused, match=r"but is no thing \(no mark\)"):
        check_folder(folder, ("mark",), kind="thing")
    (folder / "mark").write_text("")
    check_folder(folder, ("mark",), kind="thing")


def test_a_sweep_is_removed_only_while_no_job_wrote_into_it(tmp_path):
    """D14: after a failed sweep, a sweep folder this process made that holds nothing but Hydra's multirun.yaml
    goes (with its new parents); one a job wrote into, or one that existed before, stays as it is."""
    from omegaconf import OmegaConf

    from crowdrl.training.run_folder import NewFolders, discard_refused_sweeps

    callback = NewFolders()
    (tmp_path / "multirun" / "existed").mkdir(parents=True)
    for name in ("refused", "ran", "existed"):
        sweep = tmp_path / "multirun" / name
        callback.on_multirun_start(OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}}))
        sweep.mkdir(parents=True, exist_ok=True)
        (sweep / "multirun.yaml").write_text("hydra: {}\n")
    (tmp_path / "multirun" / "ran" / "0-seed=0").mkdir()
    (tmp_path / "multirun" / "ran" / "0-seed=0" / "status.json").write_text("{}")
    discard_refused_sweeps()
    assert sorted(p.name for p in (tmp_path / "multirun").iterdir()) == ["existed", "ran"]
    assert (tmp_path / "multirun" / "ran" / "multirun.yaml").exists()
    assert (tmp_path / "multirun" / "existed" / "multirun.yaml").exists()

    alone = tmp_path / "alone" / "sweep"
    callback.on_multirun_start(OmegaConf.create({"hydra": {"sweep": {"dir": str(alone)}}}))
    alone.mkdir(parents=True)
    (alone / "multirun.yaml").write_text("hydra: {}\n")
    discard_refused_sweeps()
    assert not (tmp_path / "alone").exists()  # the new parent too


def test_the_demos_comparison_shows_an_undefined_navigation_time_as_a_dash():
    from crowdrl.cli.demo import format_comparison

    m = {"success_rate": 0.0, "collision_rate": 1.0, "timeout_rate": 0.0, "navigation_time": None, "average_return": -0.25}
    text = format_comparison(m, {**m, "navigation_time": 13.9}, "agent")
    assert "nan" not in text and "–" in text.splitlines()[1] and "13.90s" in text.splitlines()[2]
