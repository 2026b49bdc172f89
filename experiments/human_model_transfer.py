"""What other humans do to trained agents: SG-D3QN agents and the ORCA robot tested on every (human model
x robot visibility) cell, zero-shot and after training on a cell.

Cells (``eval.human_model``, ``eval.robot_visible``): ``orca`` blind (the paper's protocol), ``orca`` seeing
the robot, ``social_force`` blind and seeing the robot, ``linear`` (which ignores everyone: seeing the robot
changes nothing, so it has one cell), ``mixed`` (a mixed crowd, blind: ``social_force_share`` and ``linear_share``
0.3 each, ORCA the rest; its ``eval.*_share`` keys are ``evaluate.py``'s). Agents, one group each, over seeds:

* ``pretrained-polyak``: ``pretrained/sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s{0,1,2}`` (the
  full learner, counterfactual experience with Polyak targets, the best agents crowdrl ships), zero-shot likewise;
* ``pretrained-polyak-depth2``: the same agents acting with the depth-2 look-ahead (``eval.planning_depth=2``, the
  best act-time setting of ``docs/ceiling.md``), zero-shot likewise;
* ``pretrained``: ``pretrained/sgd3qn-planning-egreedy-episodes-s{0,1,2}`` (trained on blind ORCA at the
  episodes budget), zero-shot on every other cell;
* ``orca-robot``: the ORCA robot (deterministic: one evaluation per cell);
* with ``--train``: SG-D3QN + planning, ε-greedy, ``learner=plain``, trained at ``--preset`` (default ``demo``) on blind ORCA
  (``trained-orca``, the control at the same budget), on ORCA seeing the robot (``trained-orca-visible``) and
  on social-force humans (``trained-social_force``), each then tested on every cell.

Each test: 1000 test cases of ``--scenario`` (default circle), test seed 0, written to
``<out>/evals/<agent>/<cell>/eval.json`` by ``evaluate.py`` (skipped when there; killed training runs resume).
The table (``table.md``, ``table.json``): per group and cell, the mean over seeds of success and collision
with a 95 % stratified-bootstrap interval (rliable), and navigation time.

    python experiments/human_model_transfer.py --out results/human-models --jobs 2            # zero-shot
    python experiments/human_model_transfer.py --out results/human-models --train --jobs 2    # + trained on cells
    python experiments/human_model_transfer.py --out results/human-models --table-only
    python experiments/human_model_transfer.py --out /tmp/hm --preset smoke --train --episodes 20 --seeds 0
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np

from crowdrl.evaluation.report import RecordError, read_eval_record
from crowdrl.evaluation.stats import mean_interval
from crowdrl.files import atomic_write_bytes, atomic_write_json
from crowdrl.reproduction.plan import train_to_completion
from crowdrl.tables import interval_cell, markdown_table

ROOT = Path(__file__).resolve().parent.parent
CELLS = {  # name -> (eval.human_model, eval.robot_visible)
    "orca": ("orca", False),
    "orca-visible": ("orca", True),
    "social_force": ("social_force", False),
    "social_force-visible": ("social_force", True),
    "linear": ("linear", False),
    "mixed": ("mixed", False),
}
SHARES = {"mixed": (0.3, 0.3)}  # a mixed cell's (social_force_share, linear_share); ORCA the rest
TRAINED = {  # group -> the training cell
    "trained-orca": "orca",
    "trained-orca-visible": "orca-visible",
    "trained-social_force": "social_force",
}
PRETRAINED = {  # group -> the agents' folders
    "pretrained": "pretrained/sgd3qn-planning-egreedy-episodes-s{seed}",
    "pretrained-polyak": "pretrained/sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s{seed}",
    "pretrained-polyak-depth2": "pretrained/sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s{seed}",
}
ACTING = {"pretrained-polyak-depth2": ["eval.planning_depth=2"]}  # group -> evaluate.py's act-time overrides
# learner=plain (no counterfactual experience, hard target copies): the learner results/human-models' runs trained with
TRAIN_BASE = ["learner=plain", "logger=csv", "logger.progress_bar=false", "logger.render=false", "train.compile_acting=true",
              "train.test_episodes=100"]  # the test here is evaluate.py's on every cell


def cell_overrides(cell: str, prefix: str) -> list[str]:
    model, visible = CELLS[cell]
    shares = [f"{prefix}.{key}={share}" for key, share in zip(("social_force_share", "linear_share"), SHARES[cell])
              ] if cell in SHARES else []
    return [f"{prefix}.human_model={model}", *shares, f"{prefix}.robot_visible={str(visible).lower()}"]


def log_to(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    return open(path, "ab")


def train_one(folder: Path, cell: str, seed: int, preset: str) -> int:
    """Train one run to completion on ``cell``'s humans (resuming a killed one); returns the exit code."""
    return train_to_completion(folder, [f"seed={seed}", f"preset={preset}", *TRAIN_BASE, *cell_overrides(cell, "env")],
                               cwd=ROOT)


def test_one(agent: str | None, out: Path, cell: str, scenario: str, episodes: int, acting: Sequence[str] = ()) -> int:
    """``evaluate.py`` of a checkpoint (``agent``; ``None``: the ORCA robot) on ``cell`` (skipped when done), acting
    with the act-time overrides ``acting``."""
    if (out / "eval.json").exists():
        return 0
    who = [f"checkpoint={agent}"] if agent is not None else ["policy=orca"]
    cmd = [sys.executable, str(ROOT / "experiments" / "evaluate.py"), *who, f"env={scenario}",
           f"eval.episodes={episodes}", "eval.record_episode=null", *cell_overrides(cell, "eval"), *acting,
           f"hydra.run.dir={out}"]
    with log_to(out.parent / f"{out.name}.log") as log:
        return subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)


