"""``experiments/bench_env.py --compare-obstacles`` runs on a tiny budget and reports consistent figures."""

import json
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench(*args: str) -> subprocess.CompletedProcess:
    """``bench_env.py <args>`` in this process (:func:`crowdrl_testing.cli.run_cli`)."""
    from crowdrl_testing.cli import run_cli

    return run_cli("bench_env.py", *args)


def test_compare_obstacles_reports_both_scenarios_and_their_ratios():
    pytest.importorskip("pyrvo")
    proc = _bench("--compare-obstacles", "--batch-sizes", "4", "--steps", "2", "--warmup", "1", "--ref-steps", "20",
                  "--no-memory", "--json")
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


def test_compare_humans_takes_the_median_of_rounds_and_its_ratio_to_orca():
    proc = _bench("--compare-humans", "--batch-sizes", "4", "--steps", "2", "--warmup", "1", "--rounds", "3",
                  "--no-memory", "--no-env", "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["meta"]["rounds"] == 3
    rows = {r["humans"]: r for r in out["rows"]}
    assert len(rows) == 6 and {"orca", "social_force", "social_force (robot visible)", "linear"} <= set(rows)
    orca = rows["orca"]
    for row in rows.values():
        assert len(row["core_sps_rounds"]) == 3 and row["core_sps"] == sorted(row["core_sps_rounds"])[1]
        assert row["core_vs_orca"] == pytest.approx(row["core_sps"] / orca["core_sps"])
        assert row["core_vs_orca_rounds"] == pytest.approx(
            [r / o for r, o in zip(row["core_sps_rounds"], orca["core_sps_rounds"])])
    assert orca["core_vs_orca"] == 1.0


@pytest.mark.parametrize("args, message", [(("--compare-humans", "--rounds", "0"), "--rounds must be >= 1, got 0"),
                                           (("--rounds", "2",), "--rounds applies to --compare-humans only")])
def test_bad_rounds_are_refused_naming_the_flag(args, message):
    proc = _bench(*args, "--no-memory")
    assert proc.returncode == 2 and message in proc.stderr
