"""experiments/evaluate.py and experiments/reproduce.py end to end (training in subprocesses; refusals, re-tabling
and compare_runs.py in this process), the results
statistics and figures, and the SLURM launcher config composing with a sweep."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from crowdrl.evaluation.report import eval_file, read_eval_record
from crowdrl_testing.cli import run_cli  # refusals and reruns that train nothing, in this process

ROOT = Path(__file__).resolve().parents[1]
EVALUATE = [sys.executable, str(ROOT / "experiments" / "evaluate.py")]
REPRODUCE = [sys.executable, str(ROOT / "experiments" / "reproduce.py")]
TINY = ["budget=smoke", "variants=[egreedy,re3]", "seeds=[0,1]", "episodes=6", "reps=200", "jobs=2"]
EVAL_KEYS = {"success_rate", "collision_rate", "timeout_rate", "navigation_time", "average_return",
             "discomfort_frequency", "min_separation", "episodes", "seed", "scenario"}


def run(cmd: list[str], timeout: int = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": "offline"}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env)


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory) -> Path:
    """A tiny reproduce.py run (2 variants x 2 seeds at the smoke budget, 6 test cases per
    scenario), SIGKILLed with its whole job tree as soon as a run has a checkpoint, then rerun."""
    out = tmp_path_factory.mktemp("repro") / "results"
    proc = subprocess.Popen([*REPRODUCE, *TINY, f"out={out}"], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True, env={**os.environ, "WANDB_MODE": "offline"})
    deadline = time.time() + 300
    while not list(out.glob("runs/*/checkpoints/last.pt")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    killed = [p.parents[1].name for p in out.glob("runs/*/checkpoints/last.pt")
              if json.loads((p.parents[1] / "status.json").read_text())["state"] == "running"]
    assert killed, "no run was caught mid-training"
    (out / "killed.json").write_text(json.dumps(killed))
    again = run([*REPRODUCE, *TINY, f"out={out}"])
    assert again.returncode == 0, again.stderr[-3000:]
    return out


def test_reproduce_writes_the_table_with_intervals_and_the_figures(reproduced):
    files = {p.name for p in reproduced.iterdir()}
    assert {"table.md", "table.json", "table.csv", "curves.png", "intervals.png", "side_by_side.png",
            "egreedy_s0_circle_case0.gif", "manifest.json"} <= files
    table = json.loads((reproduced / "table.json").read_text())
    rows = {(r["method"], r["scenario"]): r for r in table["rows"]}
    assert set(rows) == {(m, s) for m in ("egreedy", "re3", "orca") for s in ("circle", "square")}
    for (method, scenario), r in rows.items():
        per_seed = r["success_rate_per_seed"]
        assert len(per_seed) == (1 if method == "orca" else 2)
        assert r["success_rate"] == pytest.approx(np.mean(per_seed))
        assert r["success_rate_lo"] <= r["success_rate"] <= r["success_rate_hi"]
        paper = {"egreedy": 0.940, "re3": 0.971, "orca": 0.769}[method] if scenario == "circle" else None
        if paper is not None:
            assert r["success_rate_paper"] == paper
    assert 0.0 <= rows[("re3", "circle")]["p_improve"] <= 1.0
    assert "p_improve" not in rows[("egreedy", "circle")]
    # every cell of the table comes from the runs' own eval.json files
    for variant in ("egreedy", "re3"):
        for seed in (0, 1):
            for scenario in ("circle", "square"):
                rec = read_eval_record(reproduced / "runs" / f"{variant}-s{seed}" / f"eval-{scenario}" / "eval.json")
                assert EVAL_KEYS <= set(rec) and rec["episodes"] == 6 and rec["scenario"] == scenario
    md = (reproduced / "table.md").read_text()
    assert "## circle" in md and "## square" in md and "(0.940)" in md
    # the minutes per run count every segment of the runs killed and resumed (summary.json's run_s)
    minutes = [json.loads((reproduced / "runs" / f"{v}-s{s}" / "summary.json").read_text())["run_s"] / 60
               for v in ("egreedy", "re3") for s in (0, 1)]
    assert (f"test per run (`summary.json`; every segment of a resumed run): {min(minutes):.1f}–{max(minutes):.1f} min."
            in md)


def test_retable_rebuilds_a_table_with_a_ceiling_row_with_the_committed_ceilings():
    from retable import overrides

    manifest = {"budget": "episodes", "train_scenario": "doorway", "episodes": 1000}
    rows = [{"method": "egreedy", "scenario": "doorway"}, {"method": "orca", "scenario": "doorway"}]
    plain = overrides({"manifest": manifest, "seeds": [0, 1], "rows": rows})
    assert not any(a.startswith("ceiling=") for a in plain) and "seeds=[0,1]" in plain
    gap = overrides({"manifest": manifest, "seeds": [0, 1], "rows": [*rows, {"method": "ceiling", "scenario": "doorway"}]})
    assert [a for a in gap if a not in plain] == ["ceiling=results/ceiling"] and set(plain) <= set(gap)
    assert (ROOT / "results" / "ceiling" / "doorway.json").is_file()  # where the committed tables' ceiling rows come from


def test_reproduce_rerun_trains_nothing_and_refuses_other_settings(reproduced):
    stamp = (reproduced / "runs" / "egreedy-s0" / "checkpoints" / "best.pt").stat().st_mtime_ns
    wall_s = json.loads((reproduced / "table.json").read_text())["wall_s"]
    proc = run_cli("reproduce.py", *TINY, f"out={reproduced}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "0 run(s) to train or finish, 4 already done" in proc.stdout
    # the table keeps the wall-clock of the call that trained, not the re-tabling call's (or none)
    assert wall_s > 0 and json.loads((reproduced / "table.json").read_text())["wall_s"] == wall_s
    assert f"{wall_s / 60:.1f} min." in (reproduced / "table.md").read_text()
    assert (reproduced / "runs" / "egreedy-s0" / "checkpoints" / "best.pt").stat().st_mtime_ns == stamp
    other = run_cli("reproduce.py", *TINY[1:], "budget=demo", f"out={reproduced}")
    assert other.returncode == 2 and "budget" in other.stderr and "fresh out=" in other.stderr


def test_a_clone_rebuilds_the_table_from_the_committed_records(reproduced, tmp_path):
    """What git keeps of a table's folder (its .gitignore: no checkpoints, Hydra files or logs) is
    enough to rebuild the table and the curves without training; the checkpoint figures stay."""
    if subprocess.run(["git", "rev-parse"], cwd=ROOT, capture_output=True).returncode != 0:
        pytest.skip("not a git checkout: .gitignore cannot be asked")
    files = [p.relative_to(reproduced) for p in reproduced.rglob("*") if p.is_file()]
    as_in_repo = [f"results/table/{f}" for f in files]
    ignored = set(subprocess.run(["git", "check-ignore", "--no-index", "--stdin"], cwd=ROOT, input="\n".join(as_in_repo),
                                 capture_output=True, text=True).stdout.split())
    kept = [f for f, r in zip(files, as_in_repo) if r not in ignored]
    assert any(f.parts[-2:] == ("checkpoints", "best.pt") for f in files)
    assert not any("checkpoints" in f.parts or ".hydra" in f.parts for f in kept)
    assert {"scalars.jsonl", "summary.json", "status.json", "config.yaml", "eval.json"} <= {f.name for f in kept}
    clone = tmp_path / "results"
    for f in kept:
        (clone / f).parent.mkdir(parents=True, exist_ok=True)
        (clone / f).write_bytes((reproduced / f).read_bytes())
    (clone / "table.json").unlink()
    (clone / "curves.png").unlink()
    proc = run_cli("reproduce.py", *TINY, f"out={clone}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "0 run(s) to train or finish, 4 already done" in proc.stdout and "no checkpoint" in proc.stdout
    assert not list(clone.glob("runs/*/checkpoints"))
    assert json.loads((clone / "table.json").read_text())["rows"] == json.loads((reproduced / "table.json").read_text())["rows"]
    assert (clone / "curves.png").exists() and (clone / "side_by_side.png").exists()


def test_a_record_whose_discomfort_separation_is_an_overlap_is_read(tmp_path):
    """A collision step counts as discomfort, and its surface distance is negative (the overlap): a smoke run's
    record with min_separation -0.016 was refused by the reader, and reproduce.py stopped after training."""
    from crowdrl.evaluation.report import RecordError, read_eval_record

    record = {"success_rate": 0.5, "collision_rate": 0.5, "timeout_rate": 0.0, "navigation_time": 10.0,
              "average_return": 0.1, "discomfort_frequency": 0.1, "min_separation": -0.016, "episodes": 4}
    path = tmp_path / "eval.json"
    path.write_text(json.dumps(record))
    assert read_eval_record(path)["min_separation"] == -0.016
    path.write_text(json.dumps({**record, "min_separation": "near"}))
    with pytest.raises(RecordError, match="min_separation: must be a finite number"):
        read_eval_record(path)


@pytest.mark.parametrize("field, value", [("success_rate", 7.5), ("collision_rate", "high"), ("episodes", None)])
def test_records_read_back_are_checked_naming_the_file_and_field(tmp_path, field, value):
    from crowdrl.evaluation.report import RecordError, read_eval_record, read_summary

    record = {"success_rate": 0.5, "collision_rate": 0.25, "timeout_rate": 0.25, "navigation_time": 10.0,
              "average_return": 0.1, "discomfort_frequency": 0.0, "min_separation": None, "episodes": 4}
    path = tmp_path / "eval.json"
    path.write_text(json.dumps({**record, field: value}))
    with pytest.raises(RecordError, match=f"^{path}: {field}: must be"):
        read_eval_record(path)
    metrics = {**record, "discomfort_min_separation": record.pop("min_separation"), field: value}
    (tmp_path / "summary.json").write_text(json.dumps({"test": {"metrics": metrics}, "wall_s": 1.0}))
    with pytest.raises(RecordError, match=f"summary.json: test.metrics: {field}: must be"):
        read_summary(tmp_path / "summary.json")
    path.write_text("{not json")
    with pytest.raises(RecordError, match="eval.json: not valid JSON"):
        read_eval_record(path)


def test_reproduce_refuses_a_record_out_of_range_in_one_line(reproduced, tmp_path):
    """An eval.json with success_rate 7.5 became 7.500 in table.md; a string, a traceback."""
    import shutil

    clone = tmp_path / "results"
    shutil.copytree(reproduced, clone, ignore=shutil.ignore_patterns("checkpoints"))
    bad = sorted(clone.glob("runs/*/eval-*/eval.json"))[0]
    bad.write_text(json.dumps(eval_file([{**read_eval_record(bad), "success_rate": 7.5}])))
    table = (clone / "table.md").read_bytes()
    proc = run_cli("reproduce.py", *TINY, f"out={clone}")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert f"{bad}: success_rate: must be a number in [0, 1], got 7.5" in proc.stderr, proc.stderr[-2000:]
    assert (clone / "table.md").read_bytes() == table


def test_reproduce_resumes_killed_runs(reproduced):
    """The runs killed mid-training finished from their checkpoints: the smoke budget exactly, no
    validation logged twice, status completed."""
    for name in json.loads((reproduced / "killed.json").read_text()):
        run_dir = reproduced / "runs" / name
        summary = json.loads((run_dir / "summary.json").read_text())
        assert summary["frames"] == 256
        assert json.loads((run_dir / "status.json").read_text())["state"] == "completed"
        rows = [json.loads(line) for line in (run_dir / "scalars.jsonl").read_text().splitlines()]
        # run_s: the whole run's collection, updates and validation and its test; the timers go on across the
        # kill from the checkpoint (each logged row's at most the next one's), so the first segment counts
        spent = [sum(v for k, v in r.items() if k.startswith("time/") and k.endswith("_s")) for r in rows
                 if r["kind"] == "train"]
        assert spent == sorted(spent) and spent[0] > 0 and spent[-1] <= sum(summary["timers_s"].values())
        assert summary["run_s"] == pytest.approx(sum(summary["timers_s"].values()) + summary["test_s"], rel=1e-9)
        assert 0 < summary["test_s"] < summary["wall_s"]
        val_frames = [r["frames"] for r in rows if r["kind"] == "val"]
        assert val_frames == sorted(set(val_frames))


def test_evaluate_cli_orca(tmp_path):
    """policy=orca through the CLI on square (circle: in-process in tests/test_evaluation.py; a
    checkpoint on both scenarios through the CLI: below)."""
    for scenario in ("square",):
        folder = tmp_path / scenario
        proc = run([*EVALUATE, "policy=orca", f"env={scenario}", "eval.episodes=8", "eval.batch=5",
                    f"hydra.run.dir={folder}"])
        assert proc.returncode == 0, proc.stderr[-2000:]
        rec = read_eval_record(folder / "eval.json")
        assert EVAL_KEYS <= set(rec) and rec["scenario"] == scenario and rec["episodes"] == 8
        assert (folder / "eval.csv").exists() and (folder / f"{scenario}_case0.png").exists()
        assert f"| orca | {scenario} |" in proc.stdout and str(folder) in proc.stdout


def test_evaluate_cli_on_a_checkpoint_equals_its_training_test(reproduced, tmp_path):
    run_dir = reproduced / "runs" / "re3-s1"
    proc = run([*EVALUATE, f"checkpoint={run_dir}", "eval.episodes=6", "eval.batch=4", "eval.record_episode=null",
                f"hydra.run.dir={tmp_path / 'e'}"])
    assert proc.returncode == 0, proc.stderr[-2000:]
    rec = read_eval_record(tmp_path / "e" / "eval.json")
    trained = read_eval_record(run_dir / "eval-circle" / "eval.json")
    for key in ("success_rate", "collision_rate", "timeout_rate", "average_return", "discomfort_frequency"):
        assert rec[key] == trained[key], key
    assert rec["policy"] == "sgd3qn+re3+planning" and rec["train_seed"] == 1  # reproduce.py plans by default
    proc = run([*EVALUATE, f"checkpoint={run_dir / 'checkpoints' / 'best.pt'}", "env=square", "eval.episodes=6",
                "eval.record_episode=2", f"hydra.run.dir={tmp_path / 'sq'}"])  # zero-shot on square, from the .pt
    assert proc.returncode == 0, proc.stderr[-2000:]
    square = read_eval_record(tmp_path / "sq" / "eval.json")
    in_reproduce = read_eval_record(run_dir / "eval-square" / "eval.json")
    assert square["scenario"] == "square" and square["train_scenario"] == "circle"
    assert square["success_rate"] == in_reproduce["success_rate"] and square["average_return"] == in_reproduce["average_return"]
    assert (tmp_path / "sq" / "square_case2.gif").exists()


@pytest.mark.parametrize("args, key", [(["policy=orcx"], "policy"), (["policy=orca", "eval.episodes=0"], "eval.episodes")])
def test_evaluate_cli_bad_input_names_it(tmp_path, args, key):
    proc = run_cli("evaluate.py", *args, f"hydra.run.dir={tmp_path / 'e'}")
    assert proc.returncode in (1, 2) and key in proc.stderr, proc.stderr[-1000:]
    assert not (tmp_path / "e" / "eval.json").exists()


def test_evaluate_cli_rejects_truncated_and_mismatched_checkpoints(reproduced, tmp_path):
    import torch

    best = reproduced / "runs" / "egreedy-s0" / "checkpoints" / "best.pt"
    cut = tmp_path / "cut.pt"
    cut.write_bytes(best.read_bytes()[:1000])
    proc = run_cli("evaluate.py", f"checkpoint={cut}", f"hydra.run.dir={tmp_path / 'e1'}")
    assert proc.returncode == 2 and "cut.pt" in proc.stderr and "truncated" in proc.stderr
    data = torch.load(best, weights_only=True)
    data["net"] = {k: v[..., :1] if v.dim() else v for k, v in data["net"].items()}  # wrong shapes
    torch.save(data, tmp_path / "shape.pt")
    proc = run_cli("evaluate.py", f"checkpoint={tmp_path / 'shape.pt'}", f"hydra.run.dir={tmp_path / 'e2'}")
    assert proc.returncode == 2 and "network shape does not match" in proc.stderr


def test_slurm_launcher_composes_with_the_sweep():
    """`train.py -m hydra/launcher=slurm ...` (what reproduce.py launcher=slurm runs) composes: the
    submitit SLURM launcher with our settings, the run's overrides, no cluster needed."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from crowdrl.training.config import RunConfig

    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["hydra/launcher=slurm", "preset=smoke", "exploration=re3",
                                                       "seed=2", "hydra.sweep.dir=/tmp/x"],
                      return_hydra_config=True)
    assert "submitit" in cfg.hydra.launcher._target_ and "Slurm" in cfg.hydra.launcher._target_
    assert cfg.hydra.launcher.timeout_min == 240 and cfg.hydra.launcher.cpus_per_task == 2
    assert cfg.exploration.name == "re3" and cfg.preset == "smoke"


