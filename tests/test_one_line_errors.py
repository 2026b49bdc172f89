"""Every failure of a command line is one clear line and exit status 2 (docs/reliability.md): Hydra's
and OmegaConf's errors, a full disk or a read-only folder, refused input; a refused or stopped command
leaves no folder it created. The commands run in-process here (their Hydra entry points), one in a
subprocess to check the whole path."""

from __future__ import annotations

import errno
import importlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from crowdrl.evaluation.report import read_eval_record
from crowdrl_testing.cli import run_cli as run_command

ROOT = Path(__file__).resolve().parents[1]


def run_cli(module: str, *args: str) -> tuple[int, str]:
    """(exit status, stderr) of ``crowdrl.cli.<module>`` run in this process with ``args``
    (:func:`crowdrl_testing.cli.run_cli`)."""
    proc = run_command(f"{module}.py", *args)
    return proc.returncode, proc.stderr


def one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(autouse=True)
def scratch(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    return tmp_path


@pytest.mark.parametrize("module, args, words", [
    ("train", ["seed=abc"], ["train.py: seed:", "could not be converted to Integer"]),
    ("train", ["sede=1"], ["train.py: sede: not read by train.py (unknown key); allowed: env,", " seed,"]),
    ("train", ["train.lrr=1"], ["train.lrr: not read by train.py (unknown key); allowed: train.num_envs,", "train.lr,"]),
    ("train", ["resume="], ["resume: is empty"]),
    # issue 52: a bool key given 2 (Hydra would store true) (D10); a lidar beyond its bound (D8)
    ("train", ["train.q_layer_norm=2"], ["train.py: train.q_layer_norm: must be true or false, got 2"]),
    ("train", ["env.lidar_rays=100000000"], ["train.py: invalid configuration: env.lidar_rays must be an integer in "
                                             "0..1024 (0: no scan), got 100000000"]),
    ("evaluate", ["env=mars"], ["Could not find 'env/mars'", "available options in 'env': circle"]),
    # issue 49: a scenario mix with an unknown scenario, a negative or all-zero proportion
    ("train", ["+env.mix={circle: 1, mars: 1}"], ["train.py: ", "env.mix: unknown scenario 'mars'"]),
    ("train", ["env=mix", "env.mix.doorway=-1"], ["env.mix.doorway: a proportion must be a finite number >= 0"]),
    ("train", ["+env.mix={circle: 0, room: 0}"], ["env.mix: every proportion is 0"]),
    ("train", ["env=mix", "env.scenario=doorway", "env.mix.doorway=0"], ["env.scenario: (doorway) must be one of "
                                                                        "env.mix's scenarios"]),
    ("demo", ["train.num_envs=abc"], ["demo.py: train.num_envs:", "could not be converted to Integer"]),
])
def test_hydra_and_config_errors_are_one_line_exit_2_naming_the_key(monkeypatch, capsys, scratch, module, args, words):
    code, err = run_cli(module, *args, "hydra.run.dir=out" if module != "demo" else "out=out")
    line = one_line(err)
    assert code == 2 and all(w in line for w in words), line
    assert not (scratch / "out").exists() and "HYDRA_FULL_ERROR" not in os.environ


EVALUATE_KEYS = ("allowed: checkpoint, policy, eval.seed, eval.episodes, eval.num_humans, eval.human_model, "
                 "eval.robot_visible, eval.social_force_share, eval.linear_share, eval.batch, eval.record_episode, eval.ceiling, "
                 "eval.planning_depth, eval.planning_width, eval.planning_safety_horizon, eval.planning_progress_bias, "
                 "threads, device, env=<scenario> (the crowd size "
                 "is eval.num_humans")
EXPORT_KEYS = "allowed: checkpoint, out, format, opset, check, overwrite"
REPRODUCE_KEYS = ("allowed: budget, encoders, variants, seeds, train_scenario, scenarios, episodes, jobs, launcher, "
                  "threads, reps, planning, lidar, lidar_rays, train_learner, counterfactual.mode, counterfactual.actions, "
                  "counterfactual.k, counterfactual.weight, train.target_tau, train.huber_delta, train.grad_clip_norm, "
                  "train.lr_end, train.q_layer_norm, ceiling, out")


@pytest.mark.parametrize("module, args, words", [
    # an unknown key: refused by Hydra against the typed schema, or (added with +) by the command's reading of it
    ("evaluate", ["eval.episods=5"], ["evaluate.py: eval.episods: not read by evaluate.py (unknown key)", EVALUATE_KEYS]),
    ("evaluate", ["+eval.episods=5"], ["evaluate.py: eval.episods: not read by evaluate.py (unknown key)", EVALUATE_KEYS]),
    ("evaluate", ["+encoder=sarl"], ["evaluate.py: encoder: not read by evaluate.py (unknown key)", EVALUATE_KEYS]),
    ("evaluate", ["env=square", "env.num_humans=20"], ["evaluate.py: env.num_humans: not read by evaluate.py", EVALUATE_KEYS]),
    ("evaluate", ["env.human_model=linear"], ["evaluate.py: env.human_model: not read by evaluate.py", EVALUATE_KEYS]),
    ("export", ["opsett=18"], ["export.py: opsett: not read by export.py (unknown key)", EXPORT_KEYS]),
    ("export", ["+opsett=18"], ["export.py: opsett: not read by export.py (unknown key)", EXPORT_KEYS]),
    ("reproduce", ["varients=[egreedy]"], ["reproduce.py: varients: not read by reproduce.py (unknown key)",
                                           REPRODUCE_KEYS]),
    ("reproduce", ["+counterfactual.modes=merged"], ["reproduce.py: counterfactual.modes: not read by reproduce.py "
                                                     "(unknown key)", REPRODUCE_KEYS]),
    # a value of the wrong type
    ("evaluate", ["eval.episodes=abc"], ["evaluate.py: eval.episodes:", "'abc' of type 'str' could not be converted to Integer"]),
    ("evaluate", ["eval.robot_visible=maybe"], ["evaluate.py: eval.robot_visible:", "'maybe' is not a valid bool"]),
    ("export", ["opset=abc"], ["export.py: opset:", "'abc' of type 'str' could not be converted to Integer"]),
    ("export", ["overwrite=maybe"], ["export.py: overwrite:", "'maybe' is not a valid bool"]),
    ("reproduce", ["episodes=abc"], ["reproduce.py: episodes:", "'abc' of type 'str' could not be converted to Integer"]),
    ("reproduce", ["planning=maybe"], ["reproduce.py: planning:", "'maybe' is not a valid bool"]),
    # a bool key given an integer, which Hydra would store as true (issue 52, D10)
    ("evaluate", ["eval.robot_visible=2"], ["evaluate.py: eval.robot_visible: must be true or false, got 2"]),
    ("export", ["check=2"], ["export.py: check: must be true or false, got 2"]),
    ("reproduce", ["train.q_layer_norm=2"], ["reproduce.py: train.q_layer_norm: must be true or false, got 2"]),
    ("reproduce", ["planning=0"], ["reproduce.py: planning: must be true or false, got 0"]),
    ("reproduce", ["counterfactual.k=abc"], ["reproduce.py: counterfactual.k:", "could not be converted to Integer"]),
    ("reproduce", ["seeds=[0,x]"], ["reproduce.py: seeds", "'x' of type 'str' could not be converted to Integer"]),
    ("reproduce", ["variants=egreedy"], ["reproduce.py: variants:", "give a list in brackets: variants=[...]"]),
])
def test_typed_schemas_refuse_unknown_keys_and_wrong_types_naming_them_and_write_nothing(monkeypatch, capsys, scratch,
                                                                                        module, args, words):
    """evaluate, export and reproduce read their config through a typed schema (crowdrl.cli.schemas,
    crowdrl.reproduction.config): one line naming the key (and the keys allowed), exit 2, no folder."""
    first = {"evaluate": ["policy=orca", "eval.episodes=2"], "export": ["checkpoint=runs/x", "out=p.onnx"],
             "reproduce": ["budget=smoke", "variants=[egreedy]", "seeds=[0]", "episodes=2"]}[module]
    where = {"evaluate": "hydra.run.dir=out", "export": "hydra.run.dir=.", "reproduce": "out=out"}[module]
    code, err = run_cli(module, *first, *args, where)
    line = one_line(err)
    assert code == 2 and all(w in line for w in words), line
    assert list(scratch.iterdir()) == []  # no run or out folder, no .hydra, no log, no p.onnx


def test_a_hydra_error_in_a_real_process_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "train.py"), "seed=abc"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120, env={**os.environ, "WANDB_MODE": "offline"})
    assert proc.returncode == 2 and one_line(proc.stderr).startswith("train.py: seed:"), proc.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS, errno.EACCES])
