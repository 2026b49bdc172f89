"""Collection speed against a baseline checkout, measured in one run: frames/s through the TorchRL
collector with the ε-greedy SG-D3QN policy, and where a collected frame goes.

    git worktree add /tmp/crowdrl-6dfef2c 6dfef2c
    python experiments/bench_collect.py --baseline /tmp/crowdrl-6dfef2c        # table
    python experiments/bench_collect.py --baseline /tmp/crowdrl-6dfef2c --json
    python experiments/bench_collect.py --baseline /tmp/crowdrl-6dfef2c --configs eager:eager --planning --rounds 3
    # two recent commits, both with the compiled ORCA and acting network:
    python experiments/bench_collect.py --baseline /tmp/crowdrl-parent --baseline-config compiled:compiled \
        --configs compiled:compiled --profile-backend none

Each configuration (the baseline checkout's ``experiments/bench_train.py``, then this checkout's
with the eager or compiled ORCA and the eager or compiled acting network, ``--configs``) runs in its own
subprocess, one thread, 64 environments;
the configurations alternate ``--rounds`` times so that a slow spell of the machine hits them
alike, and the table gives each one's median frames/s and its ratio to the baseline's median.
The profile (this checkout, ``--profile-backend``) splits the collector's time into the env
step (physics, ORCA), resets, the robot-centric transform, the policy and the rest.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import subprocess
import sys
import time
from pathlib import Path

from benchkit import Column, add_json_argument, emit, log, table

ROOT = Path(__file__).resolve().parents[1]


def bench_train_json(checkout: Path, args: list[str]) -> dict:
    """``checkout``'s ``experiments/bench_train.py --json`` output, run in a subprocess with its own
    ``src`` first on the path (so a baseline checkout measures its own code)."""
    cmd = [sys.executable, str(checkout / "experiments" / "bench_train.py"), *args, "--json"]
    env = dict(os.environ, PYTHONPATH=str(checkout / "src"))
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=checkout, timeout=3600)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-2000:]}")
    text = out.stdout
    return json.loads(text[text.index("{"):])


def bench_train_rows(checkout: Path, args: list[str]) -> list[dict]:
    """The result rows of ``checkout``'s ``bench_train.py --json``: ``"rows"`` in the shared format of
    ``benchkit.py``, ``"results"`` in an older checkout's."""
    out = bench_train_json(checkout, args)
    return out["rows"] if "rows" in out else out["results"]


def frames_per_s(checkout: Path, num_envs: int, batches: int, backend: str | None, acting: str | None = None,
                 planning: bool = False) -> float:
    """``collect_frames_per_s`` of ``checkout``'s bench_train.py (acting through the online planner with
    ``planning``)."""
    args = ["--num-envs", str(num_envs), "--updates", "5", "--batches", str(batches), "--warmup-frames", "2000"]
    if planning:
        args.append("--planning")
    if backend is not None:
        args += ["--orca-backend", backend]
    if acting is not None:
        args += ["--acting", acting]
    return bench_train_rows(checkout, args)[0]["collect_frames_per_s"]


