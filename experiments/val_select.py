"""Which of a run's kept networks is best on more validation cases, scenario by scenario?

    python experiments/val_select.py results/mix-episodes2x/runs/egreedy-s{0,1} --episodes 200
    python experiments/val_select.py RUN --networks best last val-000300000 --scenarios corridor doorway --json out.json

A run keeps the network of its best validation (``checkpoints/best.pt``), its last one (``last.pt``) and,
with ``train.keep_val_checkpoints``, one per validation (``val-*.pt``). A scenario mix validates on its
``train.val_episodes`` cases spread over its scenarios (100 cases: 12-25 each), so its best network is
chosen on few cases per scenario. This script plays each named network on cases ``0 .. episodes-1`` of
each scenario's **validation** stream (``split=val``, the run's seed: the stream training validated on,
never test cases), through the training env maker and the run's own actor (its planner included),
under the deterministic exploration type, and prints each network's success per scenario, their mean
(each scenario weighted equally) and the mean weighted as ``env.mix`` weights them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from benchkit import Column, add_json_argument, emit, log
from diagnose_timeouts import load


def validation_success(run, net, predictor, scenario: str, first: int, episodes: int, batch: int) -> dict[str, float]:
    """Success, collision and timeout rates of ``net`` acting as trained on ``scenario``'s validation cases
    ``first .. first + episodes - 1``."""
    from crowdrl.evaluation import evaluate
    from crowdrl.training.factories import make_actor, make_env

    env = make_env(run, split="val", num_envs=min(batch, episodes), seed=run.seed, scenario=scenario)
    actor = make_actor(run, env, net, predictor)
    with torch.no_grad():
        metrics, _ = evaluate(env, actor, num_episodes=episodes, first_episode=first)
    return {"success": metrics.success_rate, "collision": metrics.collision_rate, "timeout": metrics.timeout_rate}


def network_path(run_dir: Path, network: str) -> Path | None:
    """``run_dir/checkpoints/<network>.pt``, else ``run_dir/<network>.pt`` (a pretrained agent's folder); ``None``: neither."""
    for path in (run_dir / "checkpoints" / f"{network}.pt", run_dir / f"{network}.pt"):
        if path.is_file():
            return path
    return None


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", type=Path, nargs="+", help="run folders (or folders holding <network>.pt, as a pretrained agent's)")
    p.add_argument("--networks", nargs="+", default=["best", "last"],
                   help="checkpoints/<name>.pt of each run, or <name>.pt beside it (default: best last)")
    p.add_argument("--scenarios", nargs="+", default=None, help="default: the scenarios each run trained on")
    p.add_argument("--episodes", type=int, default=200, help="validation cases 0..episodes-1 per scenario (default 200)")
    p.add_argument("--first", type=int, default=0, help="the first validation case (default 0)")
    p.add_argument("--batch", type=int, default=200, help="episodes stepped at once (results do not depend on it)")
    p.add_argument("--threads", type=int, default=1)
    add_json_argument(p, path=True)
    args = p.parse_args(argv)
    for name, low in (("episodes", 1), ("batch", 1), ("threads", 1), ("first", 0)):
        if getattr(args, name) < low:
            p.error(f"--{name}: must be >= {low}, got {getattr(args, name)}")
    from crowdrl.sim.config import SCENARIOS
    from crowdrl.training.checkpoint import CheckpointError
    from crowdrl.training.config import trained_scenarios

    if args.scenarios is not None and (unknown := sorted(set(args.scenarios) - set(SCENARIOS))):
        p.error(f"--scenarios: unknown {', '.join(unknown)}; allowed: {', '.join(SCENARIOS)}")
    for run_dir in args.runs:
        for network in args.networks:
            if network_path(run_dir, network) is None:
                p.error(f"--networks: neither {run_dir}/checkpoints/{network}.pt nor {run_dir}/{network}.pt exists")
    torch.set_num_threads(args.threads)
    rows, scenarios_seen = [], []
    for run_dir in args.runs:
        for network in args.networks:
            path = network_path(run_dir, network)
            try:
                run, net, predictor = load(path)
            except CheckpointError as exc:
                p.error(f"{path}: {exc}")
            scenarios = args.scenarios or trained_scenarios(run)
            weights = {s: float(run.env.mix[s]) if run.env.mix else 1.0 for s in scenarios}
            row: dict = {"run": str(run_dir), "network": network, "seed": run.seed, "first": args.first,
                         "episodes": args.episodes}
            for scenario in scenarios:
                row[scenario] = validation_success(run, net, predictor, scenario, args.first, args.episodes, args.batch)
                log(f"{path} {scenario}: success {row[scenario]['success']:.3f}")
                if scenario not in scenarios_seen:
                    scenarios_seen.append(scenario)
            row["mean"] = sum(row[s]["success"] for s in scenarios) / len(scenarios)
            row["mix_weighted"] = sum(weights[s] * row[s]["success"] for s in scenarios) / sum(weights.values())
            rows.append(row)
    emit(rows, columns=[Column("run"), Column("network"),
                        *[Column(lambda r, s=s: r[s]["success"] if s in r else None, s, ".3f") for s in scenarios_seen],
                        Column("mean", "mean (equal)", ".3f"), Column("mix_weighted", "mean (env.mix weights)", ".3f")],
         title=f"validation success, cases {args.first}..{args.first + args.episodes - 1} of each scenario's val stream "
               "(each run's seed)",
         meta={"first": args.first, "episodes": args.episodes, "networks": args.networks, "scenarios": scenarios_seen},
         as_json=args.json)
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
