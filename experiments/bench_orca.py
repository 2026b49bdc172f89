"""Throughput of the batched ORCA: eager (``crowdrl.sim.orca``) vs compiled (``crowdrl.sim.orca_compiled``).

Reports batched ORCA velocity computations per second, counted in agent-set steps/s (one call
on ``B`` scenes of ``N`` agents counts ``B``), for a grid of batch sizes ``B``, crowd sizes ``N``
and torch thread counts. Scenes are crowd-navigation states (``crowdrl.sim.scenarios``) a few
steps into their episodes, so the mix of feasible and infeasible (3-D fallback) programs is
the one the environment sees. Compile time (first call of a new static shape) is reported
separately from steady state.

    python experiments/bench_orca.py                  # full grid, threads 1 and 2
    python experiments/bench_orca.py --quick          # B=1024, N=10 only
    python experiments/bench_orca.py --threads 1 --json out.json   # the table, and the JSON in out.json
    python experiments/bench_orca.py --quick --env    # also the whole env step (crowd.step)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import human_preferred_velocity
from crowdrl.sim.orca import OrcaParams, orca_solve
from crowdrl.sim.scenarios import initial_states


def make_inputs(num_humans: int, batch: int, warm_steps: int = 4, scenario: str = "circle"):
    """ORCA inputs of ``batch`` crowd scenes, ``warm_steps`` ORCA steps after spawning."""
    cfg = CrowdConfig(scenario=scenario, num_humans=num_humans)
    state = initial_states(cfg, rng.episode_keys("test", 0, torch.arange(batch)))
    pos, vel, goal = state.human_position, state.human_velocity, state.human_goal
    radius = torch.full(pos.shape[:2], cfg.human_radius + cfg.orca_radius_margin, dtype=pos.dtype)
    max_speed = torch.full_like(radius, cfg.human_v_pref)
    params = OrcaParams.from_config(cfg)
    for _ in range(warm_steps):
        vel = orca_solve(pos, vel, human_preferred_velocity(pos, goal), radius, max_speed, params).velocities
        pos = pos + vel * cfg.time_step
    args = (pos, vel, human_preferred_velocity(pos, goal), radius, max_speed)
    return args, params, cfg, state.replace(human_position=pos, human_velocity=vel)


def time_calls(fn, min_time: float, repeats: int) -> list[float]:
    """Seconds per call, one sample per repeat (each repeat runs for at least ``min_time/repeats``)."""
    fn()
    t0 = time.perf_counter()
    fn()
    one = max(time.perf_counter() - t0, 1e-6)
    inner = max(1, int(min_time / repeats / one))
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        samples.append((time.perf_counter() - t0) / inner)
    return samples


def bench(threads: list[int], batches: list[int], humans: list[int], backends: list[str],
          min_time: float, repeats: int, env: bool, log) -> list[dict]:
    rows = []
    for nt in threads:
        torch.set_num_threads(nt)
        for n in humans:
            for b in batches:
                args, params, cfg, state = make_inputs(n, b)
                for backend in backends:
                    compile_s = None
                    if backend == "eager":
                        fn = lambda: orca_solve(*args, params)
                    else:
                        from crowdrl.sim.orca_compiled import compiled_orca_solve

                        fn = lambda: compiled_orca_solve(*args, params)
                        t0 = time.perf_counter()
                        fn()
                        compile_s = time.perf_counter() - t0
                    sol = fn()
                    samples = time_calls(fn, min_time, repeats)
                    sec = statistics.median(samples)
                    row = dict(what="orca", backend=backend, threads=nt, N=n, B=b, ms_per_call=sec * 1e3,
                               ms_best=min(samples) * 1e3, steps_per_s=b / sec, compile_s=compile_s,
                               infeasible=int(sol.lp_infeasible.sum()))
                    rows.append(row)
                    log(row)
                if env:
                    rows.extend(bench_env(cfg, state, backends, nt, min_time, repeats, log))
    return rows


def bench_env(cfg, state, backends, nt, min_time, repeats, log) -> list[dict]:
    """The whole ``crowd.step`` with the humans' ORCA on each backend (robot standing still)."""
    import dataclasses

    import crowdrl.sim.crowd as crowd

    rows = []
    B = state.batch_size
    vel = torch.zeros(B, 2, dtype=state.robot_position.dtype)
    for backend in backends:
        bcfg = dataclasses.replace(cfg, orca_backend="compiled" if backend == "compiled" else "eager")
        compile_s = None
        if backend == "compiled":
            t0 = time.perf_counter()
            crowd.step(bcfg, state, vel)
            compile_s = time.perf_counter() - t0
        samples = time_calls(lambda: crowd.step(bcfg, state, vel), min_time, repeats)
        sec = statistics.median(samples)
        row = dict(what="env_step", backend=backend, threads=nt, N=state.num_humans, B=B, ms_per_call=sec * 1e3,
                   ms_best=min(samples) * 1e3, steps_per_s=B / sec, compile_s=compile_s, infeasible=None)
        rows.append(row)
        log(row)
    return rows


COLUMNS = [Column("what"), Column("backend"), Column("threads", "thr"), Column("N"), Column("B"),
           Column("ms_per_call", "ms/call", ".3f"), Column("ms_best", "ms best", ".3f"),
           Column("steps_per_s", "steps/s", ",.0f"), Column("compile_s", "compile s", ".1f"),
           Column("infeasible", "infeasible")]


def format_row(r: dict) -> str:
    """A progress line for one measurement."""
    return ", ".join(f"{c.title()} {c.cell(r)}" for c in COLUMNS)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch thread counts (default: 1 2)")
    p.add_argument("--batch", type=int, nargs="+", default=[64, 256, 1024, 4096], help="batch sizes B")
    p.add_argument("--humans", type=int, nargs="+", default=[5, 10, 20], help="agents per scene N")
    p.add_argument("--backends", nargs="+", default=["eager", "compiled"], choices=["eager", "compiled"])
    p.add_argument("--quick", action="store_true", help="only B=1024, N=10 (unless --batch/--humans given)")
    p.add_argument("--env", action="store_true", help="also time the whole crowd.step per backend")
    p.add_argument("--min-time", type=float, default=1.0, help="seconds of timed calls per measurement")
    p.add_argument("--repeats", type=int, default=5, help="timing samples per measurement (median reported)")
    add_json_argument(p, path=True)
    a = p.parse_args(argv)
    given = set(sys.argv[1:] if argv is None else argv)
    if a.quick:
        if "--batch" not in given:
            a.batch = [1024]
        if "--humans" not in given:
            a.humans = [10]
        a.min_time = min(a.min_time, 0.5)
    rows = bench(a.threads, a.batch, a.humans, a.backends, a.min_time, a.repeats, a.env, lambda r: log(format_row(r)))
    meta = dict(torch=torch.__version__, cpu_capability=torch.backends.cpu.get_cpu_capability(),
                note="steps_per_s = B / median seconds per call; compile_s = first call incl. compilation")
    emit(rows, columns=COLUMNS, meta=meta, as_json=a.json,
         title=f"Batched ORCA throughput, torch {meta['torch']} ({meta['cpu_capability']}): {meta['note']}; "
               "infeasible: agents on the 3-D fallback")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
