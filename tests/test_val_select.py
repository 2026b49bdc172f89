"""experiments/val_select.py: a run's kept networks on more validation cases, per scenario."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GENERALIST = ROOT / "pretrained" / "sgd3qn-planning-egreedy-counterfactual-polyak-episodes2x-mix-s1"
ITS_RUN = ROOT / "results" / "mix-episodes2x" / "runs" / "egreedy-s1"


def _script():
    import val_select

    return val_select


def test_it_replays_the_validation_the_mixed_run_logged_for_its_best_network(capsys):
    """The generalist's best network was chosen at its validation of 451,584 frames, where square's 12 cases
    (rows 13-24 of the 100 validation envs, 13 circle rows before them: each row plays the case of its index)
    logged 11 successes. The script, on those cases of square's validation stream, must find the same."""
    logged = [json.loads(line) for line in (ITS_RUN / "scalars.jsonl").read_text().splitlines()
              if '"kind": "val"' in line and '"val/best"' in line]
    best = logged[-1]
    assert best["frames"] == 451584
    rows = _script().main([str(GENERALIST), "--networks", "best", "--scenarios", "square", "--first", "13",
                           "--episodes", "12", "--json"])
    assert rows[0]["square"]["success"] == pytest.approx(best["val/square/success_rate"]) == pytest.approx(11 / 12)
    assert rows[0]["mean"] == rows[0]["mix_weighted"] == rows[0]["square"]["success"]  # one scenario: the means agree
    assert json.loads(capsys.readouterr().out)["meta"]["first"] == 13


@pytest.mark.parametrize("argv, words", [
    (["--networks", "nowhere"], "--networks: neither"),
    (["--scenarios", "moon"], "--scenarios: unknown moon"),
    (["--first", "-1"], "--first: must be >= 0"),
    (["--episodes", "0"], "--episodes: must be >= 1"),
])
def test_bad_arguments_are_refused_naming_them(argv, words, capsys):
    with pytest.raises(SystemExit):
        _script().main([str(GENERALIST), *argv])
    assert words in capsys.readouterr().err
