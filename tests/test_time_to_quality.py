"""Validation checkpoints (``train.keep_val_checkpoints``) and ``experiments/time_to_quality.py`` on them."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from crowdrl.training import Trainer, validate
from crowdrl.training.checkpoint import config_fingerprint, load_checkpoint, val_checkpoints
from crowdrl.training.config import to_dict

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "experiments"))
import time_to_quality  # noqa: E402


def test_keeping_validation_checkpoints_leaves_the_fingerprint_alone():
    plain, kept = (config_fingerprint(to_dict(validate({"train": {"keep_val_checkpoints": keep}})))
                   for keep in (False, True))
    assert plain == kept


def test_bad_keep_val_checkpoints_is_refused_naming_the_key():
    with pytest.raises(Exception, match="keep_val_checkpoints"):
        validate({"train": {"keep_val_checkpoints": "often"}})


@pytest.fixture(scope="module")
def kept_run(tmp_path_factory):
    """A 96-frame run validating every 32 frames, keeping each validation's network; its summary."""
    folder = tmp_path_factory.mktemp("kept")
    run = validate({
        "preset": "smoke", "encoder": {"name": "sarl"}, "env": {"num_humans": 4, "orca_backend": "eager"},
        "logger": {"name": "csv", "progress_bar": False, "render": False}, "planning": {"enabled": False},
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 96, "warmup_frames": 16, "batch_size": 16,
                  "buffer_size": 1000, "updates_per_frame": 0.25, "val_every_frames": 32, "val_episodes": 2,
                  "checkpoint_every_frames": 96, "test_episodes": 2, "compile_acting": False, "compile_loss": False,
                  "keep_val_checkpoints": True}})
    trainer = Trainer(run, folder)
    try:
        summary = trainer.train()
    finally:
        trainer.close()
    return folder, summary


def test_every_validation_keeps_its_network_and_the_minutes_trained_then(kept_run):
    folder, summary = kept_run
    kept = val_checkpoints(folder)
    assert [p.name for p in kept] == ["val-000000032.pt", "val-000000064.pt", "val-000000096.pt"]
    data = [load_checkpoint(p) for p in kept]
    assert [d["frames"] for d in data] == [32, 64, 96]
    minutes = [time_to_quality.minutes_trained(d["timers_s"]) for d in data]
    assert 0 < minutes[0] < minutes[1] < minutes[2] < time_to_quality.minutes_trained(summary["timers_s"])
    best = load_checkpoint(folder / "checkpoints" / "best.pt")
    same = next(d for d in data if d["frames"] == best["frames"])
    assert all(torch.equal(same["net"][k], best["net"][k]) for k in best["net"]), "best.pt is one of the kept networks"


def test_the_first_network_reaching_the_target_gives_the_minutes(kept_run):
    folder, summary = kept_run
    record = time_to_quality.test_run(folder, "circle", episodes=2, target=0.0, screen=0.0)
    assert list(record["tested"]) == ["val-000000032.pt"], "testing stops at the first network reaching the target"
    assert json.loads((folder / time_to_quality.RECORD).read_text()) == record
    whole = time_to_quality.minutes_trained(summary["timers_s"])
    reached = time_to_quality.time_to_target(list(record["tested"].values()), 0.0, whole)
    assert reached["reached"] and reached["frames"] == 32
    assert reached["minutes"] == pytest.approx(
        time_to_quality.minutes_trained(load_checkpoint(val_checkpoints(folder)[0])["timers_s"]))
    missed = time_to_quality.time_to_target(list(record["tested"].values()), 1.01, whole)  # above any success rate
    assert not missed["reached"] and missed["frames"] is None and missed["minutes"] == whole > reached["minutes"]
    screened = time_to_quality.test_run(folder, "circle", episodes=2, target=0.0, screen=1.01)
    assert screened["tested"] == {}, "a network whose validation is below the screen is not tested"


@pytest.mark.slow  # ~30 s: two processes (train, then its tests) through the script's own command line
def test_the_script_trains_tests_and_tables(tmp_path):
    code = time_to_quality.main(["--out", str(tmp_path), "--preset", "smoke", "--seeds", "0", "--learners", "plain",
                                 "--episodes", "2", "--target", "0", "--screen", "0", "--jobs", "1",
                                 "train.total_frames=128", "train.val_every_frames=64", "planning.enabled=false",
                                 "train.test_episodes=2"])
    assert code == 0
    table = json.loads((tmp_path / "table.json").read_text())
    assert table["runs"]["plain"]["0"]["reached"] is True and table["runs"]["plain"]["0"]["frames"] == 64
    assert "| plain | 1/1 |" in (tmp_path / "table.md").read_text()
