"""``experiments/bench_env.py --compare-obstacles`` runs on a tiny budget and reports consistent figures."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_compare_obstacles_reports_both_scenarios_and_their_ratios():
    pytest.importorskip("pyrvo")
    cmd = [sys.executable, str(ROOT / "experiments" / "bench_env.py"), "--compare-obstacles", "--batch-sizes", "4",
           "--steps", "2", "--warmup", "1", "--ref-steps", "20", "--no-memory", "--json"]
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "RL_LOGGING_LEVEL": "WARNING"}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["meta"]["compare_obstacles"] == "doorway"
    circle, doorway = out["rows"]
    assert (circle["scenario"], circle["edges"], doorway["scenario"], doorway["edges"]) == ("circle", 0, "doorway", 2)
    assert all(r["B"] == 4 and r["N"] == 10 and r["core_sps"] > 0 and r["env_sps"] > 0 and r["ref_sps"] > 0
               for r in (circle, doorway))
    assert doorway["core_vs_circle"] == pytest.approx(doorway["core_sps"] / circle["core_sps"])
    assert doorway["env_vs_circle"] == pytest.approx(doorway["env_sps"] / circle["env_sps"])
    assert doorway["speedup_vs_ref"] == pytest.approx(doorway["core_sps"] / doorway["ref_sps"])
    assert 0 < doorway["ref_waypoint_share"] < 1 and "core_vs_circle" not in circle
    assert set(out["reference"]) == {"circle N=10", "doorway N=10"}