def profile(num_envs: int, batches: int, backend: str, acting: str = "eager") -> dict[str, float]:
    """Seconds per collected frame (µs) spent in each part of a collection, by cProfile."""
    import torch

    from crowdrl.training import factories
    from crowdrl.training.validation import validate
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import make_network

    torch.set_num_threads(1)
    run = validate({"train": {"num_envs": num_envs, "steps_per_batch": 8, "compile_acting": acting == "compiled"},
                    "env": {"orca_backend": backend}, "planning": {"enabled": False}})  # the greedy Q actor
    env = factories.make_env(run)
    strategy = make_strategy(run.exploration)  # one strategy: the network it modifies is the one its policy schedules
    actor = factories.make_actor(run, env, make_network(run, 81, strategy=strategy))
    policy = factories.make_exploration(env, actor, strategy)
    it = iter(factories.make_collector(run.train, env, policy, run.device))
    for _ in range(10):
        next(it)
    prof = cProfile.Profile()
    frames, start = 0, time.perf_counter()
    prof.enable()
    for _ in range(batches):
        frames += next(it).numel()
    prof.disable()
    total = time.perf_counter() - start
    stats = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tottime, cumtime, callers)

    def cum(file_end: str, name: str) -> float:
        return sum(v[3] for k, v in stats.items() if k[0].endswith(file_end) and k[2] == name)

    parts = {
        "env step: ORCA": cum("sim/humans.py", "human_velocities"),
        "env step: rest of the physics": cum("sim/crowd.py", "step") - cum("sim/humans.py", "human_velocities"),
        "env resets (CrowdNavEnv._reset)": cum("envs/crowd_nav.py", "_reset"),
        "robot-centric transform": cum("envs/robot_centric.py", "_call"),
        # compiled acting: CompiledModule.forward holds the compiled frame of CrowdQNetwork.forward
        "policy forward (Q network)": max(cum("models/qnet.py", "forward"), cum("crowdrl/compile.py", "forward")),
    }
    policy_all = cum("tensordict/nn/sequence.py", "forward")  # cProfile counts the outermost call of a recursion
    parts["policy: TensorDict modules, ε-greedy"] = max(0.0, policy_all - parts["policy forward (Q network)"])
    parts["collector, EnvBase and TensorDict overhead"] = max(0.0, total - sum(parts.values()))
    return {k: 1e6 * v / frames for k, v in parts.items()} | {"total": 1e6 * total / frames}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", type=Path, help="a checkout (e.g. a git worktree of 6dfef2c) to compare against")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--batches", type=int, default=40, help="timed collector batches of num_envs x 8 frames")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--configs", nargs="+", default=["eager:eager", "compiled:eager", "compiled:compiled"],
                   choices=[f"{o}:{a}" for o in ("eager", "compiled") for a in ("eager", "compiled")],
                   help="this checkout's configurations, ORCA:acting (env.orca_backend, train.compile_acting)")
    p.add_argument("--baseline-config", default=None,
                   choices=[f"{o}:{a}" for o in ("eager", "compiled") for a in ("eager", "compiled")],
                   help="the baseline's ORCA:acting, for a baseline whose bench_train.py has --orca-backend and "
                        "--acting (default: its own defaults; 6dfef2c has neither flag)")
    p.add_argument("--planning", action="store_true",
                   help="also time each of this checkout's configurations acting through SG-D3QN's online planner "
                        "(the baseline as it is: 6dfef2c has no planner)")
    p.add_argument("--profile-backend", default="compiled", choices=["eager", "compiled", "none"])
    p.add_argument("--profile-acting", default="compiled", choices=["eager", "compiled"])
    add_json_argument(p)
    args = p.parse_args(argv)
    if min(args.num_envs, args.batches, args.rounds) < 1:
        p.error("--num-envs, --batches and --rounds must be >= 1")
    if args.baseline is not None and not (args.baseline / "experiments" / "bench_train.py").is_file():
        p.error(f"--baseline {args.baseline} has no experiments/bench_train.py")
    if args.baseline_config is not None and args.baseline is None:
        p.error("--baseline-config needs --baseline")
    base_orca, base_acting = args.baseline_config.split(":") if args.baseline_config else (None, None)
    configs = ([("baseline", args.baseline, base_orca, base_acting, False)] if args.baseline else []) + \
              [(f"ORCA {o}, acting {a}{', planning' if plan else ''}", ROOT, o, a, plan)
               for o, a in (c.split(":") for c in args.configs) for plan in ((False, True) if args.planning else (False,))]
    rates: dict[str, list[float]] = {name: [] for name, *_ in configs}
    for _ in range(args.rounds):
        for name, checkout, backend, acting, plan in configs:
            rates[name].append(frames_per_s(checkout, args.num_envs, args.batches, backend, acting, plan))
            log(f"{name}: {rates[name][-1]:,.0f} frames/s")
    base = statistics.median(rates["baseline"]) if args.baseline else None
    rows = [{"config": name, "frames_per_s": statistics.median(v), "runs": v,
             "ratio_to_baseline": statistics.median(v) / base if base else None} for name, v in rates.items()]
    parts = profile(args.num_envs, args.batches, args.profile_backend, args.profile_acting) \
        if args.profile_backend != "none" else {}
    meta = {"num_envs": args.num_envs, "threads": 1, "rounds": args.rounds,
            "baseline": str(args.baseline) if args.baseline else None, "baseline_config": args.baseline_config,
            "profile_backend": args.profile_backend, "profile_acting": args.profile_acting}
    columns = [Column("config", "config (this checkout unless baseline)"), Column("frames_per_s", "frames/s", ",.0f"),
               Column("ratio_to_baseline", "ratio", ".2f"),
               Column(lambda r: ", ".join(f"{x:,.0f}" for x in r["runs"]), "runs")]
    notes = []
    if parts:
        profile_rows = [{"part": k, "us_per_frame": v, "share_pct": 100 * v / parts["total"]} for k, v in parts.items()]
        notes.append(f"Where a collected frame goes (this checkout, ORCA {args.profile_backend}, acting "
                     f"{args.profile_acting}, cProfile):\n\n"
                     + table(profile_rows, [Column("part"), Column("us_per_frame", "µs", ".1f"),
                                            Column("share_pct", "%", ".1f")]))
    return emit(rows, columns=columns, meta=meta, as_json=args.json, notes=notes,
                extra={"profile_us_per_frame": parts},
                title=f"Collection, {args.num_envs} envs, 1 thread, ε-greedy SG-D3QN, "
                      f"median of {args.rounds} alternating runs")


if __name__ == "__main__":
    main(sys.argv[1:])
