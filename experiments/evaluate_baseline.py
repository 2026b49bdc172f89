"""Evaluate the ORCA robot baseline on the fixed test cases of each scenario.

    python experiments/evaluate_baseline.py                      # 1000 cases, circle and square
    python experiments/evaluate_baseline.py --scenarios circle --episodes 200 --json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import torch

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
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    args = p.parse_args(argv)
    if args.episodes < 1 or args.batch_size < 1 or args.threads < 1:
        p.error("--episodes, --batch-size and --threads must be >= 1")
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    results = {}
    for scenario in args.scenarios:
        cfg = CrowdConfig(scenario=scenario, num_humans=args.num_humans, collision_velocity=args.collision_velocity)
        start = time.perf_counter()
        metrics, _ = evaluate_orca(cfg, seed=args.seed, episodes=args.episodes, batch=args.batch_size)
        results[scenario] = {**metrics.as_dict(), "seconds": time.perf_counter() - start}
    if args.json:
        print(json.dumps({"seed": args.seed, "episodes": args.episodes, "results": results}, indent=1))
    else:
        print(format_table(results, args.episodes, args.seed))
    return results


def format_table(results: dict, episodes: int, seed: int) -> str:
    lines = [f"ORCA robot baseline, {episodes} test cases (seed {seed}); upstream in brackets",
             f"{'scenario':<8} {'success':>15} {'collision':>15} {'timeout':>8} {'nav time (s)':>17} "
             f"{'avg return':>17} {'±1σ success':>11}"]
    for scenario, m in results.items():
        up = UPSTREAM.get(scenario, (math.nan,) * 4)
        sigma = math.sqrt(max(m["success_rate"] * (1 - m["success_rate"]), 1e-12) / m["episodes"])
        lines.append(
            f"{scenario:<8} {m['success_rate']:>7.3f} ({up[1]:.3f}) {m['collision_rate']:>7.3f} ({up[2]:.3f}) "
            f"{m['timeout_rate']:>8.3f} {m['navigation_time']:>8.2f} ({up[3]:.2f}) "
            f"{m['average_return']:>8.4f} ({up[0]:.4f}) {sigma:>11.3f}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main(sys.argv[1:])