def test_a_full_or_read_only_disk_during_training_is_one_line_naming_the_file(monkeypatch, capsys, scratch, code):
    import crowdrl.training as training

    def full(run, run_dir, **kwargs):
        raise OSError(code, os.strerror(code), str(Path(run_dir) / "checkpoints" / "last.pt"))

    monkeypatch.setattr(training, "run_training", full)
    status, err = run_cli("train", "preset=smoke", "logger=csv", "hydra.run.dir=run")
    line = one_line(err)
    assert status == 2 and f"({errno.errorcode[code]})" in line and "last.pt" in line, line
    assert f"resume={scratch / 'run'}" in line, line
    assert not (scratch / "run").exists()  # the monkeypatched run wrote nothing: the folder Hydra made is gone


@pytest.mark.parametrize("fault", ["ENOSPC", "EROFS", "stopped", "SIGTERM"])
def test_a_failed_or_stopped_evaluation_is_one_line_and_leaves_no_folder(monkeypatch, capsys, scratch, fault):
    """A full or read-only disk: exit 2; Ctrl-C, and SIGTERM as Ctrl-C (issue 52, D9): exit 130; either way the
    eval folder the command made is removed while empty."""
    import signal

    import crowdrl.evaluation.report as report

    def write_records(folder, records, stem="eval"):
        if fault == "stopped":
            raise KeyboardInterrupt
        if fault == "SIGTERM":
            # without a handler SIGTERM would kill this test process: fail instead
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, None), "SIGTERM is not handled"
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises at once
            raise AssertionError("SIGTERM did not stop the evaluation")
        raise OSError(getattr(errno, fault), os.strerror(getattr(errno, fault)), str(Path(folder) / "eval.json"))

    monkeypatch.setattr(report, "write_records", write_records)
    code, err = run_cli("evaluate", "policy=orca", "eval.episodes=2", "eval.record_episode=null",
                        "hydra.run.dir=runs/eval-x")
    line = one_line(err)
    stopped = fault in ("stopped", "SIGTERM")
    assert code == (130 if stopped else 2), line
    assert ("evaluate.py: interrupted" if stopped else "eval.json: ") in line, line
    assert not (scratch / "runs").exists()
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the command's handler is gone with it


