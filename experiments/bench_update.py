"""D3QN update speed against a baseline checkout, measured in one run.

    git worktree add /tmp/crowdrl-6dfef2c 6dfef2c
    python experiments/bench_update.py --baseline /tmp/crowdrl-6dfef2c          # table
    python experiments/bench_update.py --baseline /tmp/crowdrl-6dfef2c --json

One update of the SG-D3QN network at batch 100 (sample, three forward passes, one backward,
Adam), ε-greedy, one thread: the baseline checkout's ``experiments/bench_train.py`` (its own
``src`` first on the path) and this checkout's, each in its own subprocess, alternating
``--rounds`` times so that a slow spell of the machine hits both alike. The table gives each
one's median update time, its breakdown (from the median run) and the baseline's median divided
by it (the speed-up), with the projection of the paper's budget (500k frames + 500k updates at
that collection rate).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from bench_collect import ROOT, bench_train_rows  # noqa: E402
from benchkit import Column, add_json_argument, emit, log  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", type=Path, help="a checkout (e.g. a git worktree of 6dfef2c) to compare against")
    p.add_argument("--updates", type=int, default=500, help="timed updates per run (default 500)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--loss", nargs="+", default=["compiled", "eager"], choices=["compiled", "eager"],
                   help="this checkout's update: one compiled graph and/or eager")
    add_json_argument(p)
    args = p.parse_args(argv)
    if min(args.updates, args.rounds) < 1:
        p.error("--updates and --rounds must be >= 1")
    if args.baseline is not None and not (args.baseline / "experiments" / "bench_train.py").is_file():
        p.error(f"--baseline {args.baseline} has no experiments/bench_train.py")
    common = ["--num-envs", "16", "--batches", "2", "--updates", str(args.updates), "--warmup-frames", "2000"]
    configs = ([("baseline (compiled loss)", args.baseline, "compiled")] if args.baseline else []) + \
              [(f"this checkout, {b}", ROOT, b) for b in args.loss]
    runs: dict[str, list[dict]] = {name: [] for name, _, _ in configs}
    for _ in range(args.rounds):
        for name, checkout, loss in configs:
            result = bench_train_rows(checkout, [*common, "--loss", loss])[0]
            runs[name].append(result)
            log(f"{name}: {result['update_ms']:.2f} ms")
    base = statistics.median(r["update_ms"] for r in runs[configs[0][0]]) if args.baseline else None
    rows = []
    for name, results in runs.items():
        times = [r["update_ms"] for r in results]
        median_run = sorted(results, key=lambda r: r["update_ms"])[len(results) // 2]
        rows.append({"config": name, "update_ms": statistics.median(times), "runs_ms": times,
                     "breakdown_ms": median_run["update_breakdown_ms"],
                     "speedup_vs_baseline": base / statistics.median(times) if base else None,
                     "paper_budget_hours": median_run["paper_budget_hours"]})
    meta = {"threads": 1, "batch_size": 100, "baseline": str(args.baseline) if args.baseline else None,
            "rounds": args.rounds, "updates": args.updates}
    columns = [Column("config"), Column("update_ms", "update ms", ".2f"),
               Column("speedup_vs_baseline", "speed-up", lambda v: f"{v:.2f}×"),
               Column("paper_budget_hours", "paper budget h", ".2f"),
               Column(lambda r: ", ".join(f"{k} {v:.2f}" for k, v in r["breakdown_ms"].items()), "breakdown (ms)")]
    return emit(rows, columns=columns, as_json=args.json, meta=meta,
                title=f"D3QN update of SG-D3QN at batch 100, 1 thread, median of {args.rounds} alternating runs")


if __name__ == "__main__":
    main(sys.argv[1:])
