"""``experiments/compare_runs.py --split val``: arms compared on the validations their runs logged."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from crowdrl.evaluation.report import read_eval_record
from crowdrl_testing.cli import run_cli

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "experiments" / "compare_runs.py"


def _in_process(argv: list[str]) -> subprocess.CompletedProcess:
    """``compare_runs.py`` with ``argv``, run in this process (:func:`crowdrl_testing.cli.run_cli`)."""
    return run_cli("compare_runs.py", *argv)


def _run_folder(path: Path, successes: list[float], timeouts: list[float]) -> Path:
    path.mkdir(parents=True)
    rows = [{"kind": "train", "frames": 5, "train/success_rate": 1.0}]
    rows += [{"kind": "val", "frames": 10 * (i + 1), "val/episodes": 100, "val/success_rate": s,
              "val/timeout_rate": t, "val/collision_rate": round(1 - s - t, 6)}
             for i, (s, t) in enumerate(zip(successes, timeouts))]
    (path / "scalars.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_val_split_averages_the_last_validations_and_keeps_the_best(tmp_path):
    a = [_run_folder(tmp_path / f"a{s}", [0.5, 0.9, 0.8, 0.8], [0.0, 0.0, 0.1, 0.0]) for s in range(2)]
    b = [_run_folder(tmp_path / f"b{s}", [0.6, 0.95, 0.3, 0.2], [0.0, 0.0, 0.6, 0.7]) for s in range(2)]
    cmd = ["--split", "val", "--last", "2", "--reps", "200", "--out", str(tmp_path / "out"), "--json",
           "--group", "A=" + ",".join(map(str, a)), "--group", "B=" + ",".join(map(str, b))]
    proc = subprocess.run([sys.executable, str(SCRIPT), *cmd], capture_output=True, text=True, timeout=120)  # the CLI
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {r["group"]: r for r in json.loads(proc.stdout)["rows"]}
    assert rows["A"]["success_rate"] == pytest.approx(0.8) and rows["A"]["timeout_rate"] == pytest.approx(0.05)
    assert rows["B"]["success_rate"] == pytest.approx(0.25) and rows["B"]["timeout_rate"] == pytest.approx(0.65)
    assert rows["B"]["best_success_rate"] == 0.95  # the best validation hides B's late fall
    assert rows["B"]["p_improve"] == 0.0 and rows["A"]["episodes"] == 200
    # stability: the last validations below the best, and the largest fall below the running best late on
    assert rows["A"]["gap_to_best"] == pytest.approx(0.1) and rows["B"]["gap_to_best"] == pytest.approx(0.7)
    assert rows["A"]["late_drop"] == pytest.approx(0.1) and rows["B"]["late_drop"] == pytest.approx(0.75)
    none_after = _in_process([*cmd, "--after", "40"])
    assert none_after.returncode == 0, none_after.stderr[-2000:]
    assert all(r["late_drop"] == 0.0 for r in json.loads(none_after.stdout)["rows"])  # no validation after 40 frames
    assert "validation" in (tmp_path / "out" / "table.md").read_text()
    # the frames to the first validation that reaches a success rate: A's seeds reach 0.9 at frame 20, B's seed 0
    # only 0.6 (its seed 1 reaches 0.95 at 20); 0.96 is reached by none
    assert rows["A"]["frames_to_reach"] == 10 and rows["A"]["reached"] == 2  # --reach 0.5 by default
    b[0].joinpath("scalars.jsonl").write_text(b[0].joinpath("scalars.jsonl").read_text().replace('"val/success_rate": 0.95',
                                                                                                 '"val/success_rate": 0.6'))
    high = _in_process([*cmd, "--reach", "0.9"])
    assert high.returncode == 0, high.stderr[-2000:]
    rows = {r["group"]: r for r in json.loads(high.stdout)["rows"]}
    assert rows["A"]["frames_to_reach_per_seed"] == [20, 20] and rows["B"]["reached"] == 1
    text = (tmp_path / "out" / "table.md").read_text()
    assert "| 1/2 reached (20) |" in text and "frames to first val. ≥ 0.9" in text
    never = _in_process([*cmd, "--reach", "0.96"])
    assert never.returncode == 0 and "0/2 reached |" in (tmp_path / "out" / "table.md").read_text()
    bad = _in_process([*cmd, "--reach", "0"])
    assert bad.returncode == 2 and "--reach must lie in (0, 1], got 0.0" in bad.stderr
    short = _in_process([*cmd[:-4], "--last", "9", "--group", "A=" + str(a[0]), "--group", "B=" + str(b[0])])
    assert short.returncode != 0 and "fewer than --last 9" in short.stderr


def _compare(*args: str) -> subprocess.CompletedProcess:
    return _in_process(["--reps", "200", *args])


def test_val_split_names_the_episodes_the_validations_held(tmp_path):
    from tests.test_sweep_summary import fake_run

    runs = [fake_run(tmp_path / f"r{s}", [f"seed={s}"], frames=512) for s in range(2)]
    proc = _compare("--split", "val", "--last", "2", "--out", str(tmp_path / "out"),
                    "--group", f"A={runs[0]}", "--group", f"B={runs[1]}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = (tmp_path / "out" / "table.md").read_text()
    assert "(2 x 4 episodes at the end of training)" in text and "x 100" not in text


def test_run_folders_of_a_sweep_commas_and_all_compare_on_train_pys_own_test(tmp_path):
    """Paths with commas are joined back; a run folder as train.py writes it (top-level eval.json) counts
    for its training scenario, and an eval-<scenario>/eval.json beside it is preferred."""
    from tests.test_sweep_summary import fake_sweep

    sweep = fake_sweep(tmp_path / "multirun" / "s", [(["exploration.beta=0.005", "exploration=re3", f"seed={s}"],
                                                      {"success": 0.5 + 0.1 * s}) for s in range(2)]
                       + [(["exploration.beta=0.01", "exploration=re3", f"seed={s}"], {"success": 0.8}) for s in range(2)])
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert all("," in j.name for j in jobs)
    other = {**read_eval_record(jobs[2] / "eval.json"), "episodes": 100, "success_rate": 0.1,
             "collision_rate": 0.1, "timeout_rate": 0.8, "scenario": "circle", "seed": 0,
             "min_separation": 0.07}
    (jobs[2] / "eval-circle").mkdir()
    (jobs[2] / "eval-circle" / "eval.json").write_text(json.dumps(other))
    out = tmp_path / "out"
    proc = _compare("--out", str(out), "--json", "--group", f"low={jobs[0]},{jobs[1]}",
                    "--group", f"high={jobs[2]},{jobs[3]}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout)
    assert result["groups"]["low"] == [str(jobs[0]), str(jobs[1])]
    rows = {r["group"]: r for r in result["rows"]}
    assert [r["scenario"] for r in result["rows"]] == ["circle", "circle"]  # the one scenario every run holds
    assert rows["low"]["success_rate_per_seed"] == pytest.approx([0.5, 0.6])
    assert rows["high"]["success_rate_per_seed"] == pytest.approx([0.1, 0.8])  # eval-circle/eval.json first
    assert rows["high"]["episodes_per_seed"] == [100, 8] and "8/100 test cases per run" in (out / "table.md").read_text()
    # a scenario a run holds no record on: one line naming the run and the record, nothing written
    missing = _compare("--out", str(tmp_path / "new"), "--scenarios", "square", "--group", f"low={jobs[0]}",
                       "--group", f"high={jobs[2]}")
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1, missing.stderr
    assert f"--group 'low': {jobs[0]}: no eval-square/eval.json, its own test (eval.json) is on circle" in missing.stderr
    assert not (tmp_path / "new").exists()


def test_two_sweeps_compare_in_one_command(tmp_path):
    from tests.test_sweep_summary import fake_sweep

    a = fake_sweep(tmp_path / "A", [(["exploration=egreedy", f"seed={s}"], {"success": 0.5}) for s in range(3)])
    b = fake_sweep(tmp_path / "B", [(["exploration.beta=0.005", "exploration=re3", "seed=0"], {"success": 0.9}),
                                    (["exploration.beta=0.005", "exploration=re3", "seed=1"], {"state": "failed"}),
                                    (["exploration.beta=0.01", "exploration=re3", "seed=0"], {"success": 0.7})])
    out = tmp_path / "out"
    proc = _compare("--sweep", str(a), "--sweep", str(b), "--out", str(out), "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {r["group"]: r for r in json.loads(proc.stdout)["rows"]}
    assert list(rows) == ["A: exploration=egreedy", "B: exploration.beta=0.005", "B: exploration.beta=0.01"]
    assert rows["A: exploration=egreedy"]["seeds"] == 3 and rows["B: exploration.beta=0.005"]["seeds"] == 1
    assert rows["B: exploration.beta=0.005"]["p_improve"] == 1.0
    assert "left out (not completed)" in proc.stderr and "seed=1 (failed)" in proc.stderr
    assert "## circle" in (out / "table.md").read_text()
    # a group and a sweep mix, in command-line order; a label given twice and a folder that is no sweep: refused
    mixed = _compare("--group", f"base={next(p for p in a.iterdir() if p.is_dir())}", "--sweep", str(b),
                     "--out", str(tmp_path / "mixed"), "--json")
    assert mixed.returncode == 0 and json.loads(mixed.stdout)["rows"][0]["group"] == "base"
    for args, words in ((["--sweep", str(a), "--sweep", str(a)], "--sweep: the label 'A: exploration=egreedy'"),
                        (["--sweep", str(a), "--sweep", str(tmp_path)], "--sweep: "),
                        (["--sweep", str(a), "--sweep", str(tmp_path / "none")], "is not a folder")):
        bad = _compare(*args, "--out", str(tmp_path / "bad"))
        assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and words in bad.stderr, bad.stderr
    assert not (tmp_path / "bad").exists()
