"""Compare groups of finished runs (seeds) on their recorded test results, with confidence intervals.

A group is ``--group LABEL=RUN[,RUN...]`` (a run folder whose name holds commas, as a Hydra sweep's
``0-a=1,b=2`` does, is found by joining the pieces back together, the longest existing path first)
or, with ``--sweep DIR``, every override set of a ``train.py -m`` sweep folder (its jobs that differ
only in ``seed`` pooled; labelled ``<sweep folder>: <overrides>``; a job that did not complete is
left out, and named). Groups keep their command-line order; the first is the baseline.

A run's test record on a scenario is its ``eval-<scenario>/eval.json`` (what ``reproduce.py`` and
``evaluate.py checkpoint=<run> hydra.run.dir=<run>/eval-<scenario>`` write), else, on the scenario
it trained on, the test ``train.py`` made of it (its top-level ``eval.json``). ``--scenarios``
defaults to every scenario all runs hold a record on. Per scenario and group: the mean over seeds
of success, collision, navigation time and return with a 95 % stratified-bootstrap interval
(rliable), and each group's probability of improving on the first group's success rate. Writes
``table.md`` and ``table.json`` under ``--out``.

``--split val`` compares on the validation episodes the runs logged while training (their
``scalars.jsonl``), never on test cases: what settings are chosen by. Per run: the success,
collision and timeout rates over its last ``--last`` validations (the end of training: a run that
falls back late scores low), its best validation success, how far the last validations sit below
that best (``gap``), the largest drop of a validation below the run's running best among those
after ``--after`` frames (default: the second half of the run), and the frames to its first validation
whose success reaches ``--reach`` (default 0.5; how fast exploration finds the goal, even where the final
rates tie; a run that never reaches it counts as not reached and its group's cell shows how many did).

    python experiments/compare_runs.py --out results/planning \\
        --group "ε-greedy=results/demo/runs/egreedy-s0,results/demo/runs/egreedy-s1,results/demo/runs/egreedy-s2" \\
        --group "ε-greedy + planning=results/planning/runs/plan-s0,results/planning/runs/plan-s1,results/planning/runs/plan-s2"
    python experiments/compare_runs.py --sweep multirun/<A> --sweep multirun/<B> --out results/ab
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from crowdrl.evaluation.stats import mean_interval, probability_of_improvement
from crowdrl.evaluation.report import RecordError, parse_run_group, read_run_test_record, run_test_scenarios
from crowdrl.files import atomic_write_bytes, atomic_write_json, dumps_json
from crowdrl.sim.config import SCENARIOS
from crowdrl.tables import interval_cell, markdown_table

METRICS = (("success_rate", "success", 3), ("collision_rate", "collision", 3), ("navigation_time", "nav time (s)", 2),
           ("average_return", "avg return", 4))
VAL_METRICS = (("success_rate", "success (last val.)", 3), ("collision_rate", "collision (last val.)", 3),
               ("timeout_rate", "timeout (last val.)", 3), ("best_success_rate", "best val. success", 3),
               ("gap_to_best", "best - last val.", 3), ("late_drop", "largest drop", 2),
               ("frames_to_reach", "frames to first val. ≥ reach", 0))
VAL_SCENARIO = "validation"


class Refused(ValueError):
    """Bad input: the message names the argument; nothing is written."""


def val_record(run: Path, last: int, after: int | None = None, reach: float = 0.5) -> dict:
    """A run's validation results: rates over its last ``last`` validations, its best success, the
    best minus the last validations' success (``gap_to_best``), the largest drop below the running
    best among the validations after ``after`` frames (``late_drop``; None: the second half of the run),
    and the frames of its first validation with success ``>= reach`` (``frames_to_reach``; None: never).
    ``episodes``: the episodes of those last validations together; ``val_episodes``: each one's."""
    rows = [json.loads(line) for line in (run / "scalars.jsonl").read_text().splitlines() if line.strip()]
    vals = [r for r in rows if r.get("kind") == "val"]
    if len(vals) < last:
        raise Refused(f"--last: {run} logged {len(vals)} validations, fewer than --last {last}")
    tail = vals[-last:]
    out = {f"{k}": float(np.mean([r[f"val/{k}"] for r in tail])) for k in ("success_rate", "collision_rate",
                                                                           "timeout_rate")}
    success = np.array([r["val/success_rate"] for r in vals])
    frames = np.array([r["frames"] for r in vals])
    out["best_success_rate"] = float(success.max())
    out["gap_to_best"] = out["best_success_rate"] - out["success_rate"]
    late = frames > (frames[-1] / 2 if after is None else after)
    out["late_drop"] = float((np.maximum.accumulate(success) - success)[late].max(initial=0.0))
    reached = np.flatnonzero(success >= reach)
    out["frames_to_reach"] = int(frames[reached[0]]) if reached.size else None
    out["val_episodes"] = [int(r["val/episodes"]) for r in tail]
    out["episodes"] = sum(out["val_episodes"])
    out["frames"] = [tail[0]["frames"], tail[-1]["frames"]]
    return out