def test_evaluate_refuses_episodes_beyond_memory_naming_the_key(monkeypatch, capsys, scratch):
    code, err = run_cli("evaluate", "policy=orca", "eval.episodes=1000000000",
                        "hydra.run.dir=runs/eval-x")
    line = one_line(err)
    assert code == 2 and "eval.episodes: 1000000000 episodes keep" in line and "memory available" in line, line
    assert not (scratch / "runs").exists()


def test_a_run_folder_whose_config_holds_an_unknown_key_or_target_is_refused_naming_it(tmp_path):
    from omegaconf import OmegaConf

    from crowdrl.cli.train import resumed_config
    from crowdrl.training.config import ConfigError, RunConfig

    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.pt").write_bytes(b"")
    for text, key in (("seed: 0\nfoo: 1\n", "foo"), ("_target_: os.system\nseed: 0\n", "_target_")):
        (tmp_path / "config.yaml").write_text(text)
        with pytest.raises(ConfigError, match=f"config.yaml is not a run config train.py can read \\({key}: Key"):
            resumed_config(OmegaConf.structured(RunConfig), tmp_path, [f"resume={tmp_path}"])


def test_logger_online_without_wandb_credentials_is_refused_at_start(monkeypatch, tmp_path):
    from crowdrl.training.config import ConfigError, RunConfig
    from crowdrl.training.validation import validate

    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("NETRC", str(tmp_path / "no-netrc"))
    run = RunConfig()
    run.logger.name, run.logger.mode = "wandb", "online"
    with pytest.raises(ConfigError, match="^logger.mode: online, but wandb has no credentials"):
        validate(run)
    monkeypatch.setenv("WANDB_API_KEY", "x" * 40)
    validate(run)


