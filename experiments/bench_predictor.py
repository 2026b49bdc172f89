"""The planner's crowd-predictor update: eager autograd vs one compiled graph (``PredictorLoss``).

    python experiments/bench_predictor.py            # batch 100, 5 alternating rounds of 30 steps
    python experiments/bench_predictor.py --json

One process, one thread: a learned predictor on 100 real circle transitions (10 humans), each
step = loss and gradients + Adam; the eager and compiled paths alternate round after round (the
machine's load drifts) and the medians are compared. The first compiled call (compilation) is
timed separately.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchkit import Column, add_json_argument, emit, log


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", type=int, default=100)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--steps", type=int, default=30)
    add_json_argument(p)
    args = p.parse_args()
    if min(args.batch, args.rounds, args.steps) < 1:
        p.error("--batch, --rounds and --steps must be >= 1")
    from crowdrl.envs import CrowdNavEnv
    from crowdrl.models.predictor import make_predictor
    from crowdrl.training.predictor_loss import PredictorLoss

    torch.set_num_threads(1)
    torch.manual_seed(0)
    env = CrowdNavEnv("circle", num_envs=args.batch, seed=0)
    td = env.reset()
    td["action"] = torch.zeros(args.batch, dtype=torch.long)
    robot, humans, next_humans = td["robot"], td["humans"], env.step(td)["next", "humans"]
    predictor = make_predictor("learned", env.config.time_step)
    optimizer = torch.optim.Adam(predictor.parameters(), lr=1e-3)
    paths = {"eager": PredictorLoss(predictor), "compiled": PredictorLoss(predictor, compile=True)}
    paths["eager"].loss_and_grad(robot, humans, next_humans)
    start = time.perf_counter()
    paths["compiled"].loss_and_grad(robot, humans, next_humans)
    compile_s = time.perf_counter() - start
    log(f"first compiled call (compilation): {compile_s:.1f} s")
    times: dict[str, list[float]] = {k: [] for k in paths}
    for _ in range(args.rounds):
        for name, loss in paths.items():
            start = time.perf_counter()
            for _ in range(args.steps):
                loss.loss_and_grad(robot, humans, next_humans)
                optimizer.step()
            times[name].append((time.perf_counter() - start) / args.steps * 1e3)
    ms = {k: statistics.median(v) for k, v in times.items()}
    rows = [{"path": name, "ms": ms[name], "speedup_vs_eager": ms["eager"] / ms[name], "runs_ms": times[name]}
            for name in paths]
    columns = [Column("path"), Column("ms", "ms per update", ".2f"), Column("speedup_vs_eager", "speed-up", ".2f"),
               Column(lambda r: ", ".join(f"{x:.2f}" for x in r["runs_ms"]), "runs (ms)")]
    emit(rows, columns=columns, as_json=args.json,
         meta={"batch": args.batch, "threads": 1, "rounds": args.rounds, "steps": args.steps, "compile_s": compile_s},
         title=f"Predictor update (loss + gradients + Adam), batch {args.batch}, 1 thread, median of {args.rounds} rounds",
         notes=[f"First compiled call (compilation): {compile_s:.1f} s"])


if __name__ == "__main__":
    main()
