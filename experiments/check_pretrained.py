"""Evaluate every pretrained agent again and compare with its recorded ``eval.json``.

Each agent in ``pretrained/`` is tested on the scenarios its ``eval.json`` records (the same test
cases, test seed and episode count), through the same code as ``evaluate.py``; a row says whether
the record came back to every digit and, where not, the largest relative difference of a metric and
how many outcomes differ. Exit status 1 if an outcome rate moved by more than ``--tolerance``.

    python experiments/check_pretrained.py                     # all agents, 12 evaluations of 1000 test cases
    python experiments/check_pretrained.py --agents sgd3qn-planning-re3-demo-s0 --json
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from benchkit import Column, add_json_argument, emit, log

from crowdrl.evaluation.report import read_eval_record, read_eval_records

os.environ.setdefault("WANDB_MODE", "offline")
ROOT = Path(__file__).resolve().parents[1]
PRETRAINED = ROOT / "pretrained"
RATES = ("success_rate", "collision_rate", "timeout_rate")
METRICS = (*RATES, "navigation_time", "average_return", "discomfort_frequency", "min_separation")


def compare(want: dict, got: dict) -> dict:
    """How a fresh evaluation ``got`` differs from the record ``want``."""
    rel = [abs(got[k] - want[k]) / max(abs(want[k]), 1e-12) for k in METRICS
           if want.get(k) is not None and got.get(k) is not None]
    moved = max(abs(got[k] - want[k]) for k in RATES)
    return {"identical": all(got.get(k) == want.get(k) for k in METRICS), "max_rel_diff": max(rel, default=0.0),
            "outcomes_moved": round(moved * want["episodes"]), "max_rate_diff": moved,
            "success_want": want["success_rate"], "success_got": got["success_rate"]}


def check(agent: Path, record: dict, scratch: Path) -> dict:
    """``evaluate.py`` on ``record``'s scenario, test seed and episodes, in a subprocess of its own."""
    out = scratch / f"{agent.name}-{record['scenario']}"
    cmd = [sys.executable, str(ROOT / "experiments" / "evaluate.py"), f"checkpoint={agent}", f"env={record['scenario']}",
           f"eval.seed={record['seed']}", f"eval.episodes={record['episodes']}", "eval.record_episode=null", "threads=1",
           f"hydra.run.dir={out}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    got = read_eval_record(out / "eval.json")
    log(f"  {agent.name} on {record['scenario']}: success {got['success_rate']:.3f}")
    return {"agent": agent.name, "scenario": record["scenario"], "episodes": record["episodes"], **compare(record, got)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agents", nargs="+", help="names under pretrained/ (default: every agent)")
    p.add_argument("--jobs", type=int, default=2, help="evaluations at a time (each a process on one torch thread)")
    p.add_argument("--tolerance", type=float, default=0.003,
                   help="largest change of an outcome rate that passes (0.003: 3 of 1000 episodes)")
    add_json_argument(p)
    args = p.parse_args(argv)
    have = sorted(f.parent.name for f in PRETRAINED.glob("*/eval.json"))
    names = args.agents or have
    unknown = [n for n in names if n not in have]
    if unknown:
        p.error(f"--agents: no pretrained agent {', '.join(map(repr, unknown))}; available: {', '.join(have) or 'none'}")
    if not 0 <= args.tolerance < 1:
        p.error(f"--tolerance: a change of an outcome rate in [0, 1), got {args.tolerance}")
    if args.jobs < 1:
        p.error(f"--jobs: must be >= 1, got {args.jobs}")
    todo = [(PRETRAINED / n, r) for n in names for r in read_eval_records(PRETRAINED / n / "eval.json")]
    log(f"{len(todo)} evaluations of {len(names)} agent(s), {args.jobs} at a time")
    with tempfile.TemporaryDirectory(prefix="crowdrl-check-pretrained-") as scratch, \
            ThreadPoolExecutor(max_workers=args.jobs) as pool:  # threads that wait on one subprocess each
        rows = list(pool.map(lambda job: check(*job, Path(scratch)), todo))
    failed = [r for r in rows if r["max_rate_diff"] > args.tolerance]
    emit(rows, columns=[Column("agent"), Column("scenario"), Column("episodes"),
                        Column("success_want", "success (eval.json)", ".3f"), Column("success_got", "success now", ".3f"),
                        Column("identical", "every digit"), Column("outcomes_moved", "outcomes moved"),
                        Column("max_rel_diff", "max rel. diff of a metric", ".1e")],
         title=f"pretrained agents evaluated again ({len(rows) - len(failed)}/{len(rows)} within "
               f"{args.tolerance} of their outcome rates)",
         meta={"machine": platform.processor() or platform.machine(), "tolerance": args.tolerance},
         as_json=args.json)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
