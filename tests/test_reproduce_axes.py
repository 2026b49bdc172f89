"""reproduce.py's settings and axes (as subprocesses): bad settings named, the encoder axis.
Apart from tests/test_reproduce.py so that the two files run on different workers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from crowdrl_testing.cli import run_cli  # refusals, in this process

ROOT = Path(__file__).resolve().parents[1]
REPRODUCE = [sys.executable, str(ROOT / "experiments" / "reproduce.py")]
TINY = ["budget=smoke", "variants=[egreedy,re3]", "seeds=[0,1]", "episodes=6", "reps=200", "jobs=2"]


def run(cmd: list[str], timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                          env={**os.environ, "WANDB_MODE": "offline"})


@pytest.mark.parametrize("override, key", [("variants=[egreedy,bogus]", "variants"), ("seeds=[-1]", "seeds"),
                                           ("encoders=[sgd3qn,transformer]", "encoders")])
def test_reproduce_bad_settings_fail_naming_the_key(tmp_path, override, key):
    proc = run_cli("reproduce.py", *TINY, override, f"out={tmp_path / 'r'}")
    assert proc.returncode == 2 and proc.stderr.strip().startswith(f"reproduce.py: {key}"), proc.stderr[-1000:]
    assert not (tmp_path / "r").exists(), "a refused call leaves no out= folder behind"


def test_a_refused_reproduce_keeps_an_out_folder_that_existed_before(tmp_path):
    (tmp_path / "r").mkdir()
    proc = run_cli("reproduce.py", *TINY, "seeds=[-1]", f"out={tmp_path / 'r'}")
    assert proc.returncode == 2 and proc.stderr.strip().startswith("reproduce.py: seeds"), proc.stderr[-1000:]
    assert (tmp_path / "r").is_dir() and not any((tmp_path / "r").iterdir())


def test_reproduce_with_another_encoder_names_its_runs_and_rows_by_it(tmp_path):
    """encoders=[mp_rgl]: runs mp_rgl-<variant>-s<seed>, rows mp_rgl+<variant> with the paper's
    MP-RGL values (circle), each variant compared with mp_rgl's own ε-greedy."""
    out = tmp_path / "r"
    proc = run([*REPRODUCE, "budget=smoke", "encoders=[mp_rgl]", "variants=[egreedy,re3]", "seeds=[0]", "episodes=4",
                "reps=100", "jobs=2", "scenarios=[circle]", f"out={out}"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert {p.name for p in (out / "runs").iterdir() if p.is_dir()} == {"mp_rgl-egreedy-s0", "mp_rgl-re3-s0"}
    from omegaconf import OmegaConf

    assert OmegaConf.load(out / "runs" / "mp_rgl-re3-s0" / "config.yaml").encoder.name == "mp_rgl"
    rows = {r["method"]: r for r in json.loads((out / "table.json").read_text())["rows"]}
    assert set(rows) == {"mp_rgl+egreedy", "mp_rgl+re3", "orca"}
    assert rows["mp_rgl+egreedy"]["success_rate_paper"] == 0.941 and "p_improve" in rows["mp_rgl+re3"]
    assert "p_improve" not in rows["mp_rgl+egreedy"]
    assert "| mp_rgl+egreedy | 1 |" in (out / "table.md").read_text()


def test_a_table_rebuilt_by_a_call_that_trains_nothing_keeps_how_the_training_call_launched(tmp_path):
    """The wall-clock line names the jobs of the call that trained the runs, not of a later call that only
    re-tabled them; a table written before that was recorded names none."""
    from omegaconf import OmegaConf

    from crowdrl.reproduction.table import launch_mode, markdown, recorded_wall, write_table
    from crowdrl.reproduction.plan import make_plan
    from crowdrl.resources import config_dir

    cfg = OmegaConf.to_container(OmegaConf.load(config_dir() / "reproduce.yaml"))
    cfg.pop("hydra"), cfg.pop("defaults")
    trained = make_plan({**cfg, "out": str(tmp_path), "jobs": 2})
    write_table(trained, [], 600.0, launch_mode(trained))
    assert recorded_wall(trained) == (600.0, "jobs=2")
    retable = make_plan({**cfg, "out": str(tmp_path), "jobs": 1})
    assert "call (jobs=2) that trained or tested the last runs: 10.0 min" in markdown(retable, [], *recorded_wall(retable))
    old = json.loads((tmp_path / "table.json").read_text())
    del old["wall_how"]
    (tmp_path / "table.json").write_text(json.dumps(old))
    assert recorded_wall(retable) == (600.0, None)
    assert "`reproduce.py` call that trained or tested the last runs: 10.0 min" in markdown(retable, [], 600.0, None)


def test_new_runs_are_refused_in_a_folder_trained_at_another_frame_budget(tmp_path):
    """budget=demo was 200k frames before issue 50 and 80k after: a variant added to a folder of the old demo
    runs would have trained at 80k beside them, silently. Refused naming the budget; a rebuild that trains
    nothing, and a folder whose runs used the budget's frames, are not."""
    from crowdrl.reproduction.plan import PlanError, budget_frames, check_budget_of_new_runs, make_plan

    plan = make_plan({"budget": "demo", "variants": ["egreedy", "rnd"], "seeds": [0], "out": str(tmp_path)})
    old = tmp_path / "runs" / "egreedy-s0"
    old.mkdir(parents=True)
    (old / "config.yaml").write_text("train:\n  total_frames: 200000\n")
    new = [(plan.methods[1], 0)]
    with pytest.raises(PlanError, match=rf"^budget: demo trains {budget_frames('demo')} frames now, but the runs in "
                                        rf".* were trained at 200000 \(e.g. egreedy-s0; .*budget=demo200k"):
        check_budget_of_new_runs(plan, new)
    check_budget_of_new_runs(plan, [])  # nothing to train: the table is rebuilt from its records
    check_budget_of_new_runs(make_plan({"budget": "demo200k", "variants": ["egreedy", "rnd"], "seeds": [0],
                                        "out": str(tmp_path)}), new)
