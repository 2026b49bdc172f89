"""Bad values are rejected at start, naming the key; a run whose numbers blow up fails loudly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from crowdrl_testing.cli import run_cli
from crowdrl.evaluation.report import read_eval_record
from crowdrl.training.config import ConfigError, RunConfig
from crowdrl.training.validation import check_device, validate

ROOT = Path(__file__).resolve().parents[1]


def smoke(**train) -> RunConfig:
    run = RunConfig()
    run.train.total_frames, run.train.warmup_frames, run.train.buffer_size, run.train.batch_size = 256, 64, 10_000, 32
    for key, value in train.items():
        setattr(run.train, key, value)
    return run


@pytest.mark.parametrize("key", ["lr", "updates_per_frame", "gamma"])
@pytest.mark.parametrize("value", [float("inf"), float("nan")])
def test_non_finite_floats_are_rejected_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=f"train.{key}: must be a finite number"):
        validate(smoke(**{key: value}))


def test_non_finite_exploration_values_are_rejected():
    run = smoke()
    run.exploration.beta = float("inf")
    with pytest.raises(ConfigError, match="exploration.beta: must be a finite number"):
        validate(run)


def test_a_budget_that_cannot_update_is_rejected():
    with pytest.raises(ConfigError, match="train.total_frames.*not a single update"):
        validate(smoke(batch_size=5000))
    validate(smoke(batch_size=5000, updates_per_frame=0.0))  # a run that never updates is allowed on purpose


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
@pytest.mark.parametrize("device", ["cuda", "cuda:1"])
def test_cuda_without_cuda_is_rejected_at_start(device):
    with pytest.raises(ConfigError, match="device: .*CUDA is not available"):
        check_device(device)


def test_unknown_device_names_are_rejected():
    with pytest.raises(ConfigError, match="device: got 'gpu'"):
        check_device("gpu")


def test_a_run_whose_weights_blow_up_fails_and_writes_no_result(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "train.py"), "preset=smoke", "logger=csv",
                           "train.lr=1e30", f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "WANDB_MODE": "offline"})
    assert proc.returncode == 1 and "non-finite" in proc.stderr and "update" in proc.stderr, proc.stderr[-2000:]
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status["state"] == "failed" and "non-finite" in status["error"]
    assert not (tmp_path / "run" / "eval.json").exists() and not (tmp_path / "run" / "summary.json").exists()


# ----------------------------------------------------------------------------- run folders

TRAIN = [sys.executable, str(ROOT / "experiments" / "train.py")]
ENV = {**os.environ, "WANDB_MODE": "offline"}


def folder_hashes(folder: Path) -> dict[str, str]:
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory) -> list[Path]:
    """Two finished smoke runs (seeds 0 and 1) made by train.py."""
    base = tmp_path_factory.mktemp("runs")
    procs = [subprocess.Popen([*TRAIN, "preset=smoke", "logger=csv", "logger.render=false", f"seed={s}",
                               f"hydra.run.dir={base / f's{s}'}"],
                              env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for s in (0, 1)]
    for p in procs:
        assert p.wait(timeout=300) == 0, p.stderr.read()[-2000:]
    return [base / "s0", base / "s1"]


@pytest.mark.parametrize("damage", ["truncated", "foreign", "older"])
def test_a_refused_resume_leaves_the_folder_byte_for_byte(smoke_runs, tmp_path, damage):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(smoke_runs[0], run)
    last = run / "checkpoints" / "last.pt"
    words = []
    if damage == "truncated":
        last.write_bytes(last.read_bytes()[:5000])
    elif damage == "older":  # written by an older crowdrl: its environments' snapshot of format 1
        from crowdrl.training.checkpoint import load_checkpoint, save_checkpoint

        data = load_checkpoint(last)
        data["env"]["format"] = 1
        save_checkpoint(last, {k: v for k, v in data.items() if k not in ("format", "fingerprint")}, data["fingerprint"])
        words = ["snapshot of format 1; this code restores format 2 only", "resume it with that version"]
    else:
        shutil.copyfile(smoke_runs[1] / "checkpoints" / "last.pt", last)  # another run's (seed 1)
    before = folder_hashes(run)
    proc = run_cli("train.py", f"resume={run}")
    assert proc.returncode == 2 and "last.pt" in proc.stderr, proc.stderr[-2000:]
    assert all(w in proc.stderr for w in words), proc.stderr[-2000:]
    assert folder_hashes(run) == before


def test_resume_reads_the_folders_own_config_and_refuses_conflicting_overrides(smoke_runs, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(smoke_runs[1], run)
    proc = run_cli("train.py", f"resume={run}", "seed=0")
    assert proc.returncode == 2 and "refused override(s): seed=0 (the run has seed=1)" in proc.stderr
    proc = run_cli("train.py", f"resume={run}", "seed=1", "preset=smoke")  # agreeing overrides: the run's own config
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((run / "status.json").read_text())["state"] == "completed"


def test_resume_overrides_are_compared_with_schema_defaults_for_keys_a_folder_predates():
    from crowdrl.training.config import RunConfig
    from crowdrl.training.compat import resume_conflicts
    from omegaconf import OmegaConf

    saved = OmegaConf.to_container(OmegaConf.structured(RunConfig(seed=1)))
    del saved["planning"]  # a run folder written before the planning key existed
    saved = OmegaConf.create(saved)
    current = OmegaConf.structured(RunConfig(seed=1))
    current.planning.enabled = True  # today's default, but the old run trained without planning (STORED_DEFAULTS)
    assert resume_conflicts(current, saved, ["planning.enabled=true"]) == [
        "planning.enabled=true (the run has planning.enabled=False)"]
    current.planning.enabled = False  # what the old run ran with
    assert resume_conflicts(current, saved, ["planning.enabled=false", "seed=1", "resume=x", "hydra.run.dir=y"]) == []
    current.seed, current.env.num_humans = 0, 5
    conflicts = resume_conflicts(current, saved, ["seed=0", "env.num_humans=5", "env=circle"])
    assert conflicts[:2] == ["seed=0 (the run has seed=1)", "env.num_humans=5 (the run has env.num_humans=10)"]
    assert len(conflicts) == 3 and conflicts[2].startswith("env=circle (the run has env={")  # a group: its content


def test_a_folder_that_predates_the_recommended_learner_resumes_as_it_ran_and_tests_to_every_digit(tmp_path):
    """Issue 50: a run folder whose config.yaml predates train.counterfactual and train.target_tau (the plain
    learner, the defaults then) resumes under today's defaults with its own learner (its checkpoint's fingerprint
    agrees) and tests to every digit of the record it wrote; the run is never switched to the new learner."""
    import shutil

    from omegaconf import OmegaConf

    from crowdrl.training.checkpoint import load_checkpoint

    run = tmp_path / "old"
    proc = subprocess.run([*TRAIN, "preset=smoke", "logger=csv", "logger.render=false", "learner=plain",
                           f"hydra.run.dir={run}"], env=ENV, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    first = read_eval_record(run / "eval.json")
    config = OmegaConf.load(run / "config.yaml")
    del config.train["counterfactual"], config.train["target_tau"]  # written before the keys
    (run / "config.yaml").write_text(OmegaConf.to_yaml(config))
    for name in ("summary.json", "eval.json"):  # unfinished: the resume tests it again
        (run / name).unlink()
    proc = run_cli("train.py", f"resume={run}")  # in this process: the resume only tests
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert read_eval_record(run / "eval.json") == first
    stored = load_checkpoint(run / "checkpoints" / "last.pt")["config"]["train"]
    assert stored["counterfactual"]["mode"] == "off" and stored["target_tau"] == 1.0
    shutil.rmtree(run)


def test_another_runs_best_checkpoint_is_refused(smoke_runs, tmp_path):
    import shutil

    from crowdrl.training import CheckpointError, evaluate_best
    from crowdrl.training.validation import validate
    from omegaconf import OmegaConf

    run = tmp_path / "run"
    shutil.copytree(smoke_runs[0], run)
    shutil.copyfile(smoke_runs[1] / "checkpoints" / "best.pt", run / "checkpoints" / "best.pt")
    (run / "eval.json").unlink()
    with pytest.raises(CheckpointError, match="another configuration"):
        evaluate_best(validate(OmegaConf.load(run / "config.yaml")), run)
    assert not (run / "eval.json").exists()


@pytest.mark.slow  # ~40 s (two train.py processes); make test-slow
def test_sigterm_checkpoints_marks_interrupted_and_resumes(tmp_path):
    import signal
    import time

    run = tmp_path / "run"
    args = ["preset=smoke", "logger=csv", "logger.render=false", "train.total_frames=640",
            "train.checkpoint_every_frames=100000"]
    proc = subprocess.Popen([*TRAIN, *args, f"hydra.run.dir={run}"], env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        scalars = run / "scalars.jsonl"
        if scalars.exists() and '"kind": "val"' in scalars.read_text():  # the first validation: 128 frames
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=120) == 130, proc.stderr.read()[-2000:]
    status = json.loads((run / "status.json").read_text())
    assert status["state"] == "interrupted"
    assert (run / "scalars.csv").exists() and (run / "checkpoints" / "last.pt").exists()
    assert not (run / "eval.json").exists()
    proc = subprocess.run([*TRAIN, f"resume={run}"], env=ENV, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["frames"] == 640


def test_a_second_writer_to_a_run_folder_is_refused(tmp_path):
    from crowdrl.training.pipeline import RunFolderBusy, lock_run_dir

    first = lock_run_dir(tmp_path)
    with pytest.raises(RunFolderBusy, match="another process"):
        lock_run_dir(tmp_path)
    first.release()
    lock_run_dir(tmp_path).release()  # free again once the holder is gone


def test_run_folder_names_carry_a_random_suffix():
    """Two runs started in the same second get different folders (`${crowdrl_uid:}` in conf/)."""
    from omegaconf import OmegaConf

    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()
    first = OmegaConf.create({"dir": "runs/x-${crowdrl_uid:}", "again": "${crowdrl_uid:}"})
    second = OmegaConf.create({"dir": "runs/x-${crowdrl_uid:}"})
    assert first.dir == f"runs/x-{first.again}" and len(first.again) == 6  # one value per config
    assert first.dir != second.dir  # each run's config draws its own
    assert "${crowdrl_uid:}" in (ROOT / "conf" / "config.yaml").read_text()


def test_orca_backend_is_a_validated_config_key_that_reaches_the_env():
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import to_dict
    from crowdrl.training.factories import make_env

    run = smoke()
    run.env.orca_backend = "warp"
    with pytest.raises(ConfigError, match="env.orca_backend.*allowed: eager, compiled"):
        validate(run)
    run.env.orca_backend = "compiled"
    env = make_env(validate(run), split="val", num_envs=2)
    assert env.base_env.config.orca_backend == "compiled"
    eager = smoke()
    assert config_fingerprint(to_dict(run)) == config_fingerprint(to_dict(eager))  # same numbers: resumable across


# ----------------------------------------------------------------------------- exact resume


EXACT = {"logger": {"name": "csv", "progress_bar": False, "render": False}, "preset": "smoke",
         "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 288, "buffer_size": 1000, "batch_size": 16,
                   "warmup_frames": 32, "updates_per_frame": 0.25, "target_update_frames": 64, "val_every_frames": 96,
                   "val_episodes": 4, "checkpoint_every_frames": 64, "test_episodes": 4, "save_buffer": True,
                   "compile_loss": False},
         "env": {"num_humans": 4}}


# every stable-bonus option that keeps running state (observation and reward statistics, the terminal
# value's mean) or reads the frame count (the exp β schedule)
BONUS_OPTIONS = {"reward_norm": "std", "reward_center": True, "reward_clip": 3.0, "obs_norm": True,
                 "terminal_value": True, "icm_feature_norm": "layernorm", "beta_schedule": "exp", "beta_decay": 1e-3}


# counterfactual experience: its later batch's loss (train/loss_counterfactual) is a mean over the updates
# since the last logged row, which a checkpoint between two rows must carry
COUNTERFACTUAL = {"mode": "second_update", "actions": "random", "k": 3}


def _exact_run(name: str) -> RunConfig:
    cfg = json.loads(json.dumps(EXACT))
    options = BONUS_OPTIONS if name.endswith("+options") else {}
    if name.endswith("+counterfactual"):
        cfg["train"]["counterfactual"] = COUNTERFACTUAL
    cfg["exploration"] = {"name": name.removesuffix("+options").removesuffix("+counterfactual"), "anneal_frames": 288,
                          **options}
    return validate(cfg)


def _final(run_dir: Path) -> tuple[dict, dict, list]:
    from crowdrl.training.checkpoint import load_checkpoint

    last = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    rows = [{k: v for k, v in json.loads(line).items() if not k.startswith("time/")}
            for line in (run_dir / "scalars.jsonl").read_text().splitlines()]
    return last["loss"], read_eval_record(run_dir / "eval.json"), rows


# ICM with the bonus options carries the most state (its networks, its optimizer, the one-step
# successors, the normalisers' statistics); the others run in make test-slow, and
# tests/test_training.py's slow test kills a real train.py process with SIGKILL.
@pytest.mark.parametrize("name", ["icm+options", "egreedy+counterfactual", *[pytest.param(n, marks=pytest.mark.slow)
                                                   for n in ("icm", "egreedy", "noisy", "dropout", "re3", "rnd")]])
def test_a_killed_run_resumed_with_its_buffer_is_bit_identical_to_the_uninterrupted_run(tmp_path, name):
    """Killed mid-update at frame 224 (last checkpoint: frame 192, in-flight episodes and all), then
    resumed by a new trainer: the same final weights (online, target, optimizer), the same test
    metrics and the same logged rows (every column but the wall-clock time/ ones: with counterfactual experience
    its train/counterfactual_* and train/loss_counterfactual too) as the run that was never stopped."""
    from crowdrl_testing import train_until_killed
    from crowdrl.training.pipeline import run_training

    run = _exact_run(name)
    run_training(run, tmp_path / "ref")
    train_until_killed(run, tmp_path / "run", frame=224)
    from crowdrl.training.checkpoint import load_checkpoint

    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["counters"]["frames"] == 192
    run_training(run, tmp_path / "run")

    ref_weights, ref_metrics, ref_rows = _final(tmp_path / "ref")
    weights, metrics, rows = _final(tmp_path / "run")
    assert ref_weights.keys() == weights.keys()
    differing = [k for k in ref_weights if not torch.equal(ref_weights[k], weights[k])]
    assert not differing, f"weights differ after the resume: {differing[:5]}"
    assert metrics == ref_metrics
    assert [sorted(r) for r in rows] == [sorted(r) for r in ref_rows]
    differing = [(i, k, ref[k], row[k]) for i, (ref, row) in enumerate(zip(ref_rows, rows)) for k in ref
                 if ref[k] != row[k] and not (ref[k] != ref[k] and row[k] != row[k])]  # NaN == NaN here
    assert not differing, f"logged rows differ after the resume (row, column, uninterrupted, resumed): {differing[:5]}"
    if name.endswith("+counterfactual"):
        assert any("train/loss_counterfactual" in r for r in rows)


def test_logger_wandb_mirrors_the_scalars_into_an_offline_run_whose_id_the_checkpoint_keeps(tmp_path):
    """``logger=wandb`` (the default outside tests, offline): TorchRL's WandbLogger writes an offline run in
    the run folder holding the logged scalars; ``last.pt`` records its id, so a resume continues that run."""
    import torch

    run = tmp_path / "run"
    proc = subprocess.run([*TRAIN, "preset=smoke", "logger=wandb", "logger.render=false", "train.test_episodes=4",
                           f"hydra.run.dir={run}"], env={**ENV, "WANDB_MODE": "offline"}, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    wandb_id = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["wandb_id"]
    (record,) = run.glob(f"wandb/offline-run-*-{wandb_id}/run-{wandb_id}.wandb")
    assert b"val/success_rate" in record.read_bytes() and b"train/success_rate" in record.read_bytes()


# ----------------------------------------------------------------------------- issue 40: clear failures, nothing left


def test_an_empty_resume_is_refused_naming_resume():
    """``resume=$RUN`` with RUN unset must not start a brand-new run."""
    run = smoke()
    run.resume = ""
    with pytest.raises(ConfigError, match="^resume: is empty"):
        validate(run)


def test_a_writer_killed_mid_write_leaves_a_temporary_that_the_next_write_removes(tmp_path):
    """SIGKILL inside an atomic write leaves ``.last.pt.<pid>.<id>.tmp``; the next atomic write of
    ``last.pt`` removes it (its process is gone), and leaves a live process's temporaries alone."""
    from crowdrl.files import atomic_write_bytes

    target = tmp_path / "last.pt"
    code = ("import os, signal, sys\nfrom crowdrl.files import atomic_write_with\n"
            "def write(tmp):\n    tmp.write_bytes(b'x' * 4096)\n    os.kill(os.getpid(), signal.SIGKILL)\n"
            "atomic_write_with(sys.argv[1], write)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(target)], capture_output=True, timeout=60)
    assert proc.returncode == -9
    (left,) = tmp_path.glob(".last.pt.*.tmp")
    live = tmp_path / f".last.pt.{os.getppid()}.0123456789ab.tmp"  # a running process's write in progress
    live.write_bytes(b"y")
    other = tmp_path / ".best.pt.999999999.0123456789ab.tmp"  # another target's: not this write's business
    other.write_bytes(b"z")
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new" and not left.exists()
    assert live.exists() and other.exists()
