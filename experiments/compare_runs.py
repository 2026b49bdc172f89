"""Compare groups of finished runs (seeds) on their recorded test results, with confidence intervals.

Each group is a label and run folders that hold ``eval-<scenario>/eval.json`` (what
``reproduce.py`` and ``evaluate.py checkpoint=<run> hydra.run.dir=<run>/eval-<scenario>`` write).
Per scenario and group: the mean over seeds of success, collision, navigation time and return
with a 95 % stratified-bootstrap interval (rliable), and each group's probability of improving on
the first group's success rate. Writes ``table.md`` and ``table.json`` under ``--out``.

``--split val`` compares on the validation episodes the runs logged while training (their
``scalars.jsonl``), never on test cases: what settings are chosen by. Per run: the success,
collision and timeout rates over its last ``--last`` validations (the end of training, 100 episodes
each: a run that falls back late scores low), its best validation success, how far the last
validations sit below that best (``gap``), and the largest drop of a validation below the run's
running best among those after ``--after`` frames (default: the second half of the run).

    python experiments/compare_runs.py --out results/planning \\
        --group "ε-greedy=results/demo/runs/egreedy-s0,results/demo/runs/egreedy-s1,results/demo/runs/egreedy-s2" \\
        --group "ε-greedy + planning=results/planning/runs/plan-s0,results/planning/runs/plan-s1,results/planning/runs/plan-s2"
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from crowdrl.evaluation.stats import mean_interval, probability_of_improvement
from crowdrl.evaluation.report import RecordError, parse_run_group, read_eval_record
from crowdrl.files import atomic_write_bytes, atomic_write_json, dumps_json
from crowdrl.sim.config import SCENARIOS
from crowdrl.tables import interval_cell, markdown_table

METRICS = (("success_rate", "success", 3), ("collision_rate", "collision", 3), ("navigation_time", "nav time (s)", 2),
           ("average_return", "avg return", 4))
VAL_METRICS = (("success_rate", "success (last val.)", 3), ("collision_rate", "collision (last val.)", 3),
               ("timeout_rate", "timeout (last val.)", 3), ("best_success_rate", "best val. success", 3),
               ("gap_to_best", "best - last val.", 3), ("late_drop", "largest drop", 2))
VAL_SCENARIO = "validation"


def val_record(run: Path, last: int, after: int | None = None) -> dict:
    """A run's validation results: rates over its last ``last`` validations, its best success, the
    best minus the last validations' success (``gap_to_best``), and the largest drop below the running
    best among the validations after ``after`` frames (``late_drop``; None: the second half of the run)."""
    rows = [json.loads(line) for line in (run / "scalars.jsonl").read_text().splitlines() if line.strip()]
    vals = [r for r in rows if r.get("kind") == "val"]
    if len(vals) < last:
        raise SystemExit(f"--split val: {run} logged {len(vals)} validations, fewer than --last {last}")
    tail = vals[-last:]
    out = {f"{k}": float(np.mean([r[f"val/{k}"] for r in tail])) for k in ("success_rate", "collision_rate",
                                                                           "timeout_rate")}
    success = np.array([r["val/success_rate"] for r in vals])
    frames = np.array([r["frames"] for r in vals])
    out["best_success_rate"] = float(success.max())
    out["gap_to_best"] = out["best_success_rate"] - out["success_rate"]
    late = frames > (frames[-1] / 2 if after is None else after)
    out["late_drop"] = float((np.maximum.accumulate(success) - success)[late].max(initial=0.0))
    out["episodes"] = int(sum(r["val/episodes"] for r in tail))
    out["frames"] = [tail[0]["frames"], tail[-1]["frames"]]
    return out


def parse_group(text: str, scenarios: list[str]) -> tuple[str, list[Path]]:
    """``--group LABEL=RUN[,RUN...]``: every run must hold its test result on each scenario."""
    try:
        label, runs = parse_run_group(text)
    except ValueError as exc:
        raise SystemExit(f"--group: {exc}") from None
    for run in runs:
        if scenarios == [VAL_SCENARIO]:
            if not (run / "scalars.jsonl").exists():
                raise SystemExit(f"--group {label!r}: {run} has no scalars.jsonl")
            continue
        for scenario in scenarios:
            if not (run / f"eval-{scenario}" / "eval.json").exists():
                raise SystemExit(f"--group {label!r}: {run} has no eval-{scenario}/eval.json")
    return label, runs


def compare(groups: list[tuple[str, list[Path]]], scenarios: list[str], reps: int, last: int = 5,
            after: int | None = None) -> list[dict]:
    rows = []
    metrics = VAL_METRICS if scenarios == [VAL_SCENARIO] else METRICS
    for scenario in scenarios:
        if scenario == VAL_SCENARIO:
            records = {label: [val_record(r, last, after) for r in runs] for label, runs in groups}
        else:
            records = {label: [read_eval_record(r / f"eval-{scenario}" / "eval.json") for r in runs]
                       for label, runs in groups}
        first = groups[0][0]
        for label, recs in records.items():
            row = {"group": label, "scenario": scenario, "seeds": len(recs), "episodes": recs[0]["episodes"]}
            for key, _, _ in metrics:
                values = np.array([r[key] for r in recs], dtype=np.float64)
                mean, lo, hi = mean_interval({label: values}, reps=reps)[label]
                row.update({key: mean, f"{key}_lo": lo, f"{key}_hi": hi, f"{key}_per_seed": values.tolist()})
            if label != first:
                ours = np.array([r["success_rate"] for r in recs])
                base = np.array([r["success_rate"] for r in records[first]])
                p, plo, phi = probability_of_improvement(ours, base, reps=reps)
                row.update({"p_improve": p, "p_improve_lo": plo, "p_improve_hi": phi})
            rows.append(row)
    return rows


def markdown(rows: list[dict], scenarios: list[str], first: str, reps: int, last: int = 5,
             after: int | None = None) -> str:
    metrics = VAL_METRICS if scenarios == [VAL_SCENARIO] else METRICS

    lines = [f"Cells: mean over seeds [95 % stratified-bootstrap CI, rliable, {reps} resamples]; "
             f"P(improve): probability that the group's success rate beats {first}'s on a random pair of seeds.", ""]
    if scenarios == [VAL_SCENARIO]:
        lines[-1:] = [f"Validation episodes only (the runs' scalars.jsonl): rates over each run's last {last} "
                      f"validations ({last} x 100 episodes at the end of training), its best validation, the best minus "
                      f"those last validations, and the largest drop of a validation below the run's running best "
                      f"after {'half the run' if after is None else f'{after} frames'}.", ""]
    for scenario in scenarios:
        cells = [[r["group"], r["seeds"], *(interval_cell(r, k, d, interval=r["seeds"] > 1) for k, _, d in metrics),
                  interval_cell(r, "p_improve", 2)]
                 for r in rows if r["scenario"] == scenario]
        lines += [f"## {scenario}", "",
                  markdown_table(["group", "seeds", *(h for _, h, _ in metrics), "P(improve)"], cells), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--group", action="append", required=True, help="LABEL=RUN[,RUN...]; the first is the baseline")
    p.add_argument("--scenarios", nargs="+", default=["circle", "square"], choices=list(SCENARIOS))
    p.add_argument("--split", choices=["test", "val"], default="test",
                   help="test: the eval-<scenario>/eval.json records; val: the validations logged in training")
    p.add_argument("--last", type=int, default=5, help="--split val: validations at the end of training to average")
    p.add_argument("--after", type=int, default=None,
                   help="--split val: the largest drop counts validations after these frames (default: 2nd half)")
    p.add_argument("--reps", type=int, default=2000, help="bootstrap resamples")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--json", action="store_true", help="print the rows as JSON instead of Markdown")
    args = p.parse_args(argv)
    if len(args.group) < 2:
        raise SystemExit("--group: give at least two groups (the first is the baseline)")
    if args.reps < 100:
        raise SystemExit("--reps must be >= 100")
    if args.last < 1:
        raise SystemExit("--last must be >= 1")
    if args.after is not None and args.after < 0:
        raise SystemExit("--after must be >= 0")
    scenarios = [VAL_SCENARIO] if args.split == "val" else args.scenarios
    groups = [parse_group(g, scenarios) for g in args.group]
    try:
        rows = compare(groups, scenarios, args.reps, args.last, args.after)
    except RecordError as exc:  # a record read back that crowdrl would not write: file and field named
        p.exit(2, f"{p.prog}: {exc}\n")
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"groups": {label: [str(r) for r in runs] for label, runs in groups}, "rows": rows}
    atomic_write_json(args.out / "table.json", result)
    text = markdown(rows, scenarios, groups[0][0], args.reps, args.last, args.after)
    atomic_write_bytes(args.out / "table.md", text.encode())
    print(dumps_json(result) if args.json else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
