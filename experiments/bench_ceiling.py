"""The ceiling search's speed: seconds per case on one core, per scenario, and the time 1000 cases would take
(the target: 1000 circle cases in at most 10 minutes at the default settings).

    python experiments/bench_ceiling.py                      # 100 circle cases, default widths
    python experiments/bench_ceiling.py --scenarios circle square doorway --cases 200 --json bench.json

Each row labels cases ``0 .. cases-1`` of the test stream (seed 0) with ``compute_ceiling`` exactly as
``experiments/ceiling.py`` does (replay excluded), one torch thread.
"""

from __future__ import annotations

import argparse
import platform
import time

import torch
from benchkit import Column, add_json_argument, emit, log

from crowdrl.evaluation.ceiling import DEFAULT_CELL, DEFAULT_WIDTHS, compute_ceiling
from crowdrl.sim.config import SCENARIOS, CrowdConfig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", default=["circle"], choices=SCENARIOS)
    p.add_argument("--cases", type=int, default=100, help="test cases per scenario (0 .. cases-1)")
    p.add_argument("--widths", type=int, nargs="+", default=list(DEFAULT_WIDTHS))
    p.add_argument("--num-humans", type=int, default=10)
    add_json_argument(p, path=True)
    a = p.parse_args(argv)
    if a.cases < 1:
        p.error("--cases: must be >= 1")
    torch.set_num_threads(1)
    rows = []
    for scenario in a.scenarios:
        log(f"{scenario}: {a.cases} cases")
        began = time.perf_counter()
        c = compute_ceiling(CrowdConfig(scenario=scenario, num_humans=a.num_humans), cases=a.cases,
                            widths=tuple(a.widths), cell=DEFAULT_CELL)
        seconds = time.perf_counter() - began
        n = c.counts()
        rows.append({"scenario": scenario, "cases": a.cases, "solved": n["solved"], "infeasible": n["infeasible"],
                     "unknown": n["unknown"], "s_per_case": seconds / a.cases, "min_per_1000": seconds / a.cases * 1000 / 60})
    emit(rows, columns=[Column("scenario"), Column("cases"), Column("solved"), Column("infeasible"), Column("unknown"),
                        Column("s_per_case", "s / case", ".3f"), Column("min_per_1000", "min / 1000 cases", ".1f")],
         title=f"Ceiling search, one thread, widths {a.widths}, cell {DEFAULT_CELL} m ({platform.processor() or 'cpu'})",
         meta={"widths": a.widths, "cases": a.cases, "num_humans": a.num_humans, "threads": 1}, as_json=a.json,
         notes=["Target: 1000 circle cases in at most 10 min (docs/ceiling.md)."])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
