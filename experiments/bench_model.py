"""Cost of one double-DQN update of the SG-D3QN Q network: optimised encoder vs the naive one.

One update (batch ``--batch``, ``--num-humans`` humans), as the trainer does it:

* online forward on ``s`` (with grad) and gather of the taken action's Q;
* under ``no_grad``: online forward on ``s'`` for the argmax, target forward on ``s'`` for its
  value, target ``y = r + gamma * (1 - terminated) * Q_target(s', argmax)``;
* MSE loss, backward, Adam step (lr 1e-3).

Batches are drawn once beforehand (random robot-centric states; values do not change the cost),
so only the update is timed. Each (encoder, threads) pair is timed in ``--rounds`` interleaved
rounds of ``--updates / --rounds`` updates after a warm-up; the median round and the best round
are printed as wall-clock ms/update (with the process CPU time per update, a check on
contention from other processes: with 1 thread it should be close to the wall time), with the
projection for ``--project`` updates (500k by default) in
hours. ``naive`` is :class:`~crowdrl.models.SGD3QNEncoderNaive` (concatenated pairs through the
``nn.Sequential`` MLP, both layers for every node, as upstream), with the same weights.

Usage::

    python experiments/bench_model.py                  # threads 1,2; 200 updates each
    python experiments/bench_model.py --threads 1 --updates 1000 --json
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch
import torch.nn.functional as F

from benchkit import Column, add_json_argument, emit, log
from crowdrl.models import CrowdQNetwork, DuelingHead, SGD3QNEncoder, SGD3QNEncoderNaive

GAMMA = 0.974
ENCODERS = {"sgd3qn": SGD3QNEncoder, "naive": SGD3QNEncoderNaive}


def make_batches(count: int, batch: int, num_humans: int, generator: torch.Generator) -> list[tuple[torch.Tensor, ...]]:
    out = []
    for _ in range(count):
        out.append(
            (
                torch.randn(batch, 9, generator=generator),
                torch.randn(batch, num_humans, 5, generator=generator),
                torch.randint(0, 81, (batch, 1), generator=generator),
                torch.randn(batch, generator=generator),
                torch.randn(batch, 9, generator=generator),
                torch.randn(batch, num_humans, 5, generator=generator),
                (torch.rand(batch, generator=generator) < 0.05).float(),
            )
        )
    return out


def ddqn_update(online, target, optimizer, batch) -> torch.Tensor:
    robot, humans, action, reward, next_robot, next_humans, terminated = batch
    q = online(robot, humans).gather(-1, action).squeeze(-1)
    with torch.no_grad():
        next_action = online(next_robot, next_humans).argmax(-1, keepdim=True)
        next_q = target(next_robot, next_humans).gather(-1, next_action).squeeze(-1)
        y = reward + GAMMA * (1.0 - terminated) * next_q
    loss = F.mse_loss(q, y)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.detach()


def build(encoder: str, state: dict | None, adam: str = "default"):
    online = CrowdQNetwork(ENCODERS[encoder](), DuelingHead(32, 81, 128))
    if state is not None:
        online.load_state_dict(state)
    target = copy.deepcopy(online)
    for p in target.parameters():
        p.requires_grad_(False)
    kwargs = {"default": {}, "loop": {"foreach": False}, "foreach": {"foreach": True}, "fused": {"fused": True}}[adam]
    optimizer = torch.optim.Adam(online.parameters(), lr=1e-3, **kwargs)
    return online, target, optimizer


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", default="1,2", help="comma-separated torch intra-op thread counts")
    parser.add_argument("--encoders", default="sgd3qn,naive", help=f"comma-separated, from {sorted(ENCODERS)}")
    parser.add_argument("--updates", type=int, default=200, help="timed updates per (encoder, threads)")
    parser.add_argument("--rounds", type=int, default=4, help="interleaved timing rounds")
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--batch", type=int, default=100)
    parser.add_argument("--num-humans", type=int, default=10)
    parser.add_argument("--project", type=float, default=500_000, help="updates in the projection")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--adam", default="default", choices=("default", "loop", "foreach", "fused"),
        help="Adam implementation (torch's default on CPU tensors is the per-parameter loop)",
    )
    add_json_argument(parser)
    args = parser.parse_args(argv)

    threads = [int(t) for t in args.threads.split(",")]
    encoders = args.encoders.split(",")
    for name in encoders:
        if name not in ENCODERS:
            parser.error(f"unknown encoder {name!r}; allowed: {sorted(ENCODERS)}")
    gen = torch.Generator().manual_seed(args.seed)
    batches = make_batches(8, args.batch, args.num_humans, gen)
    torch.manual_seed(args.seed)
    state = CrowdQNetwork(SGD3QNEncoder(), DuelingHead(32, 81, 128)).state_dict()
    per_round = max(1, args.updates // args.rounds)

    rows = []
    for nt in threads:
        torch.set_num_threads(nt)
        nets = {name: build(name, state, args.adam) for name in encoders}
        for name, (online, target, opt) in nets.items():
            for i in range(args.warmup):
                ddqn_update(online, target, opt, batches[i % len(batches)])
        times = {name: [] for name in encoders}
        cpu = {name: [] for name in encoders}
        for _ in range(args.rounds):
            for name, (online, target, opt) in nets.items():
                t0, c0 = time.perf_counter(), time.process_time()
                for i in range(per_round):
                    ddqn_update(online, target, opt, batches[i % len(batches)])
                times[name].append((time.perf_counter() - t0) / per_round * 1e3)
                cpu[name].append((time.process_time() - c0) / per_round * 1e3)
        for name in encoders:
            rows.append({"threads": nt, "encoder": name, "ms_per_update": statistics.median(times[name]),
                         "ms_best_round": min(times[name]), "cpu_ms_per_update": statistics.median(cpu[name])})
            rows[-1]["projected_hours"] = rows[-1]["ms_per_update"] * args.project / 3.6e6
            log(f"threads={nt} {name}: {rows[-1]['ms_per_update']:.3f} ms/update")
    for r in rows:  # the naive encoder's time over this one's, at the same thread count
        naive = [o["ms_per_update"] for o in rows if o["encoder"] == "naive" and o["threads"] == r["threads"]]
        r["speedup_vs_naive"] = naive[0] / r["ms_per_update"] if naive else None
    columns = [Column("threads"), Column("encoder"), Column("ms_per_update", "ms/update", ".3f"),
               Column("ms_best_round", "best round ms", ".3f"), Column("cpu_ms_per_update", "process CPU ms", ".3f"),
               Column("speedup_vs_naive", "vs naive", lambda v: f"{v:.2f}×"),
               Column("projected_hours", f"h per {args.project:,.0f} updates", ".2f")]
    emit(rows, columns=columns, as_json=args.json,
         meta={"torch": torch.__version__, "batch": args.batch, "num_humans": args.num_humans, "rounds": args.rounds,
               "updates_per_round": per_round, "warmup": args.warmup, "adam": args.adam, "project": args.project},
         title=f"One D3QN update, torch {torch.__version__}; batch {args.batch}, N={args.num_humans}; median of "
               f"{args.rounds} rounds x {per_round} updates after {args.warmup} warm-up; Adam {args.adam}")


if __name__ == "__main__":
    main()