@pytest.mark.parametrize("env_mode, logger_mode, expected", [
    (None, "offline", "offline"), (None, "online", "online"), (None, "disabled", "disabled"),
    ("disabled", "online", "disabled"), ("offline", "online", "offline")])
def test_the_wandb_mode_follows_logger_mode_and_the_environment_wins_when_set(monkeypatch, tmp_path, env_mode,
                                                                              logger_mode, expected):
    """The mode WandbMirror hands to wandb (through TorchRL's WandbLogger, stubbed here): logger.mode, or
    WANDB_MODE when set; importing a command line no longer sets WANDB_MODE behind the user's back."""

    import torchrl.record.loggers.wandb as torchrl_wandb

    from crowdrl.training.scalars import WandbMirror

    monkeypatch.delenv("WANDB_MODE", raising=False)
    for name in ("train", "evaluate", "demo", "reproduce"):
        importlib.import_module(f"crowdrl.cli.{name}")
    assert "WANDB_MODE" not in os.environ
    if env_mode is not None:
        monkeypatch.setenv("WANDB_MODE", env_mode)
    seen = {}

    class StubLogger:
        def __init__(self, **kwargs):
            seen.update(kwargs)
            self.experiment = type("Run", (), {"id": "stub"})()

    monkeypatch.setattr(torchrl_wandb, "WandbLogger", StubLogger)
    WandbMirror(tmp_path, {}, "crowdrl", logger_mode, None)
    assert seen["mode"] == expected


# ----------------------------------------------------------------------------- issue 52: nothing a user owns is overwritten

REPRODUCE_TINY = ["budget=smoke", "variants=[egreedy]", "seeds=[0]", "scenarios=[circle]", "episodes=2"]


def test_reproduce_refuses_an_out_folder_it_did_not_make(monkeypatch, capsys, scratch):
    """D4: `out=<a folder holding the user's own table.md>`: refused naming `out`, before its lock; the folder
    is as it was (reproduce.py's own folders, with their manifest.json, still resume: tests/test_run_folders.py)."""
    mine = scratch / "mine"
    mine.mkdir()
    (mine / "table.md").write_text("my table")
    code, err = run_cli("reproduce", *REPRODUCE_TINY, f"out={mine}")
    line = one_line(err)
    assert code == 2 and line.startswith(f"reproduce.py: out: {mine} holds files (table.md)"), line
    assert "no reproduce.py folder (no manifest.json)" in line, line
    assert [p.name for p in mine.iterdir()] == ["table.md"] and (mine / "table.md").read_text() == "my table"


def test_reproduce_refuses_an_empty_out_and_writes_nothing(monkeypatch, capsys, scratch):
    """D4b: `out=` (empty: `out=$DIR` with DIR unset) would have made the current directory the results folder."""
    code, err = run_cli("reproduce", *REPRODUCE_TINY, "out=")
    line = one_line(err)
    assert code == 2 and line.startswith("reproduce.py: out: is empty"), line
    assert list(scratch.iterdir()) == []