def parse_group(text: str) -> tuple[str, list[Path]]:
    """``--group LABEL=RUN[,RUN...]`` (:func:`crowdrl.evaluation.report.parse_run_group`)."""
    try:
        return parse_run_group(text)
    except ValueError as exc:
        raise Refused(f"--group: {exc}") from None


def sweep_groups(folder: Path) -> tuple[list[tuple[str, list[Path]]], list[str]]:
    """``--sweep DIR``: one group per override set of the sweep (seeds pooled), labelled
    ``<folder name>: <overrides>``, of its completed jobs; and the jobs left out (not completed), named."""
    from crowdrl.training.sweep_summary import SweepError, summarize_sweep

    try:
        rows = summarize_sweep(folder)
    except (SweepError, OSError) as exc:
        raise Refused(f"--sweep: {exc}") from None
    groups, left_out = [], []
    for row in rows:
        runs = [folder / j["folder"] for j in row["jobs"] if j["status"] == "completed"]
        left_out += [f"{folder / j['folder']} ({j['status']})" for j in row["jobs"] if j["status"] != "completed"]
        if runs:
            groups.append((f"{folder.name}: {row['label']}", runs))
    if not groups:
        raise Refused(f"--sweep: {folder}: no job of the sweep completed ({'; '.join(left_out)})")
    return groups, left_out


def choose_scenarios(groups: list[tuple[str, list[Path]]], given: list[str] | None) -> list[str]:
    """``--scenarios`` as given, else every scenario all runs hold a test record on (in SCENARIOS order)."""
    if given:
        return given
    common = set(SCENARIOS)
    for _, runs in groups:
        for run in runs:
            common &= set(run_test_scenarios(run))
    if not common:
        raise Refused("--scenarios: the runs hold no test record on a scenario in common "
                      "(eval-<scenario>/eval.json, or train.py's eval.json on its training scenario); name them")
    return [s for s in SCENARIOS if s in common]


def check_records(groups: list[tuple[str, list[Path]]], scenarios: list[str],
                  flags: dict[str, str] | None = None) -> None:
    """Every run holds what the comparison reads (``scalars.jsonl``, or a test record per scenario);
    ``flags``: the argument (``--group``, ``--sweep``) each label came from, for the message."""
    for label, runs in groups:
        flag = (flags or {}).get(label, "--group")
        for run in runs:
            if scenarios == [VAL_SCENARIO]:
                if not (run / "scalars.jsonl").exists():
                    raise Refused(f"{flag} {label!r}: {run} has no scalars.jsonl")
                continue
            for scenario in scenarios:
                try:
                    read_run_test_record(run, scenario)
                except RecordError as exc:
                    raise Refused(f"{flag} {label!r}: {exc}") from None


