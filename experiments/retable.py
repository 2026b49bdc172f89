"""Rebuild every committed ``reproduce.py`` table from its tracked run records, in a temporary copy, and compare.

For each ``results/**/manifest.json`` in git: the folder's tracked files are copied to a temporary folder and
``reproduce.py`` is called there with the settings its manifest and table name (budget, scenarios, seeds,
variants, encoders, learner, levers, lidar; the committed ceilings for a table with a ceiling row), which
trains nothing when every run's records are there; the rebuilt ``table.json`` rows are compared with the
committed ones. A folder that tracks fewer run records than its table has runs is skipped (a rebuild would
train). Prints one line per folder; exit status 1 if a rebuilt table differs or a rebuild fails.

    python experiments/retable.py                                  # every committed table
    python experiments/retable.py results/demo-intrinsic results/obstacles-demo/room
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the ceiling files every committed table with a ceiling row was made with (relative: reproduce.py runs in the repo)
CEILINGS = "results/ceiling"


def tracked(pattern: str) -> list[str]:
    return subprocess.run(["git", "ls-files", pattern], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()


def overrides(table: dict) -> list[str]:
    """The ``reproduce.py`` settings that made ``table`` (its manifest, seeds and rows)."""
    man, rows = table["manifest"], table["rows"]
    methods = list(dict.fromkeys(r["method"] for r in rows if r["method"] not in ("orca", "ceiling")))
    encoders = sorted({m.split("+")[0] if "+" in m else "sgd3qn" for m in methods})
    variants = list(dict.fromkeys(m.split("+")[-1] for m in methods))
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    out = [f"budget={man['budget']}", f"train_scenario={man['train_scenario']}", f"episodes={man['episodes']}",
           f"planning={str(man.get('planning', False)).lower()}", f"seeds=[{','.join(map(str, table['seeds']))}]",
           f"variants=[{','.join(variants)}]", f"encoders=[{','.join(encoders)}]", f"scenarios=[{','.join(scenarios)}]",
           "jobs=1"]
    if any(r["method"] == "ceiling" for r in rows):  # made with ceiling=: the committed ceilings (results/ceiling)
        out.append(f"ceiling={CEILINGS}")
    counterfactual = man.get("counterfactual")
    if counterfactual is None:  # a manifest from before the key: the plain learner
        return [*out, "train_learner=plain"]
    out += [f"counterfactual.{k}={v}" for k, v in counterfactual.items()]
    text = lambda v: "null" if v is None else str(v).lower() if isinstance(v, bool) else str(v)  # noqa: E731
    out += [f"train.{k}={text(v)}" for k, v in man.get("levers", {"target_tau": 1.0}).items()]
    lidar = man.get("lidar")
    if lidar and lidar["encoder"] != "off":
        out += [f"lidar={lidar['encoder']}", f"lidar_rays={lidar['rays']}"]
    return out


def retable(folder: Path) -> tuple[bool | None, str]:
    """``(rows identical, what happened)``; ``None``: skipped."""
    table = json.loads((ROOT / folder / "table.json").read_text())
    args = overrides(table)
    files = tracked(str(folder))
    runs = len([a for a in args if a.startswith("variants=")][0].split(",")) * len(table["seeds"])
    runs *= len([a for a in args if a.startswith("encoders=")][0].split(","))
    statuses = [f for f in files if f.endswith("/status.json") and "/runs/" in f]
    if len(statuses) < runs:
        return None, f"skipped, {len(statuses)} of {runs} runs' records tracked (a rebuild would train)"
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            dst = Path(tmp) / Path(f).relative_to(folder)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, dst)
        proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "reproduce.py"), *args, f"out={tmp}"], cwd=ROOT,
                              capture_output=True, text=True, env={**os.environ, "WANDB_MODE": "offline"})
        if proc.returncode != 0:
            return False, f"rebuild failed ({proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}"
        if "0 run(s) to train" not in proc.stdout:
            return False, "the rebuild trained runs: the records are incomplete"
        rebuilt = json.loads((Path(tmp) / "table.json").read_text())["rows"]
    if rebuilt == table["rows"]:
        return True, f"rows identical ({len(rebuilt)} rows)"
    diff = [(a.get("method"), a.get("scenario"), k) for a, b in zip(table["rows"], rebuilt) for k in sorted(set(a) | set(b))
            if a.get(k) != b.get(k)]
    return False, f"rows differ ({len(table['rows'])} vs {len(rebuilt)} rows; first: {diff[:3]})"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="*", type=Path, help="default: every folder with a committed manifest.json")
    args = p.parse_args(argv)
    folders = args.folders or [Path(m).parent for m in tracked("results/**/manifest.json")]
    bad = 0
    for folder in folders:
        if not (ROOT / folder / "table.json").is_file():
            p.exit(2, f"{p.prog}: {folder}: no table.json (not a reproduce.py folder)\n")
        same, said = retable(folder)
        bad += same is False
        print(f"{folder}: {said}", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
