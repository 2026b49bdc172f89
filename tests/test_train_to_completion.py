"""``crowdrl.reproduction.plan.train_to_completion``: the one way the experiment scripts train a run folder."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from crowdrl.reproduction import plan


@pytest.fixture
def calls(monkeypatch):
    """The commands ``train_to_completion`` would run (none is run); each exits with 0."""
    seen: list[list[str]] = []

    def fake_call(cmd, **kwargs):
        seen.append(list(cmd))
        kwargs["stdout"].write(b"trained\n")
        return 0

    monkeypatch.setattr(subprocess, "call", fake_call)
    return seen


def test_a_new_run_starts_in_its_folder_with_the_overrides_and_logs_beside_it(calls, tmp_path):
    folder = tmp_path / "runs" / "egreedy-s3"
    assert plan.train_to_completion(folder, ["seed=3", "preset=demo"]) == 0
    assert calls == [[sys.executable, "-m", "crowdrl.cli.train", f"hydra.run.dir={folder}", "seed=3", "preset=demo"]]
    assert (tmp_path / "runs" / "egreedy-s3.log").read_bytes() == b"trained\n"


def test_a_killed_run_resumes_with_its_own_config_and_the_log_is_appended(calls, tmp_path):
    folder = tmp_path / "egreedy-s0"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "last.pt").write_bytes(b"")
    (tmp_path / "egreedy-s0.log").write_bytes(b"before\n")
    plan.train_to_completion(folder, ["seed=0", "preset=demo"])
    assert calls == [[sys.executable, "-m", "crowdrl.cli.train", f"resume={folder}"]]
    assert (tmp_path / "egreedy-s0.log").read_bytes() == b"before\ntrained\n"


def test_a_finished_run_is_not_trained_again(calls, tmp_path):
    folder = tmp_path / "egreedy-s0"
    folder.mkdir()
    (folder / "status.json").write_text(json.dumps({"state": "completed"}))
    assert plan.train_to_completion(folder, ["seed=0"]) == 0
    assert calls == []


def test_the_exit_code_of_a_failed_run_is_returned(monkeypatch, tmp_path):
    monkeypatch.setattr(subprocess, "call", lambda cmd, **kwargs: 2)
    assert plan.train_to_completion(Path(tmp_path / "bad"), ["env.num_humans=-1"]) == 2
