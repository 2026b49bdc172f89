"""Generalisation over crowd sizes: trained checkpoints (and ORCA) tested at several crowd sizes.

Each group is a label and one or more run folders (seeds) trained the same way; every run's best
checkpoint is tested on the same ``--episodes`` circle (or square) test cases at each size of
``--sizes`` (``evaluate.py eval.num_humans=<size>``), ORCA beside them. Writes ``table.md``,
``table.json`` and one ``cells/*.json`` per (run, size) under ``--out``; a rerun reuses the cells.

    python experiments/crowd_sizes.py --out results/crowd_sizes --sizes 5 10 15 20 \\
        --group "10 humans=results/demo/runs/egreedy-s0,results/demo/runs/egreedy-s1,results/demo/runs/egreedy-s2" \\
        --group "5-20 humans=results/crowd_range/runs/range-s0"
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from crowdrl.evaluation.report import parse_run_group
from crowdrl.files import atomic_write_bytes, atomic_write_json, dumps_json
from crowdrl.agents import evaluate_spec
from crowdrl.tables import markdown_table

METRICS = ("success_rate", "collision_rate", "timeout_rate", "navigation_time", "average_return")


def parse_group(text: str) -> tuple[str, list[str]]:
    """``--group LABEL=RUN[,RUN...]`` (run folders, one per seed)."""
    try:
        label, runs = parse_run_group(text)
    except ValueError as exc:
        raise SystemExit(f"--group: {exc}") from None
    return label, [str(run) for run in runs]


def cell(out: Path, what: str, scenario: str, size: int, episodes: int, seed: int) -> dict:
    """One evaluation (cached under ``out/cells``): ``what`` is a run folder or ``orca``."""
    name = hashlib.sha256(json.dumps([str(Path(what).resolve()) if what != "orca" else what, scenario, size,
                                      episodes, seed]).encode()).hexdigest()[:16]
    path = out / "cells" / f"{name}.json"
    if path.exists():
        return json.loads(path.read_text())
    tick = time.perf_counter()
    if what == "orca":
        record, _ = evaluate_spec(policy="orca", scenario=scenario, seed=seed, episodes=episodes, num_humans=size)
    else:
        record, _ = evaluate_spec(checkpoint=what, scenario=scenario, seed=seed, episodes=episodes, num_humans=size)
    record = {**record, "source": what, "num_humans": size, "wall_s": time.perf_counter() - tick}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, record)
    return record


def summarise(records: list[dict]) -> dict:
    """Mean, min and max over seeds of each metric (nav time over the seeds that have one)."""
    out = {"seeds": len(records)}
    for key in METRICS:
        values = [r[key] for r in records if r.get(key) is not None and r[key] == r[key]]
        out[key] = ({"mean": statistics.fmean(values), "min": min(values), "max": max(values)} if values else None)
    return out


def markdown(table: dict, sizes: list[int], scenario: str, episodes: int, seed: int) -> str:
    def fmt(s: dict | None, digits: int) -> str:
        if s is None:
            return "–"
        if s["min"] == s["max"]:
            return f"{s['mean']:.{digits}f}"
        return f"{s['mean']:.{digits}f} [{s['min']:.{digits}f}, {s['max']:.{digits}f}]"

    lines = [f"# Crowd-size generalisation on {scenario} ({episodes} test cases of test seed {seed} per size)", "",
             "Cells: mean over seeds [min, max over seeds]; ORCA is deterministic (one evaluation).", ""]
    for metric, digits in (("success_rate", 3), ("collision_rate", 3), ("navigation_time", 2), ("average_return", 4)):
        rows = [[label, by_size[str(sizes[0])]["seeds"], *(fmt(by_size[str(n)][metric], digits) for n in sizes)]
                for label, by_size in table.items()]
        lines += [f"## {metric.replace('_', ' ')}", "",
                  markdown_table(["policy", "seeds", *(f"{n} humans" for n in sizes)], rows), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--group", action="append", required=True, help="LABEL=RUN[,RUN...] (run folders, one per seed)")
    p.add_argument("--sizes", type=int, nargs="+", default=[5, 10, 15, 20])
    p.add_argument("--scenario", default="circle", choices=["circle", "square"])
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0, help="test stream seed")
    p.add_argument("--no-orca", action="store_true", help="leave out the ORCA rows")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--json", action="store_true", help="print the table as JSON instead of Markdown")
    args = p.parse_args(argv)
    if any(n < 1 for n in args.sizes) or args.episodes < 1:
        raise SystemExit("--sizes and --episodes must be >= 1")
    torch.set_num_threads(1)
    groups = [parse_group(g) for g in args.group]
    if not args.no_orca:
        groups.append(("ORCA", ["orca"]))
    table: dict[str, dict[str, dict]] = {}
    for label, runs in groups:
        table[label] = {}
        for n in args.sizes:
            records = [cell(args.out, run, args.scenario, n, args.episodes, args.seed) for run in runs]
            table[label][str(n)] = summarise(records)
            print(f"{label:>20} N={n:<3} success " + " ".join(f"{r['success_rate']:.3f}" for r in records),
                  file=sys.stderr, flush=True)
    result = {"scenario": args.scenario, "episodes": args.episodes, "seed": args.seed, "sizes": args.sizes,
              "groups": {label: runs for label, runs in groups}, "table": table}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / "table.json", result)
    text = markdown(table, args.sizes, args.scenario, args.episodes, args.seed)
    atomic_write_bytes(args.out / "table.md", text.encode())
    print(dumps_json(result) if args.json else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
