"""Spawn time: seconds of ``initial_states`` (rejection sampling of every start and goal) per (B, N).

Each (B, N) draws episodes ``0 .. B-1`` of the ``train`` stream, seed 0, and reports the median
of ``--repeat`` calls. With ``--baseline-src`` the same sizes are timed, in a subprocess, on
another checkout's ``src`` (e.g. the sampler before the speed-up) and the table adds its time,
the ratio old / new and whether both produced byte-identical states (sha256 of positions and
goals).

Usage::

    git worktree add /tmp/old-spawn fc03616
    python experiments/bench_reset.py --baseline-src /tmp/old-spawn/src
    python experiments/bench_reset.py --sizes 1024x10,512x64 --json > reset.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time

import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.rng import episode_keys
from crowdrl.sim.scenarios import initial_states

SIZES = ((1024, 10), (1024, 30), (1024, 50), (512, 64), (1024, 64))


def time_sizes(scenario: str, sizes: list[tuple[int, int]], repeat: int) -> list[dict]:
    """Median seconds of ``initial_states`` and the sha256 of its states, per (B, N)."""
    initial_states(CrowdConfig(scenario=scenario, num_humans=5), episode_keys("train", 0, torch.arange(8)))  # warm-up
    rows = []
    for B, N in sizes:
        cfg = CrowdConfig(scenario=scenario, num_humans=N)
        keys = episode_keys("train", 0, torch.arange(B))
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            s = initial_states(cfg, keys)
            times.append(time.perf_counter() - t0)
        digest = hashlib.sha256()
        for t in (s.human_position, s.human_goal):
            digest.update(t.contiguous().numpy().tobytes())
        rows.append({"B": B, "N": N, "seconds": statistics.median(times), "sha256": digest.hexdigest()})
        log(f"  {sys.modules[initial_states.__module__].__file__}: B={B} N={N} {rows[-1]['seconds']:.3f} s")
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default=",".join(f"{b}x{n}" for b, n in SIZES), help="BxN,BxN,...")
    p.add_argument("--scenario", default="circle", choices=("circle", "square"))
    p.add_argument("--repeat", type=int, default=3, help="calls per size; the median is reported")
    p.add_argument("--baseline-repeat", type=int, default=1)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--baseline-src", help="another checkout's src directory, timed in a subprocess")
    add_json_argument(p)
    # the baseline's run: this script with the other checkout's src first on the path, printing the raw
    # rows of time_sizes (B, N, seconds, sha256) for the parent to compare
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    sizes = [tuple(int(x) for x in s.split("x")) for s in args.sizes.split(",")]

    if args.worker:
        print(json.dumps(time_sizes(args.scenario, sizes, args.repeat)))
        return
    new = time_sizes(args.scenario, sizes, args.repeat)
    old = None
    if args.baseline_src:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, (args.baseline_src, os.environ.get("PYTHONPATH")))))
        cmd = [sys.executable, __file__, "--worker", "--sizes", args.sizes, "--scenario", args.scenario,
               "--repeat", str(args.baseline_repeat), "--threads", str(args.threads)]
        old = json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout)
    rows = []
    for i, r in enumerate(new):
        row = {"B": r["B"], "N": r["N"], "new_s": r["seconds"]}
        if old is not None:
            row.update(old_s=old[i]["seconds"], ratio=old[i]["seconds"] / r["seconds"],
                       identical=old[i]["sha256"] == r["sha256"])
        rows.append(row)
    columns = [Column("B"), Column("N"), Column("new_s", "new s", ".3f")]
    if old is not None:
        columns += [Column("old_s", "old s", ".3f"), Column("ratio", "old/new", ".1f"), Column("identical", "same")]
    emit(rows, columns=columns, as_json=args.json,
         meta={"scenario": args.scenario, "threads": args.threads, "torch": torch.__version__,
               "baseline_src": args.baseline_src, "repeat": args.repeat},
         title=f"Spawn time of initial_states (median of {args.repeat}), {args.scenario}, {args.threads} thread(s), "
               f"torch {torch.__version__}")


if __name__ == "__main__":
    main()
