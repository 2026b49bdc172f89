"""Training throughput on this machine: collection frames/s and D3QN updates/s, with a breakdown.

    python experiments/bench_train.py                   # SG-D3QN, batch 100, 16 envs, 1 thread
    python experiments/bench_train.py --threads 2 --json

Measures, in one process: collecting frames with the ε-greedy policy through the TorchRL
collector (env + policy), sampling a batch of 100 from the replay buffer, the double-DQN loss
(forward passes), backward, and the optimiser step. Projects the paper's budget
(500k frames, 500k updates of batch 100) from the measured rates.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import torch


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--num-envs", type=int, default=16)
    p.add_argument("--updates", type=int, default=300, help="timed updates (default 300)")
    p.add_argument("--batches", type=int, default=20, help="timed collector batches (default 20)")
    p.add_argument("--encoder", default="sgd3qn")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    if min(args.threads, args.num_envs, args.updates, args.batches) < 1:
        p.error("all counts must be >= 1")
    torch.set_num_threads(args.threads)

    from crowdrl.training.config import validate
    from crowdrl.training.trainer import STORED_KEYS, Trainer
    from torchrl.collectors import Collector

    run = validate({"logger": {"name": "csv"}, "encoder": {"name": args.encoder},
                    "train": {"num_envs": args.num_envs, "steps_per_batch": 8}})
    tr = Trainer(run, "/tmp/crowdrl-bench-train")
    collector = Collector(tr.env, tr.policy, frames_per_batch=args.num_envs * 8, total_frames=-1,
                          auto_register_policy_transforms=False)
    # fill the buffer, warm up
    frames = 0
    it = iter(collector)
    while frames < 5000:
        batch = next(it)
        tr.buffer.extend(batch.select(*STORED_KEYS))
        frames += batch.numel()
    start = time.perf_counter()
    collected = 0
    for _ in range(args.batches):
        collected += next(it).numel()
    collect_s = time.perf_counter() - start
    collector.shutdown()

    parts = {"sample": [], "loss_forward": [], "backward": [], "optimizer": []}
    for i in range(args.updates + 20):
        t0 = time.perf_counter()
        sample = tr.buffer.sample()
        t1 = time.perf_counter()
        loss = tr.loss(sample)["loss"]
        t2 = time.perf_counter()
        tr.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        t3 = time.perf_counter()
        tr.optimizer.step()
        tr.counters.updates += 1
        if tr.counters.updates % tr.updates_per_copy == 0:
            tr.loss.update_target()
        t4 = time.perf_counter()
        if i >= 20:
            for k, v in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                v_list = parts[k]
                v_list.append(v)
    ms = {k: 1e3 * statistics.mean(v) for k, v in parts.items()}
    update_ms = sum(ms.values())
    frames_per_s = collected / collect_s
    budget_frames, budget_updates = 500_000, 500_000
    hours = (budget_frames / frames_per_s + budget_updates * update_ms / 1e3) / 3600
    result = {"threads": args.threads, "num_envs": args.num_envs, "encoder": args.encoder,
              "collect_frames_per_s": frames_per_s, "update_ms": update_ms, "update_breakdown_ms": ms,
              "updates_per_s": 1e3 / update_ms, "paper_budget_hours": hours}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(f"threads {args.threads}, {args.num_envs} envs, encoder {args.encoder}")
        print(f"collection: {frames_per_s:,.0f} frames/s (env + ε-greedy policy through the collector)")
        print(f"update (batch 100): {update_ms:.2f} ms = {1e3 / update_ms:.1f} updates/s")
        for k, v in ms.items():
            print(f"  {k:<13} {v:6.2f} ms  ({100 * v / update_ms:4.1f}%)")
        print(f"paper budget (500k frames + 500k updates): {hours:.2f} h projected")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
