"""``experiments/compare_runs.py --split val``: arms compared on the validations their runs logged."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
    cmd = [sys.executable, str(ROOT / "experiments" / "compare_runs.py"), "--split", "val", "--last", "2",
           "--reps", "200", "--out", str(tmp_path / "out"), "--json",
           "--group", "A=" + ",".join(map(str, a)), "--group", "B=" + ",".join(map(str, b))]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {r["group"]: r for r in json.loads(proc.stdout)["rows"]}
    assert rows["A"]["success_rate"] == pytest.approx(0.8) and rows["A"]["timeout_rate"] == pytest.approx(0.05)
    assert rows["B"]["success_rate"] == pytest.approx(0.25) and rows["B"]["timeout_rate"] == pytest.approx(0.65)
    assert rows["B"]["best_success_rate"] == 0.95  # the best validation hides B's late fall
    assert rows["B"]["p_improve"] == 0.0 and rows["A"]["episodes"] == 200
    # stability: the last validations below the best, and the largest fall below the running best late on
    assert rows["A"]["gap_to_best"] == pytest.approx(0.1) and rows["B"]["gap_to_best"] == pytest.approx(0.7)
    assert rows["A"]["late_drop"] == pytest.approx(0.1) and rows["B"]["late_drop"] == pytest.approx(0.75)
    none_after = subprocess.run([*cmd, "--after", "40"], capture_output=True, text=True, timeout=120)
    assert none_after.returncode == 0, none_after.stderr[-2000:]
    assert all(r["late_drop"] == 0.0 for r in json.loads(none_after.stdout)["rows"])  # no validation after 40 frames
    assert "validation" in (tmp_path / "out" / "table.md").read_text()
    short = subprocess.run([*cmd[:-4], "--last", "9", "--group", "A=" + str(a[0]), "--group", "B=" + str(b[0])],
                           capture_output=True, text=True, timeout=120)
    assert short.returncode != 0 and "fewer than --last 9" in short.stderr