def compare(groups: list[tuple[str, list[Path]]], scenarios: list[str], reps: int, last: int = 5,
            after: int | None = None, reach: float = 0.5) -> list[dict]:
    rows = []
    metrics = VAL_METRICS if scenarios == [VAL_SCENARIO] else METRICS
    for scenario in scenarios:
        if scenario == VAL_SCENARIO:
            records = {label: [val_record(r, last, after, reach) for r in runs] for label, runs in groups}
        else:
            records = {label: [read_run_test_record(r, scenario) for r in runs] for label, runs in groups}
        first = groups[0][0]
        for label, recs in records.items():
            row: dict[str, Any] = {"group": label, "scenario": scenario, "seeds": len(recs),
                                   "episodes": recs[0]["episodes"], "episodes_per_seed": [r["episodes"] for r in recs]}
            if scenario == VAL_SCENARIO:
                row["val_episodes"] = sorted({n for r in recs for n in r["val_episodes"]})
                row["reach"], row["reached"] = reach, sum(r["frames_to_reach"] is not None for r in recs)
            for key, _, _ in metrics:
                values = np.array([np.nan if r[key] is None else r[key] for r in recs], dtype=np.float64)
                mean, lo, hi = mean_interval({label: values}, reps=reps)[label]
                row.update({key: mean, f"{key}_lo": lo, f"{key}_hi": hi, f"{key}_per_seed": values.tolist()})
            if label != first:
                ours = np.array([r["success_rate"] for r in recs])
                base = np.array([r["success_rate"] for r in records[first]])
                p, plo, phi = probability_of_improvement(ours, base, reps=reps)
                row.update({"p_improve": p, "p_improve_lo": plo, "p_improve_hi": phi})
            rows.append(row)
    return rows


def _val_cell(row: dict, key: str, digits: int) -> str:
    """A metric's cell; the frames to reach a success shows how many seeds reached it when not all did."""
    if key == "frames_to_reach" and row["reached"] < row["seeds"]:
        seen = [int(v) for v in row[f"{key}_per_seed"] if v == v]  # NaN: never reached
        return f"{row['reached']}/{row['seeds']} reached" + (f" ({', '.join(map(str, seen))})" if seen else "")
    return interval_cell(row, key, digits, interval=row["seeds"] > 1)


def _counts(values: set[int]) -> str:
    return "/".join(str(v) for v in sorted(values))


def markdown(rows: list[dict], scenarios: list[str], first: str, reps: int, last: int = 5,
             after: int | None = None, reach: float = 0.5) -> str:
    metrics = VAL_METRICS if scenarios == [VAL_SCENARIO] else METRICS

    lines = [f"Cells: mean over seeds [95 % stratified-bootstrap CI, rliable, {reps} resamples]; "
             f"P(improve): probability that the group's success rate beats {first}'s on a random pair of seeds.", ""]
    if scenarios == [VAL_SCENARIO]:
        per_val = {n for r in rows for n in r.get("val_episodes", [])}
        lines[-1:] = [f"Validation episodes only (the runs' scalars.jsonl): rates over each run's last {last} "
                      f"validations ({last} x {_counts(per_val)} episodes at the end of training), its best validation, "
                      f"the best minus those last validations, the largest drop of a validation below the run's "
                      f"running best after {'half the run' if after is None else f'{after} frames'}, and the frames to "
                      f"its first validation with success ≥ {reach}.", ""]
    for scenario in scenarios:
        mine = [r for r in rows if r["scenario"] == scenario]
        cells = [[r["group"], r["seeds"], *(_val_cell(r, k, d) for k, _, d in metrics),
                  interval_cell(r, "p_improve", 2)] for r in mine]
        lines += [f"## {scenario}", ""]
        if scenario != VAL_SCENARIO:
            cases = {n for r in mine for n in r.get("episodes_per_seed", [r["episodes"]])}
            lines += [f"{_counts(cases)} test cases per run.", ""]
        headers = [h.replace("reach", f"{reach:g}") for _, h, _ in metrics]
        lines += [markdown_table(["group", "seeds", *headers, "P(improve)"], cells), ""]
    return "\n".join(lines)


