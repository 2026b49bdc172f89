"""Check the ORCA robot baseline against upstream's published values, optionally with upstream's collision check.

    python experiments/orca_upstream.py                      # 1000 cases, circle and square
    python experiments/orca_upstream.py --collision-velocity start   # upstream's collision check
    python experiments/orca_upstream.py --scenarios circle --episodes 200 --json

Evaluates the ORCA robot (``crowdrl.evaluation.evaluate_orca``, the rollout every policy goes
through) on the fixed test cases of each scenario and puts upstream's row (docs/mdp.md, "ORCA
robot baseline") beside each metric, with the standard error of the success rate. For a plain
evaluation of the baseline (one scenario, eval.json and a rendered episode), use
``python experiments/evaluate.py policy=orca``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.evaluation import evaluate_orca
from crowdrl.sim.config import OPEN_SCENARIOS, SCENARIOS, CrowdConfig

# Upstream's ORCA row (docs/mdp.md, "ORCA robot baseline"): return, success, collision, navigation time.
UPSTREAM = {"circle": (0.3315, 0.769, 0.222, 13.880), "square": (0.4417, 0.840, 0.151, 12.856)}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", nargs="+", default=list(OPEN_SCENARIOS), choices=SCENARIOS)
    p.add_argument("--episodes", type=int, default=1000, help="test cases 0..episodes-1 (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="test stream seed (default 0)")
    p.add_argument("--num-humans", type=int, default=10)
    p.add_argument("--batch-size", type=int, default=1000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--collision-velocity", choices=("new", "start"), default="new",
                   help="humans' velocities in the collision check: this step's (default) or, as "
                        "upstream, those from the start of the step")
    add_json_argument(p)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.batch_size < 1 or args.threads < 1:
        p.error("--episodes, --batch-size and --threads must be >= 1")
    return args


def with_upstream(key: str, spec: str) -> Column:
    """A metric with upstream's value in parentheses."""
    return Column(lambda r: f"{format(r[key], spec)} ({format(r['upstream_' + key], spec)})"
                  if r.get("upstream_" + key) is not None else format(r[key], spec), key.replace("_", " "))


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for scenario in args.scenarios:
        cfg = CrowdConfig(scenario=scenario, num_humans=args.num_humans, collision_velocity=args.collision_velocity)
        start = time.perf_counter()
        metrics, _ = evaluate_orca(cfg, seed=args.seed, episodes=args.episodes, batch=args.batch_size)
        m = metrics.as_dict()
        up = UPSTREAM.get(scenario)
        row = {"scenario": scenario, **m, "seconds": time.perf_counter() - start,
               "success_stderr": math.sqrt(max(m["success_rate"] * (1 - m["success_rate"]), 1e-12) / m["episodes"])}
        for key, i in (("average_return", 0), ("success_rate", 1), ("collision_rate", 2), ("navigation_time", 3)):
            row["upstream_" + key] = up[i] if up else None
        rows.append(row)
        log(f"{scenario}: success {m['success_rate']:.3f} in {row['seconds']:.1f} s")
    columns = [Column("scenario"), with_upstream("success_rate", ".3f"), with_upstream("collision_rate", ".3f"),
               Column("timeout_rate", "timeout rate", ".3f"), with_upstream("navigation_time", ".2f"),
               with_upstream("average_return", ".4f"), Column("success_stderr", "±1σ success", ".3f")]
    return emit(rows, columns=columns, as_json=args.json,
                meta={"seed": args.seed, "episodes": args.episodes, "num_humans": args.num_humans,
                      "collision_velocity": args.collision_velocity},
                title=f"ORCA robot baseline, {args.episodes} test cases (seed {args.seed}), collision check with the "
                      f"humans' {args.collision_velocity} velocities; upstream's values in parentheses")


if __name__ == "__main__":
    main(sys.argv[1:])