def test_stats_intervals_and_probability_of_improvement():
    from crowdrl.evaluation.stats import mean_interval, probability_of_improvement

    est = mean_interval({"a": np.array([0.8, 0.9, 1.0]), "b": np.array([0.5, np.nan, 0.7]), "c": np.array([0.4])})
    mean, lo, hi = est["a"]
    assert mean == pytest.approx(0.9) and 0.8 <= lo <= mean <= hi <= 1.0
    assert est["b"][0] == pytest.approx(0.6)  # NaN seeds left out
    assert est["c"] == (0.4, 0.4, 0.4)
    assert probability_of_improvement(np.array([0.9, 0.95]), np.array([0.1, 0.2]))[0] == 1.0
    assert probability_of_improvement(np.array([0.5, 0.5]), np.array([0.5, 0.5]))[0] == 0.5


def test_intervals_depend_on_the_scores_and_seed_only_and_leave_numpys_global_state_alone():
    """rliable resamples with numpy's global generator whatever random_state it is given: the
    intervals must not change with what drew from that generator before, nor disturb it."""
    from crowdrl.evaluation.stats import mean_interval, probability_of_improvement

    x, y = np.array([0.91, 0.87, 0.93]), np.array([0.88, 0.90, 0.85])
    results = []
    for state in (0, 1, 2):
        np.random.seed(state)
        np.random.rand(state + 1)
        results.append((mean_interval({"x": x}, reps=500), probability_of_improvement(x, y, reps=500)))
        after = np.random.rand()
        np.random.seed(state)
        np.random.rand(state + 1)
        assert after == np.random.rand(), "the caller's global numpy stream was disturbed"
    assert results[0] == results[1] == results[2]