def has_checkpoint(folder: Path) -> bool:
    """A run folder's ``checkpoints/best.pt`` or a pretrained folder's ``best.pt``."""
    return (folder / "checkpoints" / "best.pt").exists() or (folder / "best.pt").exists()


def agents(out: Path, groups: list[str], seeds: list[int]) -> dict[str, dict[str, str | None]]:
    """Per group, ``{label: checkpoint}`` (``None``: the ORCA robot); label names its folder under evals/."""
    table: dict[str, dict[str, str | None]] = {}
    for group in groups:
        if group == "orca-robot":
            table[group] = {"orca-robot": None}
        elif group in PRETRAINED:
            table[group] = {f"{group}-s{s}": str(ROOT / PRETRAINED[group].format(seed=s)) for s in seeds}
        else:
            table[group] = {f"{group}-s{s}": str(out / "runs" / f"{group}-s{s}") for s in seeds}
    return table


def summarise(out: Path, table: dict[str, dict[str, str | None]], cells: list[str]) -> list[dict]:
    rows = []
    for group, members in table.items():
        for cell in cells:
            records = []
            for label in members:
                try:
                    records.append(read_eval_record(out / "evals" / label / cell / "eval.json"))
                except (FileNotFoundError, RecordError):
                    continue
            if not records:
                continue
            row: dict = {"group": group, "cell": cell, "seeds": len(records)}
            for key in ("success_rate", "collision_rate", "timeout_rate", "navigation_time"):
                values = np.array([r[key] for r in records], dtype=float)
                mean, lo, hi = mean_interval({key: values})[key]
                row.update({key: mean, f"{key}_lo": lo, f"{key}_hi": hi,
                            f"{key}_per_seed": [float(v) for v in values]})
            rows.append(row)
    return rows


def write_table(out: Path, rows: list[dict], meta: dict) -> str:
    header = ["agents", "humans (cell)", "seeds", "success", "collision", "timeout", "nav time (s)"]
    body = [[r["group"], r["cell"], r["seeds"], interval_cell(r, "success_rate", 3),
             interval_cell(r, "collision_rate", 3), interval_cell(r, "timeout_rate", 3, interval=False),
             interval_cell(r, "navigation_time", 2, interval=False)] for r in rows]
    text = (f"# Human models: {meta['episodes']} test cases of {meta['scenario']} (test seed 0) per cell\n\n"
            "Mean over seeds [95 % stratified-bootstrap CI, rliable]; the ORCA robot is deterministic (one "
            "evaluation). Cells: the humans' model, `-visible` where they see the robot"
            + "".join(f"; `{c}`: {sf:g} social force, {lin:g} linear, ORCA the rest" for c, (sf, lin) in SHARES.items()
                      if c in meta["cells"]) + ".\n\n"
            + markdown_table(header, body) + "\n")
    atomic_write_bytes(out / "table.md", text.encode())
    atomic_write_json(out / "table.json", {"meta": meta, "rows": rows})
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--cells", nargs="+", default=list(CELLS), choices=list(CELLS))
    ap.add_argument("--train", action="store_true", help="also train SG-D3QN on cells and test it on every cell")
    ap.add_argument("--trained", nargs="+", default=list(TRAINED), choices=list(TRAINED),
                    help="which trained groups --train makes (default all)")
    ap.add_argument("--preset", default="demo", help="the training budget of --train (default demo)")
    ap.add_argument("--scenario", default="circle")
    ap.add_argument("--episodes", type=int, default=1000, help="test cases per cell (default 1000)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs: must be >= 1, got {args.jobs}")
    if args.episodes < 1:
        ap.error(f"--episodes: must be >= 1, got {args.episodes}")
    groups = [*PRETRAINED, "orca-robot", *(args.trained if args.train else [])]
    table = agents(args.out, groups, args.seeds)
    failed: list[str] = []
    if not args.table_only:
        start = time.time()
        with ThreadPoolExecutor(args.jobs) as pool:
            if args.train:  # seed by seed: partial results stay balanced
                order = [(g, s) for s in args.seeds for g in args.trained]
                codes = list(pool.map(lambda gs: train_one(args.out / "runs" / f"{gs[0]}-s{gs[1]}", TRAINED[gs[0]],
                                                           gs[1], args.preset), order))
                failed += [f"train {g}-s{s}" for (g, s), code in zip(order, codes) if code]
            tests = [(label, ckpt, cell, ACTING.get(group, [])) for group, members in table.items()
                     for label, ckpt in members.items() for cell in args.cells if ckpt is None or has_checkpoint(Path(ckpt))]
            codes = list(pool.map(lambda t: test_one(t[1], args.out / "evals" / t[0] / t[2], t[2], args.scenario,
                                                     args.episodes, t[3]), tests))
            failed += [f"test {t[0]} on {t[2]}" for t, code in zip(tests, codes) if code]
        print(f"done in {(time.time() - start) / 60:.0f} min" + (f"; failed: {', '.join(failed)}" if failed else ""))
    meta = {"scenario": args.scenario, "episodes": args.episodes, "test_seed": 0, "seeds": args.seeds,
            "preset": args.preset, "cells": {c: list(CELLS[c]) for c in args.cells},
            "shares": {c: list(SHARES[c]) for c in args.cells if c in SHARES}, "train_base": TRAIN_BASE,
            "pretrained": PRETRAINED, "acting": ACTING}
    print(write_table(args.out, summarise(args.out, table, args.cells), meta))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
