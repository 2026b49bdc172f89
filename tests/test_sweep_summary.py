"""A sweep's summary (``crowdrl.training.sweep_summary``): rows per override set, seeds pooled, failed jobs shown."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from crowdrl.training import sweep_summary
from crowdrl.training.sweep_summary import SweepSummary, main, summarize_sweep, write_summary

ROOT = Path(__file__).resolve().parents[1]


def fake_run(folder: Path, overrides: list[str], *, success: float = 0.5, collision: float = 0.25,
             nav: float | None = 11.0, state: str = "completed", scenario: str = "circle", frames: int = 256,
             val_episodes: int = 4, seed: int | None = None, test_cases: int = 8) -> Path:
    """A run folder with the files ``train.py`` writes (their layout as a smoke run leaves them):
    ``.lock``, ``status.json``, ``config.yaml``, ``.hydra/overrides.yaml``, ``scalars.jsonl`` and, once
    completed, ``summary.json`` and the top-level ``eval.json`` (nested ``metrics``)."""
    collision = min(collision, 1 - success)
    folder.mkdir(parents=True)
    (folder / ".lock").write_text("")
    (folder / ".hydra").mkdir()
    (folder / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    seed = seed if seed is not None else int(next((o.split("=")[1] for o in overrides if o.startswith("seed=")), 0))
    (folder / "config.yaml").write_text(yaml.safe_dump({"env": {"scenario": scenario}, "seed": seed}))
    vals = [{"episodes": 3 * (i + 1), "frames": 128 * (i + 1), "kind": "val", "val/episodes": val_episodes,
             "val/success_rate": success, "val/collision_rate": collision, "val/timeout_rate": 1 - success - collision,
             "val/average_return": 0.1, "val/navigation_time": nav} for i in range(frames // 128)]
    (folder / "scalars.jsonl").write_text("".join(json.dumps(r) + "\n" for r in vals))
    if state != "completed":
        (folder / "status.json").write_text(json.dumps({"state": state, "error": "NonFiniteError('loss is nan')",
                                                        "frames": frames // 2}))
        return folder
    metrics = {"episodes": test_cases, "success_rate": success, "collision_rate": collision,
               "timeout_rate": round(1 - success - collision, 9), "navigation_time": nav, "average_return": 0.1,
               "discomfort_frequency": 0.05, "discomfort_min_separation": 0.07}
    test = {"checkpoint_frames": 128, "test_seed": 0, "metrics": metrics}
    summary = {"frames": frames, "updates": 56, "episodes": 12, "best_val_score": success + 1e-4, "best_frames": 128,
               "test": test, "wall_s": 11.4}
    (folder / "eval.json").write_text(json.dumps(test))
    (folder / "summary.json").write_text(json.dumps(summary))
    (folder / "status.json").write_text(json.dumps({"state": "completed", **summary}))
    return folder


def fake_sweep(folder: Path, jobs: list[tuple[list[str], dict]]) -> Path:
    """A sweep folder as ``train.py -m`` leaves it: ``multirun.yaml`` and ``<num>-<override_dirname>/`` per job."""
    folder.mkdir(parents=True)
    (folder / "multirun.yaml").write_text("hydra: {}\n")
    for num, (overrides, kw) in enumerate(jobs):
        fake_run(folder / f"{num}-{','.join(sorted(overrides))}", overrides, **kw)
    return folder


def _two_by_two(folder: Path) -> Path:
    return fake_sweep(folder, [
        (["exploration=re3", "exploration.beta=0.005", "seed=0"], {"success": 0.5}),
        (["exploration=re3", "exploration.beta=0.005", "seed=1"], {"success": 0.7, "nav": None}),
        (["exploration=re3", "exploration.beta=0.01", "seed=0"], {"success": 0.9}),
        (["exploration=re3", "exploration.beta=0.01", "seed=1"], {"state": "failed"}),
    ])


def test_seeds_pool_into_one_row_and_a_failed_job_is_a_row_that_says_so(tmp_path):
    rows = summarize_sweep(_two_by_two(tmp_path / "sweep"))
    assert [r["label"] for r in rows] == ["exploration.beta=0.005", "exploration.beta=0.01"]
    first, second = rows
    assert first["seeds"] == ["0", "1"] and first["status"] == "completed" and first["frames"] == [256]
    assert first["success_rate"] == pytest.approx(0.6) and first["success_rate_per_seed"] == [0.5, 0.7]
    assert first["navigation_time"] == 11.0 and first["navigation_time_per_seed"] == [11.0, None]
    assert first["best_val_score"] == pytest.approx(0.6001) and first["episodes"] == [8]
    assert second["status"] == "seed 1: failed" and second["completed"] == 1
    assert second["success_rate"] == 0.9 and second["success_rate_per_seed"] == [0.9]
    assert "nan" in second["jobs"][1]["error"] and second["frames"] == [128, 256]


def test_the_summary_is_written_atomically_and_printed(tmp_path, capsys):
    sweep = _two_by_two(tmp_path / "sweep")
    write_summary(sweep)
    text = (sweep / "summary.md").read_text()
    assert capsys.readouterr().out.startswith(text)
    assert "| exploration.beta=0.005 | 0, 1 | 0.600 (0.500, 0.700) |" in text
    assert "seed 1: failed" in text and "Every row also ran with: exploration=re3" in text
    data = json.loads((sweep / "summary.json").read_text())
    assert [r["label"] for r in data["rows"]] == ["exploration.beta=0.005", "exploration.beta=0.01"]
    assert sorted(p.name for p in sweep.iterdir() if p.is_file()) == ["multirun.yaml", "summary.json", "summary.md"]


def test_damaged_records_and_missing_overrides_do_not_stop_the_summary(tmp_path):
    sweep = fake_sweep(tmp_path / "sweep", [(["seed=0"], {}), (["seed=1"], {}), (["seed=2"], {})])
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    (jobs[0] / ".hydra" / "overrides.yaml").unlink()  # the folder name: 0-seed=0
    (jobs[1] / "eval.json").write_text("{not json")
    (jobs[2] / "status.json").unlink()  # a job killed before its first status
    (row,) = summarize_sweep(sweep)
    assert row["label"] == "(defaults)" and row["seeds"] == ["0", "1", "2"]
    assert row["status"] == "seed 1: completed, test record unreadable; seed 2: no status.json"
    assert "not valid JSON" in row["jobs"][1]["error"]
    assert row["success_rate_per_seed"] == [0.5]


def test_the_callback_writes_at_the_end_and_nothing_for_a_refused_sweep(tmp_path, monkeypatch):
    done = _two_by_two(tmp_path / "done")
    refused = tmp_path / "refused"
    refused.mkdir()
    (refused / "multirun.yaml").write_text("hydra: {}\n")
    registered = []
    monkeypatch.setattr(sweep_summary.atexit, "register", registered.append)
    monkeypatch.setattr(sweep_summary.atexit, "unregister", registered.remove)
    for folder in (done, refused, tmp_path / "gone"):
        config = OmegaConf.create({"hydra": {"sweep": {"dir": str(folder)}}})
        callback = SweepSummary()
        callback.on_multirun_start(config)
        callback.on_multirun_end(config)
    assert registered == [] and (done / "summary.md").exists()
    assert [p.name for p in refused.iterdir()] == ["multirun.yaml"] and not (tmp_path / "gone").exists()
    # a sweep that stopped at a failed job: train.py exits, and the summary is written as the process exits
    stopped = _two_by_two(tmp_path / "stopped")
    callback = SweepSummary()
    callback.on_multirun_start(OmegaConf.create({"hydra": {"sweep": {"dir": str(stopped)}}}))
    assert registered == [callback._at_exit]
    registered[0]()
    assert "seed 1: failed" in (stopped / "summary.md").read_text()


def test_the_command_rebuilds_a_summary_and_refuses_a_folder_that_is_no_sweep(tmp_path, capsys):
    sweep = _two_by_two(tmp_path / "sweep")
    assert main([str(sweep)]) == 0 and (sweep / "summary.md").exists()
    (tmp_path / "empty").mkdir()
    for bad in (tmp_path / "empty", tmp_path / "missing"):
        with pytest.raises(SystemExit) as stop:
            main([str(sweep), str(bad)])
        err = capsys.readouterr().err.strip()
        assert stop.value.code == 2 and err.count("\n") == 0
        assert err.startswith("python -m crowdrl.training.sweep_summary: sweep:"), err
    assert list((tmp_path / "empty").iterdir()) == []


def test_a_real_sweep_ends_with_its_summary(tmp_path):
    """``train.py -m preset=smoke seed=0,1``: both seeds in one row of summary.md."""
    env = {**os.environ, "WANDB_MODE": "disabled"}
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), "-m", "preset=smoke", "logger=csv",
           "logger.render=false", "seed=0,1", f"hydra.sweep.dir={tmp_path / 'sweep'}"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = (tmp_path / "sweep" / "summary.md").read_text()
    assert "| preset=smoke logger=csv logger.render=False | 0, 1 |" in text and text.count("| completed |") == 1
    assert text in proc.stdout
    (row,) = json.loads((tmp_path / "sweep" / "summary.json").read_text())["rows"]
    assert row["seeds"] == ["0", "1"] and row["completed"] == 2 and row["episodes"] == [8]