class _InOrder(argparse.Action):
    """``--group`` and ``--sweep`` append to one list, so groups keep their command-line order."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        namespace.sources = [*(namespace.sources or []), (self.dest, values)]


def build_groups(sources: list[tuple[str, str]]
                 ) -> tuple[list[tuple[str, list[Path]]], dict[str, str], list[str]]:
    """The groups of ``--group`` and ``--sweep`` in order, the argument each label came from, and the
    sweep jobs left out; a label given twice is refused."""
    groups: list[tuple[str, list[Path]]] = []
    flags: dict[str, str] = {}
    left_out: list[str] = []
    for kind, text in sources:
        found, skipped = ([parse_group(text)], []) if kind == "group" else sweep_groups(Path(text))
        for label, runs in found:
            if label in flags:
                raise Refused(f"--{kind}: the label {label!r} names two groups; give each group its own label")
            flags[label] = f"--{kind}"
            groups.append((label, runs))
        left_out += skipped
    if len(groups) < 2:
        raise Refused("--group/--sweep: give at least two groups (the first is the baseline)")
    return groups, flags, left_out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="compare_runs.py", description=__doc__.split("\n\n")[0])
    p.set_defaults(sources=[])
    p.add_argument("--group", action=_InOrder, dest="group", default=argparse.SUPPRESS,
                   help="LABEL=RUN[,RUN...]; the first group given is the baseline")
    p.add_argument("--sweep", action=_InOrder, dest="sweep", default=argparse.SUPPRESS,
                   help="a train.py -m sweep folder: one group per override set, seeds pooled (repeatable)")
    p.add_argument("--scenarios", nargs="+", default=None, choices=list(SCENARIOS),
                   help="default: every scenario all runs hold a test record on")
    p.add_argument("--split", choices=["test", "val"], default="test",
                   help="test: the runs' test records (eval-<scenario>/eval.json, or train.py's eval.json); "
                        "val: the validations logged in training")
    p.add_argument("--last", type=int, default=5, help="--split val: validations at the end of training to average")
    p.add_argument("--after", type=int, default=None,
                   help="--split val: the largest drop counts validations after these frames (default: 2nd half)")
    p.add_argument("--reach", type=float, default=0.5,
                   help="--split val: report the frames to each run's first validation with success >= this (default 0.5)")
    p.add_argument("--reps", type=int, default=2000, help="bootstrap resamples")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--json", action="store_true", help="print the rows as JSON instead of Markdown")
    args = p.parse_args(argv)
    try:
        if args.reps < 100:
            raise Refused("--reps must be >= 100")
        if args.last < 1:
            raise Refused("--last must be >= 1")
        if args.after is not None and args.after < 0:
            raise Refused("--after must be >= 0")
        if not 0.0 < args.reach <= 1.0:
            raise Refused(f"--reach must lie in (0, 1], got {args.reach}")
        if args.out.exists() and not args.out.is_dir():
            raise Refused(f"--out: {args.out} is a file, not a folder")
        groups, flags, left_out = build_groups(args.sources)
        scenarios = [VAL_SCENARIO] if args.split == "val" else choose_scenarios(groups, args.scenarios)
        check_records(groups, scenarios, flags)
        rows = compare(groups, scenarios, args.reps, args.last, args.after, args.reach)
    except (Refused, RecordError) as exc:  # a record read back that crowdrl would not write: file and field named
        p.exit(2, f"{p.prog}: {exc}\n")
    for job in left_out:
        print(f"{p.prog}: left out (not completed): {job}", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"groups": {label: [str(r) for r in runs] for label, runs in groups}, "rows": rows,
              **({"left_out": left_out} if left_out else {})}
    atomic_write_json(args.out / "table.json", result)
    text = markdown(rows, scenarios, groups[0][0], args.reps, args.last, args.after, args.reach)
    atomic_write_bytes(args.out / "table.md", text.encode())
    print(dumps_json(result) if args.json else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