@pytest.mark.parametrize("manifest, words", [("garbage", "not valid JSON"), ("[]", "expected a JSON object, got list")])
def test_reproduce_refuses_a_manifest_that_is_no_json_object_in_one_line(monkeypatch, capsys, scratch, manifest, words):
    """D6: a rerun whose manifest.json is not the JSON object reproduce.py writes: one line naming the file."""
    out = scratch / "out"
    out.mkdir()
    (out / "manifest.json").write_text(manifest)
    code, err = run_cli("reproduce", *REPRODUCE_TINY, f"out={out}")
    line = one_line(err)
    assert code == 2 and line.startswith(f"reproduce.py: out: {out / 'manifest.json'}: {words}"), line
    assert (out / "manifest.json").read_text() == manifest
    assert sorted(p.name for p in out.iterdir()) == [".lock", "manifest.json"]  # the lock: taken before it is read


@pytest.mark.parametrize("module, args, where", [
    ("train", ["preset=smoke", "logger=csv", "hydra.run.dir=f"], "f is a file"),
    ("train", ["preset=smoke", "logger=csv", "hydra.run.dir=f/run"], "f/run: f is a file"),
    ("evaluate", ["policy=orca", "eval.episodes=2", "hydra.run.dir=f"], "f is a file"),
    ("reproduce", [*REPRODUCE_TINY, "out=f"], "f is a file"),
])
def test_a_file_where_the_run_folder_should_be_is_one_line_naming_it(monkeypatch, capsys, scratch, module, args, where):
    """D7: `hydra.run.dir=` (or reproduce.py's `out=`) an existing file, or below one: Hydra cannot make the
    folder; one line naming the path, exit 2, the file as it was."""
    (scratch / "f").write_text("mine")
    code, err = run_cli(module, *args)
    line = one_line(err)
    assert code == 2 and line.startswith(f"{module}.py: {where}, not a folder; give a new or empty folder"), line
    assert [p.name for p in scratch.iterdir()] == ["f"] and (scratch / "f").read_text() == "mine"


@pytest.mark.parametrize("sweep, words", [("seed=abc,0", ["train.py: seed:", "could not be converted to Integer"]),
                                          ("train.lr=-1,0.1", ["train.py: invalid configuration: train.lr: must be > 0"])])
def test_a_refused_sweep_leaves_no_sweep_folder(monkeypatch, capsys, scratch, sweep, words):
    """D14: `train.py -m ... seed=abc,0`: Hydra writes the sweep folder's multirun.yaml before it composes the
    jobs; refused (by Hydra, or by train.py's checks in the first job) before any job wrote anything, the sweep
    leaves nothing behind."""
    code, err = run_cli("train", "-m", "preset=smoke", "logger=csv", sweep)
    line = one_line(err)  # Hydra's "Launching 2 jobs locally" goes to stdout
    assert code == 2 and all(w in line for w in words), line
    assert list(scratch.iterdir()) == []


def test_evaluate_refuses_a_folder_that_holds_records_and_writes_into_a_new_or_empty_one(monkeypatch, capsys, scratch):
    """D5: `evaluate.py checkpoint=R hydra.run.dir=R` (R a finished training run) would have replaced the run's
    own test eval.json: refused naming the folder, R as it was; an empty folder is written into."""

    from crowdrl.cli.evaluate import main

    run = scratch / "run"
    run.mkdir()
    (run / "status.json").write_text('{"state": "completed"}')
    (run / "eval.json").write_text('{"episodes": 1000}')
    code, err = run_cli("evaluate", "policy=orca", "eval.episodes=2", "eval.record_episode=null",
                        f"hydra.run.dir={run}")
    line = one_line(err)
    assert code == 2 and line.startswith(f"evaluate.py: hydra.run.dir: {run} holds files (eval.json, status.json); "), line
    assert sorted(p.name for p in run.iterdir()) == ["eval.json", "status.json"]
    assert (run / "eval.json").read_text() == '{"episodes": 1000}'

    empty = scratch / "empty"
    empty.mkdir()
    monkeypatch.setattr(sys, "argv", ["evaluate.py", "policy=orca", "eval.episodes=2", "eval.record_episode=null",
                                      f"hydra.run.dir={empty}"])
    main()
    assert read_eval_record(empty / "eval.json")["episodes"] == 2
