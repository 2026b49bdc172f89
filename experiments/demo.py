"""The main job on a small default: batched ORCA-baseline rollouts on both scenarios.

Prints the metrics on the test cases, and writes a trajectory PNG and an animated GIF of one
test episode per scenario into a run folder (path printed at the end).

    python experiments/demo.py                  # 1000 test cases per scenario
    python experiments/demo.py --episodes 100 --out runs/demo
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from crowdrl.evaluation import evaluate_policy
from crowdrl.policies import OrcaRobotPolicy
from crowdrl.sim.config import SCENARIOS, CrowdConfig
from crowdrl.viz import animate_trajectory, plot_trajectory

sys.path.insert(0, str(Path(__file__).resolve().parent))
from evaluate_baseline import format_table  # noqa: E402


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--record", type=int, default=0, help="test case to render (default 0)")
    p.add_argument("--out", type=Path, default=None, help="run folder (default runs/demo-<time>)")
    args = p.parse_args(argv)
    if args.episodes < 1 or not 0 <= args.record < args.episodes:
        p.error("--episodes must be >= 1 and --record must lie in 0..episodes-1")
    torch.set_num_threads(1)
    out = args.out or Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for scenario in SCENARIOS:
        cfg = CrowdConfig(scenario=scenario)
        start = time.perf_counter()
        metrics, traj = evaluate_policy(cfg, OrcaRobotPolicy(), split="test", seed=args.seed,
                                        num_episodes=args.episodes, record_episode=args.record)
        results[scenario] = metrics.as_dict()
        print(f"[{scenario}] {metrics.summary()}  ({time.perf_counter() - start:.1f} s)", flush=True)
        plot_trajectory(traj, out / f"orca_{scenario}_case{args.record}.png",
                        title=f"ORCA baseline, {scenario} test case {args.record}")
        animate_trajectory(traj, out / f"orca_{scenario}_case{args.record}.gif")
    print()
    print(format_table(results, args.episodes, args.seed))
    print(f"\nwrote trajectory PNGs and GIFs to {out.resolve()}")
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
