"""Exploration variants inside the D3QN trainer: wiring, β = 0 equivalence, checkpoints, multirun."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from crowdrl.exploration.dropout import dropout_layers
from crowdrl.exploration.noisy import noisy_layers
from crowdrl.training import ConfigError, validate
from crowdrl.training.pipeline import evaluate_best
from crowdrl.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
TINY = {"logger": {"name": "csv", "progress_bar": False}, "preset": "smoke",
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 160, "buffer_size": 1000, "batch_size": 16,
                  "warmup_frames": 32, "updates_per_frame": 0.25, "target_update_frames": 64,
                  "val_every_frames": 160, "val_episodes": 4, "checkpoint_every_frames": 64, "test_episodes": 4,
                  "compile_loss": False},
        "env": {"num_humans": 4}}


def _run(tmp_path: Path, name: str, train: dict | None = None, **exploration) -> tuple[Trainer, dict]:
    cfg = json.loads(json.dumps(TINY))
    cfg["exploration"] = {"name": name, "anneal_frames": 160, **exploration}
    cfg["train"].update(train or {})
    run = validate(cfg)
    trainer = Trainer(run, tmp_path / name)
    try:
        summary = trainer.train()
    finally:
        trainer.close()
    return trainer, summary


@pytest.mark.parametrize("name", ["noisy", "dropout", "icm", "re3", "rnd"])
def test_every_variant_trains_validates_and_tests(tmp_path, name):
    trainer, summary = _run(tmp_path, name, eps_start=0.0, eps_end=0.0)
    assert summary["updates"] > 0 and summary["frames"] == 160
    if name == "noisy":
        assert len(noisy_layers(trainer.net)) == 6
    if name == "dropout":
        layers = dropout_layers(trainer.net)
        assert len(layers) == 4 and all(abs(m.p - 0.01) < 1e-9 for m in layers)  # schedule reached its end
    rows = [json.loads(line) for line in (tmp_path / name / "scalars.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if r["kind"] == "train"]
    if name in ("icm", "re3", "rnd"):
        assert train_rows and all(r["train/intrinsic_reward_int_raw_mean"] > 0 for r in train_rows)
    result = evaluate_best(trainer.run, tmp_path / name)  # noisy: parameters saved under own names
    assert result["metrics"]["episodes"] == 4


@pytest.mark.parametrize("name", ["icm", "re3", "rnd"])
def test_beta_zero_reproduces_the_extrinsic_only_run_bit_for_bit(tmp_path, name):
    """Same seed, β = 0: the Q network ends exactly where the run without any bonus ends."""
    plain, _ = _run(tmp_path / "plain", "egreedy", eps_start=0.0, eps_end=0.0)
    bonus, _ = _run(tmp_path / "bonus", name, eps_start=0.0, eps_end=0.0, beta=0.0)
    for a, b in zip(plain.net.state_dict().values(), bonus.net.state_dict().values()):
        assert torch.equal(a, b)
    assert bonus.strategy.transform.last_stats["reward_int_raw_mean"] > 0  # the bonus was computed, only weighted by 0


def test_beta_changes_the_run(tmp_path):
    plain, _ = _run(tmp_path / "plain", "re3", beta=0.0)
    bonus, _ = _run(tmp_path / "bonus", "re3", beta=0.5)
    assert any(not torch.equal(a, b) for a, b in zip(plain.net.state_dict().values(), bonus.net.state_dict().values()))


def test_icm_state_is_checkpointed_and_restored(tmp_path):
    trainer, _ = _run(tmp_path, "icm", train={"n_step": 3})
    data = trainer.state_dict()
    assert "bonus" in data and "bonus_optimizer" in data
    fresh = Trainer(trainer.run, tmp_path / "fresh")
    fresh.load_state_dict(data)
    for a, b in zip(trainer.strategy.bonus.state_dict().values(), fresh.strategy.bonus.state_dict().values()):
        assert torch.equal(a, b)


def test_n_step_keeps_the_one_step_successor_for_the_bonus(tmp_path):
    cfg = json.loads(json.dumps(TINY))
    cfg["exploration"] = {"name": "icm"}
    cfg["train"]["n_step"] = 3
    trainer = Trainer(validate(cfg), tmp_path / "run")
    try:
        trainer.train()
        sample = trainer.buffer.sample()
    finally:
        trainer.close()
    assert ("one_step_next", "humans_rc") in sample.keys(True)
    assert {"reward_ext", "reward_int"} <= set(sample["next"].keys())
    multi = sample["steps_to_next_obs"].view(-1) > 1
    assert bool(multi.any())  # somewhere the n-step successor is not the one-step successor
    assert not torch.equal(sample["one_step_next", "robot_rc"][multi], sample["next", "robot_rc"][multi])


@pytest.mark.parametrize("override, word", [
    ({"exploration": {"name": "curiosity"}}, "exploration.name"),
    ({"exploration": {"name": "icm", "beta": -0.1}}, "exploration.beta"),
    ({"exploration": {"name": "re3", "re3_k": 0}}, "exploration.re3_k"),
    ({"exploration": {"name": "re3", "re3_k": 100}}, "exploration.re3_k"),
    ({"exploration": {"name": "dropout", "dropout_start": 1.0}}, "exploration.dropout_start"),
    ({"exploration": {"name": "noisy", "sigma0": 0.0}}, "exploration.sigma0"),
])
def test_bad_exploration_config_names_the_key(override, word):
    with pytest.raises(ConfigError, match=word.replace(".", r"\.")):
        validate(override)


def test_multirun_sweeps_exploration_and_beta(tmp_path):
    """A 2 x 2 sweep (exploration x beta) end to end through Hydra's multirun."""
    env = {**os.environ, "WANDB_MODE": "disabled", "PYTHONHASHSEED": "0"}
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), "-m", "preset=smoke", "logger=csv", "logger.render=false",
           "exploration=icm,re3", "exploration.beta=0.0,0.02", "train.total_frames=96", "train.test_episodes=2",
           "env.num_humans=4", f"hydra.sweep.dir={tmp_path}"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stderr[-2000:]
    configs = []
    for status in sorted(tmp_path.glob("*/status.json")):
        assert json.loads(status.read_text())["state"] == "completed"
        cfg = yaml.safe_load((status.parent / "config.yaml").read_text())
        configs.append((cfg["exploration"]["name"], cfg["exploration"]["beta"]))
    assert sorted(configs) == [("icm", 0.0), ("icm", 0.02), ("re3", 0.0), ("re3", 0.02)]


def test_resuming_a_finished_run_trains_no_more_and_restores_the_schedules(tmp_path):
    """A run killed after training (e.g. during its test) resumes to the test: no extra updates,
    best.pt untouched, ε and dropout p those of its frame count rather than their start values."""
    trainer, summary = _run(tmp_path, "dropout", eps_start=0.5, eps_end=0.1)
    best = tmp_path / "dropout" / "checkpoints" / "best.pt"
    before = best.stat().st_mtime_ns
    again = Trainer(trainer.run, tmp_path / "dropout")
    try:
        resumed = again.train()
    finally:
        again.close()
    assert (resumed["frames"], resumed["updates"]) == (summary["frames"], summary["updates"])
    assert best.stat().st_mtime_ns == before
    assert again.strategy.scalars()["epsilon"] == pytest.approx(0.1)
    assert all(m.p == pytest.approx(0.01) for m in dropout_layers(again.net))


def test_n_step_longer_than_a_collected_batch_is_rejected():
    with pytest.raises(ConfigError, match=r"train\.n_step"):
        validate({"train": {"n_step": 9, "steps_per_batch": 8}})
    validate({"exploration": {"name": "icm", "re3_k": 500}})  # re3_k only matters for re3
