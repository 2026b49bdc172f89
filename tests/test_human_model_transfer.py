"""``experiments/human_model_transfer.py``: which overrides each (human model x visibility) cell gives
``evaluate.py`` and ``train.py``, which agents it tests, and the table it builds from the records."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from crowdrl.evaluation.report import write_records

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def transfer():
    spec = importlib.util.spec_from_file_location("human_model_transfer", ROOT / "experiments" / "human_model_transfer.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_each_cell_gives_its_human_model_shares_and_visibility(transfer):
    assert transfer.cell_overrides("orca-visible", "eval") == ["eval.human_model=orca", "eval.robot_visible=true"]
    assert transfer.cell_overrides("mixed", "env") == ["env.human_model=mixed", "env.social_force_share=0.3",
                                                       "env.linear_share=0.3", "env.robot_visible=false"]
    assert set(transfer.TRAINED.values()) <= set(transfer.CELLS)


def test_the_pretrained_groups_name_agents_that_ship(transfer, tmp_path):
    table = transfer.agents(tmp_path, [*transfer.PRETRAINED, "orca-robot"], [0, 1, 2])
    for group in transfer.PRETRAINED:
        assert list(table[group]) == [f"{group}-s{s}" for s in (0, 1, 2)]
        assert all(transfer.has_checkpoint(Path(folder)) for folder in table[group].values()), table[group]
    assert table["orca-robot"] == {"orca-robot": None}


def test_the_table_is_the_mean_over_the_seeds_recorded(transfer, tmp_path):
    def record(label: str, cell: str, success: float) -> None:
        folder = tmp_path / "evals" / label / cell
        folder.mkdir(parents=True)
        write_records(folder, [{"success_rate": success, "collision_rate": 1 - success, "timeout_rate": 0.0,
                                "navigation_time": 12.0, "average_return": 0.5, "discomfort_frequency": 0.1,
                                "min_separation": 0.1, "episodes": 10, "seed": 0, "scenario": "circle"}])

    record("pretrained-s0", "orca", 0.9)
    record("pretrained-s1", "orca", 0.7)
    record("orca-robot", "orca", 0.8)
    record("pretrained-s0", "linear", 0.6)  # a cell not asked for: left out
    code = transfer.main(["--out", str(tmp_path), "--table-only", "--seeds", "0", "1", "--cells", "orca",
                          "--episodes", "10"])
    assert code == 0
    rows = json.loads((tmp_path / "table.json").read_text())["rows"]
    by = {(r["group"], r["cell"]): r for r in rows}
    assert set(by) == {("pretrained", "orca"), ("orca-robot", "orca")}  # no records: no pretrained-polyak row
    assert by["pretrained", "orca"]["seeds"] == 2
    assert by["pretrained", "orca"]["success_rate"] == pytest.approx(0.8)
    assert by["pretrained", "orca"]["success_rate_per_seed"] == [0.9, 0.7]
    assert by["orca-robot", "orca"]["success_rate"] == pytest.approx(0.8)
    assert "| pretrained | orca | 2 | 0.800" in (tmp_path / "table.md").read_text()


def test_the_depth2_group_acts_with_its_overrides(transfer, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(transfer.subprocess, "call", lambda cmd, **kw: calls.append(cmd) or 0)
    transfer.test_one("agent", tmp_path / "a", "orca", "circle", 5, transfer.ACTING["pretrained-polyak-depth2"])
    transfer.test_one("agent", tmp_path / "b", "orca", "circle", 5)
    assert "eval.planning_depth=2" in calls[0]
    assert not any("planning_depth" in arg for arg in calls[1])
    assert set(transfer.ACTING) <= set(transfer.PRETRAINED)