def test_ema_weights_each_point_by_its_episodes():
    from crowdrl.viz import ema

    assert ema([1.0, 3.0], 0.0).tolist() == [1.0, 3.0]
    two_points = ema([1.0, 3.0], 0.5, counts=[1, 2])
    per_episode = ema([1.0, 3.0, 3.0], 0.5)  # the second point stands for two episodes
    assert two_points[-1] == pytest.approx(per_episode[-1])
    assert math.isnan(ema([math.nan], 0.9)[0])
    with pytest.raises(ValueError, match="smoothing"):
        ema([1.0], 1.0)


def test_compare_runs_agrees_with_the_reproduce_table(reproduced, tmp_path):
    """experiments/compare_runs.py on the same run folders gives reproduce.py's means and
    probability of improvement (ε-greedy first), and refuses a folder without test results."""
    compare = ["compare_runs.py", "--out", str(tmp_path), "--reps", "200"]  # in this process
    runs = reproduced / "runs"
    groups = ["--group", f"egreedy={runs / 'egreedy-s0'},{runs / 'egreedy-s1'}",
              "--group", f"re3={runs / 're3-s0'},{runs / 're3-s1'}"]
    proc = run_cli(*compare, *groups, "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    ours = {(r["group"], r["scenario"]): r for r in json.loads(proc.stdout)["rows"]}
    theirs = {(r["method"], r["scenario"]): r for r in json.loads((reproduced / "table.json").read_text())["rows"]}
    assert set(ours) == {(m, s) for m in ("egreedy", "re3") for s in ("circle", "square")}
    for key, row in ours.items():
        for metric in ("success_rate", "collision_rate", "average_return"):
            assert row[metric] == pytest.approx(theirs[key][metric]), (key, metric)
    assert ours[("re3", "circle")]["p_improve"] == pytest.approx(theirs[("re3", "circle")]["p_improve"])
    assert "p_improve" not in ours[("egreedy", "circle")] and (tmp_path / "table.md").exists()
    bad = run_cli(*compare, "--group", f"a={runs / 'egreedy-s0'}", "--group", f"b={tmp_path}")
    assert bad.returncode == 2 and "no test record on a scenario in common" in bad.stderr
    bad = run_cli(*compare, "--group", f"a={runs / 'egreedy-s0'}", "--group", f"b={tmp_path}", "--scenarios", "circle")
    assert bad.returncode == 2 and "circle" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize("exploration, anneal", [("egreedy", 200_000), ("re3", 200_000)])
def test_episodes_budget_is_the_papers_episodes_at_the_demos_update_ratio(exploration, anneal):
    """`budget=episodes` (conf/preset/episodes.yaml): the paper's ~10k episodes (500k frames), the
    demo's updates per frame and collection, the paper's target/validation period and schedules."""
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from crowdrl.training.config import RunConfig

    import reproduce as script
    assert "episodes" in script.BUDGETS
    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        demo = compose(config_name="config", overrides=["preset=demo", f"exploration={exploration}"])
        cfg = compose(config_name="config", overrides=["preset=episodes", f"exploration={exploration}"])
    assert cfg.preset == "episodes" and cfg.train.total_frames == 500_000
    for key in ("num_envs", "steps_per_batch", "updates_per_frame", "batch_size", "buffer_size", "test_episodes"):
        assert cfg.train[key] == demo.train[key], key
    assert cfg.train.target_update_frames == cfg.train.val_every_frames == 25_000
    assert cfg.exploration.anneal_frames == anneal and demo.exploration.anneal_frames == 40_000  # make demo's 80k frames


def test_reproduce_with_a_ceiling_adds_the_gap_and_a_ceiling_row(reproduced, tmp_path):
    """``ceiling=<folder>``: each run's and ORCA's gap.json beside its eval.json on the scenarios with a file,
    the table's gap columns and ceiling row; a ceiling file of other cases is refused at start naming ``ceiling``."""
    import shutil

    from crowdrl.evaluation.ceiling import compute_ceiling, write_ceiling
    from crowdrl.training.checkpoint import load_trained_network
    from crowdrl.training.config import crowd_config

    out = tmp_path / "results"
    shutil.copytree(reproduced, out)  # the module's other tests keep theirs as it was
    run_cfg, _, _ = load_trained_network(out / "runs" / "egreedy-s0")
    folder = tmp_path / "ceilings"
    folder.mkdir()
    write_ceiling(folder / "circle.json", compute_ceiling(crowd_config(run_cfg, scenario="circle"), cases=6,
                                                          widths=(32,), chunk=6))
    proc = run_cli("reproduce.py", *TINY, f"out={out}", f"ceiling={folder}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    for run_dir in [*(out / "runs").glob("*-s*"), out / "orca"]:
        if run_dir.is_dir():
            gap = read_eval_record(run_dir / "eval-circle" / "gap.json")
            fails = round((1 - gap["success_rate"]) * 6)
            assert gap["avoidable_failures"] + gap["unavoidable_failures"] + gap["unknown_failures"] == fails
            assert not (run_dir / "eval-square" / "gap.json").exists()
    table = (out / "table.md").read_text()
    circle, square = table.split("## square")
    assert "avoidable failures" in circle and "| ceiling | 1 |" in circle and "avoidable failures" not in square
    write_ceiling(folder / "circle.json", compute_ceiling(crowd_config(run_cfg, scenario="circle"), cases=5,
                                                          widths=(32,), chunk=5))
    refused = run_cli("reproduce.py", *TINY, f"out={out}", f"ceiling={folder}")
    assert refused.returncode == 2 and "ceiling:" in refused.stderr and "cases 5" in refused.stderr, refused.stderr


def test_a_runs_record_is_cross_checked_against_its_own_summary(tmp_path):
    """Issue 52 (D15): a hand-edited, in-range eval-circle/eval.json (success 0.0 -> 0.99) made the table while the
    run's summary.json, the same checkpoint on the same scenario and cases, still said 0.0: now refused naming the
    file; a record of another test (other cases, another scenario, another crowd) is not compared."""
    from omegaconf import OmegaConf

    from crowdrl.evaluation.report import RecordError, read_run_eval_record
    from crowdrl.reproduction.table import collect
    from crowdrl.reproduction.plan import eval_path, make_plan
    from crowdrl.resources import config_dir

    cfg = OmegaConf.to_container(OmegaConf.load(config_dir() / "reproduce.yaml"))
    cfg.pop("hydra")
    cfg.pop("defaults")
    cfg.update(out=str(tmp_path), budget="smoke", variants=["egreedy"], seeds=[0], episodes=6)
    plan = make_plan(cfg)
    run_dir = plan.run_dir(plan.methods[0], 0)
    metrics = {"episodes": 6, "success_rate": 0.0, "collision_rate": 0.5, "timeout_rate": 0.5, "navigation_time": None,
               "average_return": -0.125, "discomfort_frequency": 0.25, "discomfort_min_separation": 0.05}
    run_dir.mkdir(parents=True)
    (run_dir / "config.yaml").write_text("env:\n  scenario: circle\n")
    (run_dir / "summary.json").write_text(json.dumps({"test": {"checkpoint_frames": 640, "test_seed": 0,
                                                               "metrics": metrics}, "wall_s": 1.0}))
    record = {**{k: v for k, v in metrics.items() if k != "discomfort_min_separation"}, "min_separation": 0.05,
              "seed": 0, "policy": "sgd3qn+egreedy", "checkpoint": str(run_dir / "checkpoints" / "best.pt"),
              "checkpoint_frames": 640, "train_scenario": "circle", "train_seed": 0}
    for scenario in plan.scenarios:
        for path in (eval_path(run_dir, scenario), plan.out / "orca" / f"eval-{scenario}" / "eval.json"):
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({**record, "scenario": scenario, "success_rate": 0.5, "timeout_rate": 0.0}
                                       if scenario != "circle" else {**record, "scenario": scenario}))
    assert collect(plan)["egreedy"]["circle"][0]["success_rate"] == 0.0  # agrees with summary.json
    edited = eval_path(run_dir, "circle")
    edited.write_text(json.dumps({**record, "scenario": "circle", "success_rate": 0.99}))
    words = f"{edited}: success_rate: 0.99 disagrees with the run's own {run_dir / 'summary.json'}"
    with pytest.raises(RecordError, match=re.escape(words)):
        collect(plan)
    # another test of the same run is not the summary's: other cases, another crowd, another checkpoint
    for other in ({"episodes": 1000}, {"seed": 1}, {"human_model": "linear"}, {"checkpoint_frames": 320}):
        edited.write_text(json.dumps({**record, "scenario": "circle", "success_rate": 0.99, **other}))
        assert read_run_eval_record(edited, run_dir)["success_rate"] == 0.99
    (run_dir / "summary.json").unlink()  # nothing to compare with
    edited.write_text(json.dumps({**record, "scenario": "circle", "success_rate": 0.99}))
    assert read_run_eval_record(edited, run_dir)["success_rate"] == 0.99


def test_one_reader_for_every_eval_json_layout(tmp_path):
    """Issue 53 item 4: version 2 round-trips; the layouts before it (a flat record, a list, a training run's
    nested test) read as the same records; a newer version and another format are refused naming the file."""
    from crowdrl.evaluation.report import EVAL_VERSION, RecordError, read_eval_records, write_records

    record = {"success_rate": 0.9, "collision_rate": 0.1, "timeout_rate": 0.0, "navigation_time": 11.0,
              "average_return": 0.6, "discomfort_frequency": 0.05, "min_separation": 0.15, "episodes": 10,
              "seed": 0, "scenario": "circle", "policy": "x"}
    path, _ = write_records(tmp_path, [record, {**record, "scenario": "square"}])
    data = json.loads(path.read_text())
    assert (data["format"], data["version"]) == ("crowdrl.eval", EVAL_VERSION)
    assert read_eval_records(path) == [record, {**record, "scenario": "square"}]
    with pytest.raises(RecordError, match="holds 2 records"):
        read_eval_record(path)
    for legacy in (record, [record]):
        path.write_text(json.dumps(legacy))
        assert read_eval_records(path) == [record]
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("env:\n  scenario: circle\n")
    metrics = {**{k: v for k, v in record.items() if k not in ("min_separation", "seed", "scenario", "policy")},
               "discomfort_min_separation": 0.15}
    (run / "eval.json").write_text(json.dumps({"checkpoint_frames": 64, "test_seed": 0, "metrics": metrics}))
    old = read_eval_record(run / "eval.json")
    assert {k: old[k] for k in ("success_rate", "min_separation", "seed", "scenario", "checkpoint_frames")} == \
        {"success_rate": 0.9, "min_separation": 0.15, "seed": 0, "scenario": "circle", "checkpoint_frames": 64}
    for payload, words in (({"format": "crowdrl.eval", "version": EVAL_VERSION + 1, "records": [record]},
                            f"version {EVAL_VERSION + 1} was written by a newer crowdrl"),
                           ({"format": "other", "version": 2, "records": [record]}, "format: expected 'crowdrl.eval'"),
                           ({"format": "crowdrl.eval", "version": 2, "records": []}, "records: expected a non-empty"),
                           ({"format": "crowdrl.eval", "version": 2, "records": [{**record, "success_rate": 2}]},
                            "success_rate: must be a number in [0, 1]")):
        path.write_text(json.dumps(payload))
        with pytest.raises(RecordError, match=re.escape(f"{path}")) as err:
            read_eval_records(path)
        assert words in str(err.value)


def test_reusing_a_training_test_reads_a_folder_that_predates_later_keys(tmp_path):
    """reproduce copies a finished run's own test record; a committed run folder whose config.yaml predates
    ``env.mix`` (and other later keys) is read with what it ran with: trained on its scenario, not refused."""
    import shutil

    from crowdrl.cli.reproduce import reuse_training_test
    from crowdrl.evaluation.report import read_eval_record

    old = Path(__file__).resolve().parents[1] / "results" / "demo-planning" / "runs" / "egreedy-s0"
    assert "mix" not in (old / "config.yaml").read_text()
    for name in ("config.yaml", "summary.json"):
        shutil.copyfile(old / name, tmp_path / name)
    assert reuse_training_test(tmp_path, "circle", 1000)
    record = read_eval_record(tmp_path / "eval-circle" / "eval.json")
    assert record["train_scenario"] == "circle" and record["policy"] == "sgd3qn+egreedy+planning"
    assert record["reused_from"] == "summary.json" and not reuse_training_test(tmp_path, "square", 1000)
