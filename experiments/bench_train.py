"""Training throughput on this machine: collection frames/s and D3QN updates/s, with a breakdown.

    python experiments/bench_train.py                            # SG-D3QN, ε-greedy, batch 100, 16 envs
    python experiments/bench_train.py --threads 2 --json
    python experiments/bench_train.py --explorations egreedy noisy dropout icm re3   # overhead ratios
    python experiments/bench_train.py --loss eager compiled      # what compiling the update buys
    python experiments/bench_train.py --encoders sgd3qn sarl lstm_rl mp_rgl   # per-update cost of each encoder
    python experiments/bench_train.py --planning --counterfactual-k 0 5 81   # counterfactual experience's cost
    python experiments/bench_train.py --counterfactual-k 0 5 --counterfactual-modes second_update merged
    python experiments/bench_train.py --scenario corridor --lidar off mlp conv   # what reading the scan costs

One row per (encoder, exploration, loss); ``--json`` prints ``{"meta": ..., "rows": [...]}`` (the
shared format of ``benchkit.py``).

Measures, in one process: collecting frames with the acting policy through the TorchRL
collector (env + policy), sampling a batch of 100 from the replay buffer (for ICM/RE3 this
includes the sample-time intrinsic reward and ICM's own training step), the double-DQN loss
and its gradients (``D3QNLoss.loss_and_grad``: three forward passes and one backward), and the
optimiser step, the last two through the trainer's own learner (``D3QNLearner.step``). Projects the paper's budget (500k frames,
500k updates of batch 100) from the measured rates. With several explorations, each variant's
update cost is also given relative to the first one, all measured in the same process; the
same for ``--loss eager compiled`` (the update runs eagerly or as one ``torch.compile`` graph,
``train.compile_loss``; compilation happens in the untimed warm-up).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import time

import torch

from benchkit import Column, add_json_argument, emit

BUDGET_FRAMES = BUDGET_UPDATES = 500_000


def matmul_mflop_per_update(loss, sample) -> float:
    """Matmul MFLOP of the D3QN loss's forward + backward on ``sample`` (``torch.utils.flop_counter``;
    the optimiser is not a matmul and elementwise ops are not counted): the work an update's time buys.

    Run after all timing: with torch 2.13, torch calls in a process ran markedly slower after a
    ``FlopCounterMode`` had been used, so counting first would skew the times.
    """
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        loss(sample)["loss"].backward()
    return counter.get_total_flops() / 1e6


def counterfactual_of(k: int, mode: str = "second_update") -> dict:
    """``train.counterfactual`` for ``--counterfactual-k``: 0 off, 81 every action, else the top k by Q;
    ``mode``: a second update after the real one (SG-D3QN's arrangement) or one ``merged`` update."""
    if k == 0:
        return {"mode": "off"}
    return {"mode": mode, **({"actions": "all"} if k == 81 else {"actions": "topk", "k": k})}


def measure(encoder: str, exploration: str, loss_backend: str, args: argparse.Namespace,
            counterfactual_k: int = 0, counterfactual_mode: str = "second_update", lidar: str = "off") -> tuple[dict, tuple]:
    """Collection rate and per-update breakdown (ms) for one exploration variant, and the
    (loss, sample) to count its matmul work with once every variant is timed."""
    from torchrl.collectors import Collector

    from crowdrl.training.validation import validate
    from crowdrl.training.trainer import Trainer

    torch.manual_seed(0)
    # every row's env scans when one row's network reads the scan: the rows differ by the network alone
    rays = args.lidar_rays if any(kind != "off" for kind in args.lidar) else 0
    run = validate({"logger": {"name": "csv"}, "encoder": {"name": encoder, "lidar": lidar},
                    "exploration": {"name": exploration}, "threads": args.threads,
                    "env": {"orca_backend": args.orca_backend, "scenario": args.scenario, "lidar_rays": rays},
                    "train": {"num_envs": args.num_envs, "steps_per_batch": 8,
                                                      "compile_loss": loss_backend == "compiled",
                                                      "compile_acting": args.acting == "compiled",
                              "counterfactual": counterfactual_of(counterfactual_k, counterfactual_mode)},
                    "planning": {"enabled": args.planning}})
    tr = Trainer(run, "/tmp/crowdrl-bench-train")
    torch.set_num_threads(args.threads)
    collector = Collector(tr.env, tr.policy, frames_per_batch=args.num_envs * 8, total_frames=-1,
                          auto_register_policy_transforms=False)
    frames = 0
    it = iter(collector)
    while frames < args.warmup_frames:  # fill the buffer, warm up
        batch = next(it)
        tr.buffer.extend(batch.select(*tr.stored_keys))
        frames += batch.numel()
    start = time.perf_counter()
    collected = 0
    for _ in range(args.batches):
        collected += next(it).numel()
    collect_s = time.perf_counter() - start
    collector.shutdown()

    # the trainer's own update (its learner's D3QNLearner.step), timed in two parts: sampling, then the rest
    # "loss_and_grad": to the Q network's first optimiser step (the auxiliary learners' steps, ICM's or the crowd
    # predictor's, are in it); "optimizer": from that step to the end of the update (with counterfactual experience
    # the second batch's building, loss and step are in it too)
    parts: dict[str, list[float]] = {"sample": [], "loss_and_grad": [], "optimizer": []}
    step = tr.learner.optimizer.step

    def timed_step(*a, **k):
        t = time.perf_counter()
        out = step(*a, **k)
        marks.append(t)
        return out

    tr.learner.optimizer.step = timed_step
    for i in range(args.updates + 20):
        marks: list[float] = []
        t0 = time.perf_counter()
        sample = tr.buffer.sample()
        t1 = time.perf_counter()
        tr.learner.step(sample, i + 1)  # learners' steps, (noise reset), loss and gradients, optimiser step, target update
        t3 = time.perf_counter()
        if i >= 20:
            for key, value in zip(parts, (t1 - t0, marks[0] - t1, t3 - marks[0])):
                parts[key].append(value)
    tr.learner.optimizer.step = step
    tr.close()
    flop_probe = (tr.learner.loss, tr.buffer.sample())
    ms = {k: 1e3 * statistics.mean(v) for k, v in parts.items()}
    update_ms = sum(ms.values())
    frames_per_s = collected / collect_s
    collect_h = BUDGET_FRAMES / frames_per_s / 3600
    hours = collect_h + BUDGET_UPDATES * update_ms / 1e3 / 3600
    # what one update may cost for collection + updates to fit in one hour at this collection rate
    update_ms_for_1h = max(0.0, 1.0 - collect_h) * 3600 * 1e3 / BUDGET_UPDATES
    return {"encoder": encoder, "exploration": exploration, "loss": loss_backend, "lidar": lidar,
            "counterfactual_k": counterfactual_k,
            "counterfactual_mode": counterfactual_mode if counterfactual_k else "off",
            "collect_frames_per_s": frames_per_s,
            "update_ms": update_ms,
            "update_breakdown_ms": ms, "updates_per_s": 1e3 / update_ms, "paper_budget_hours": hours,
            "update_ms_for_1h_budget": update_ms_for_1h}, flop_probe


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--num-envs", type=int, default=16)
    p.add_argument("--updates", type=int, default=300, help="timed updates (default 300)")
    p.add_argument("--batches", type=int, default=20, help="timed collector batches (default 20)")
    p.add_argument("--warmup-frames", type=int, default=5000, help="frames collected before timing (default 5000)")
    p.add_argument("--encoders", "--encoder", nargs="+", default=["sgd3qn"],
                   help="encoders to measure (each with every exploration and loss backend)")
    p.add_argument("--explorations", nargs="+", default=["egreedy"],
                   choices=["egreedy", "noisy", "dropout", "icm", "re3"])
    p.add_argument("--loss", nargs="+", default=["compiled"], choices=["compiled", "eager"],
                   help="run the loss's Q networks compiled (default) and/or eagerly")
    p.add_argument("--orca-backend", default="eager", choices=["eager", "compiled"],
                   help="the simulator's ORCA (env.orca_backend; compiled: compiled once per shape, cached)")
    p.add_argument("--acting", default="eager", choices=["eager", "compiled"],
                   help="the acting Q network (train.compile_acting; compiled in the untimed warm-up)")
    p.add_argument("--planning", action="store_true",
                   help="act with the online planner and train its predictor (planning.enabled=true)")
    p.add_argument("--counterfactual-k", type=int, nargs="+", default=[0],
                   help="counterfactual transitions per sampled state: 0 off (default), 1..80 the top k by Q, 81 all")
    p.add_argument("--counterfactual-modes", nargs="+", default=["second_update"], choices=["second_update", "merged"],
                   help="train.counterfactual.mode of each k > 0 (one row each; default second_update)")
    p.add_argument("--scenario", default="circle", help="env.scenario of every row (default circle)")
    p.add_argument("--lidar", nargs="+", default=["off"], choices=["off", "mlp", "conv"],
                   help="encoder.lidar of each row (default off); any other than off: every row's env scans")
    p.add_argument("--lidar-rays", type=int, default=72, help="env.lidar_rays when a row reads the scan (default 72)")
    add_json_argument(p)
    args = p.parse_args(argv)
    if min(args.threads, args.num_envs, args.updates, args.batches) < 1:
        p.error("all counts must be >= 1")
    if any(not 0 <= k <= 81 for k in args.counterfactual_k):
        p.error(f"--counterfactual-k: each must lie in 0..81, got {args.counterfactual_k}")
    if args.warmup_frames < 100:
        p.error("--warmup-frames must be >= 100 (one batch of 100 is sampled from the buffer)")
    torch.set_num_threads(args.threads)
    if args.json:  # stdout carries the JSON alone (torchrl logs its storage allocation there)
        import torchrl  # noqa: F401  (its import sets the logger's level; override it after)

        logging.getLogger("torchrl").setLevel(logging.WARNING)
    from crowdrl.models import ENCODERS

    unknown = sorted(set(args.encoders) - set(ENCODERS))
    if unknown:
        p.error(f"--encoders: unknown {unknown}; allowed: {sorted(ENCODERS)}")
    measured = [measure(e, x, backend, args, k, mode, lidar) for e in args.encoders for x in args.explorations
                for backend in args.loss for k in args.counterfactual_k
                for mode in (args.counterfactual_modes if k else ["second_update"]) for lidar in args.lidar]
    results = [r for r, _ in measured]
    for r, probe in measured:  # after every timing (see matmul_mflop_per_update)
        r["matmul_mflop_per_update"] = mflop = matmul_mflop_per_update(*probe)
        r["matmul_gflop_per_s"] = mflop / r["update_ms"]
        budget_ms = r["update_ms_for_1h_budget"]
        r["matmul_gflop_per_s_for_1h_budget"] = mflop / budget_ms if budget_ms > 0 else float("inf")
    base = results[0]["update_ms"]
    for r in results:
        r["update_cost_vs_first"] = r["update_ms"] / base
    meta = {"threads": args.threads, "num_envs": args.num_envs, "encoder": args.encoders[0], "encoders": args.encoders,
            "batch_size": 100, "counterfactual_k": args.counterfactual_k, "counterfactual_modes": args.counterfactual_modes,
            "orca_backend": args.orca_backend, "acting": args.acting, "planning": args.planning,
            "scenario": args.scenario, "lidar_rays": args.lidar_rays if any(k != "off" for k in args.lidar) else 0}
    first = results[0]
    part = lambda k: Column(lambda r: r["update_breakdown_ms"][k], f"{k} ms", ".2f")  # noqa: E731
    columns = [Column("encoder"), Column("exploration"), Column("loss"), Column("lidar"),
               Column("counterfactual_k", "counterfactual k"),
               Column("counterfactual_mode", "mode"),
               Column("collect_frames_per_s", "collect frames/s", ",.0f"), Column("update_ms", "update ms", ".2f"),
               Column("updates_per_s", "updates/s", ".1f"), part("sample"), part("loss_and_grad"), part("optimizer"),
               Column("update_cost_vs_first", "vs first", ".2f"),
               Column("matmul_mflop_per_update", "matmul MFLOP", ".1f"), Column("matmul_gflop_per_s", "GFLOP/s", ".1f"),
               Column("paper_budget_hours", "paper budget h", ".2f"),
               Column("update_ms_for_1h_budget", "1 h needs ms/update", ".2f")]
    title = (f"Training throughput: threads {args.threads}, {args.num_envs} envs, batch 100, ORCA {args.orca_backend}, "
             f"acting {args.acting}" + (", planning" if args.planning else "")
             + f"; update cost relative to the first row ({first['encoder']}, {first['exploration']}, {first['loss']} loss)")
    notes = ["collect frames/s: env + acting policy through the TorchRL collector; update = sample + loss_and_grad + "
             "optimizer (ms each; optimizer: from the first optimiser step on, with counterfactual k > 0 and second_update the "
             "whole second update on the counterfactual batch; merged: one step, the counterfactual batch in loss_and_grad); "
             "matmul MFLOP: forward + backward per update; paper budget: 500k frames + 500k "
             "updates projected at these rates; 1 h needs: the update time that fits both in one hour"]
    return emit(results, columns=columns, title=title, meta=meta, as_json=args.json, notes=notes)


if __name__ == "__main__":
    main(sys.argv[1:])
