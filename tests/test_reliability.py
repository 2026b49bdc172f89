"""Bad values are rejected at start, naming the key; a run whose numbers blow up fails loudly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from crowdrl.training.config import ConfigError, RunConfig, check_device, validate

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


def test_train_py_with_cuda_on_a_cpu_machine_fails_before_creating_the_run(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "train.py"), "preset=smoke", "logger=csv",
                           "device=cuda", f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "WANDB_MODE": "offline"})
    assert proc.returncode == 2 and "device" in proc.stderr and "CUDA is not available" in proc.stderr
    assert not (tmp_path / "run" / "config.yaml").exists()


def test_a_run_whose_weights_blow_up_fails_and_writes_no_result(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "train.py"), "preset=smoke", "logger=csv",
                           "train.lr=1e30", f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "WANDB_MODE": "offline"})
    assert proc.returncode == 1 and "non-finite" in proc.stderr and "update" in proc.stderr, proc.stderr[-2000:]
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status["state"] == "failed" and "non-finite" in status["error"]
    assert not (tmp_path / "run" / "eval.json").exists() and not (tmp_path / "run" / "summary.json").exists()
