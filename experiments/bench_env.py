"""Environment throughput: batched torch simulator vs a one-episode-at-a-time RVO2 reference.

For every (B, N) it measures env-steps per second (B x steps / seconds) with uniformly random,
seeded robot actions:

* ``core``: the simulator core alone: action table + ``unicycle_step`` + ``crowd.step`` on a
  :class:`CrowdState`, with done episodes re-spawned by ``initial_states`` for the next episode
  ids of the ``train`` stream (what the env does), so resets happen at their natural rate and
  are timed (``reset%`` is their share of the core time, ``rst/1k`` the resets per 1000
  env-steps: random actions collide often, so far more than a trained policy's; ``no-reset``
  is the core's rate with the reset time taken out);
* ``env``: the same through :class:`CrowdNavEnv` and TorchRL's ``step_and_maybe_reset`` (the
  collector's loop), showing the TensorDict/TorchRL overhead;
* ``ref``: :class:`~crowdrl_testing.reference.ReferenceCrowdSim` (plain Python + RVO2) stepping the
  same scenes one env at a time, as reference simulators do; independent of B, so measured
  once per N on ``--ref-steps`` steps in total, median of three runs (building a new simulator at every reset is
  timed; drawing the initial state is not: it is generated beforehand by ``initial_states``).
  ``xref`` = core / ref. In the obstacle scenarios the reference gets the episode's obstacles (RVO2's
  ``add_obstacle``/``process_obstacles`` at every reset, timed) and, in ``doorway``, computes the
  humans' waypoints through the gap with the batched simulator's pure function on ``[N, 2]`` tensors
  (``ref wp%``: the share of its time spent there; ``xref-wp`` is ``xref`` against the reference
  with that time taken out, i.e. as if the rule cost it nothing).

``--scenario`` is any of :data:`crowdrl.sim.config.SCENARIOS`. ``--compare-obstacles [SCENARIO]``
(``doorway`` by default) measures ``circle`` and that obstacle scenario in the same run instead of the
B sweep, at B = 1024, N = 10 unless ``--batch-sizes``/``--num-humans`` say otherwise (alternating the
two scenarios for each measurement, so both see the same machine), and adds the ratios of the
obstacle scenario's rates to circle's (``core/circ``, ``env/circ``) to its row; ``edges`` is the
scenario's obstacle edges (doorway: 2 wall segments, one each side of the gap). ``--compare-humans``
likewise measures the humans' models (``orca``, ``orca`` seeing the robot, ``social_force`` with and
without, ``linear``, a ``mixed`` crowd of 0.3 social force, 0.3 linear and 0.4 ORCA) in ``--scenario``
and adds each row's ratios to invisible ORCA's (``core/orca``, ``env/orca``); no reference column there
(it simulates blind ORCA humans only).

Memory: ``state MB`` is the tensor bytes of the batched state. The peak resident memory
(printed once) is measured in a fresh subprocess at ``--memory-batch-size`` (default B=65,536),
N=10: the kernel's RSS high-water mark (``VmHWM``, reset through ``/proc/self/clear_refs`` just
before) while building the state and while taking two steps of the core, then while building a
``CrowdNavEnv`` of that size and taking two ``step_and_maybe_reset`` steps with it; reported as
the process's peak RSS (everything: Python, torch, the state, every transient tensor of the
step) and as the rise above the RSS just before (``ru_maxrss`` cannot be reset and stays at the
import peak, so it is only a fallback).

Usage::

    python experiments/bench_env.py --quick
    python experiments/bench_env.py --threads 1,2 --json > bench.json
    python experiments/bench_env.py --backend compiled --quick  # crowdrl.sim.orca_compiled, when importable
    python experiments/bench_env.py --compare-obstacles --no-memory  # circle vs doorway, B = 1024, N = 10
    python experiments/bench_env.py --compare-humans --no-memory     # orca, social_force, linear, B = 1024

The compiled backend builds one graph per (B, N) on first use (minutes with a cold inductor
cache); the warm-up steps absorb it, but restrict ``--batch-sizes``/``--num-humans`` with it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from benchkit import Column, add_json_argument, emit, log
from crowdrl.sim import crowd
from crowdrl.sim.config import OBSTACLE_SCENARIOS, SCENARIOS, CrowdConfig
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, unicycle_step
from crowdrl.sim.obstacles import process_obstacles, put_edges
from crowdrl.sim.rng import episode_keys
from crowdrl.sim.scenarios import initial_states
from crowdrl.sim.state import CrowdState

FULL_B = (1, 64, 256, 1024, 4096)
FULL_N = (5, 10, 20)
QUICK_B = (1, 64, 1024)
QUICK_N = (10,)
COMPARE_B, COMPARE_N = (1024,), (10,)  # --compare-obstacles
MEM_B, MEM_N = 65536, 10


def state_bytes(state: CrowdState) -> int:
    return sum(getattr(state, f.name).nbytes for f in dataclasses.fields(state))


def select_step(backend: str):
    """The batched step function, or ``None`` when ``backend`` cannot run here.

    The backend itself is chosen through ``CrowdConfig.orca_backend`` (see :func:`orca_backend`).
    """
    if backend == "compiled":
        try:
            from crowdrl.sim import orca_compiled  # noqa: F401,PLC0415
        except ImportError as exc:
            log(f"backend 'compiled' is unavailable: crowdrl.sim.orca_compiled cannot be imported ({exc})")
            return None
    return crowd.step


def orca_backend(backend: str) -> str:
    return "compiled" if backend == "compiled" else "eager"


# ----------------------------------------------------------------------------- batched core
def bench_core(cfg: CrowdConfig, B: int, steps: int, warmup: int, seed: int, step_fn, max_seconds: float) -> dict:
    state = initial_states(cfg, episode_keys("train", seed, torch.arange(B)))
    # the obstacles' processed edges, kept as the env keeps them (fixed per episode; re-spawned
    # episodes' edges are processed with their state, in the timed reset)
    edges = process_obstacles(state.obstacles, state.obstacle_mask) if state.has_obstacles else None
    next_id = B
    table = action_table(cfg.robot_v_pref)
    gen = torch.Generator().manual_seed(seed)
    reset_time = 0.0
    resets = 0

    def one() -> None:
        nonlocal state, edges, next_id, reset_time, resets
        action = torch.randint(0, NUM_ACTIONS, (B,), generator=gen)
        speed_rot = table[action]
        heading, velocity = unicycle_step(state.robot_heading, speed_rot[:, 0], speed_rot[:, 1])
        state, res = step_fn(cfg, state, velocity, heading, obstacle_edges=edges)
        done = res.terminated | res.truncated
        if bool(done.any()):
            t0 = time.perf_counter()
            idx = done.nonzero(as_tuple=True)[0]
            k = idx.numel()
            fresh = initial_states(cfg, episode_keys("train", seed, torch.arange(next_id, next_id + k)))
            next_id += k
            for f in dataclasses.fields(state):
                getattr(state, f.name)[idx] = getattr(fresh, f.name)
            if edges is not None:
                edges = put_edges(edges, idx, process_obstacles(fresh.obstacles, fresh.obstacle_mask))
            reset_time += time.perf_counter() - t0
            resets += k

    for _ in range(warmup):
        one()
    reset_time, resets = 0.0, 0
    done_steps = 0
    t0 = time.perf_counter()
    while done_steps < steps:
        one()
        done_steps += 1
        if time.perf_counter() - t0 > max_seconds and done_steps >= 3:
            break
    elapsed = time.perf_counter() - t0
    return dict(core_steps=done_steps, core_sps=B * done_steps / elapsed, core_ms_per_step=1e3 * elapsed / done_steps,
                step_only_sps=B * done_steps / max(elapsed - reset_time, 1e-12),
                reset_share=reset_time / elapsed, resets_per_1k=1e3 * resets / (B * done_steps),
                state_mb=state_bytes(state) / 2**20)


# ------------------------------------------------------------------------------- TorchRL env
def bench_env(cfg: CrowdConfig, B: int, steps: int, warmup: int, seed: int, max_seconds: float) -> dict:
    from crowdrl.envs.crowd_nav import CrowdNavEnv  # noqa: PLC0415 - TorchRL import only when needed

    env = CrowdNavEnv(cfg.scenario, num_envs=B, num_humans=cfg.num_humans, seed=seed, split="train", config=cfg)
    td = env.reset()
    gen = torch.Generator().manual_seed(seed)

    def one(td):
        td["action"] = torch.randint(0, NUM_ACTIONS, (B,), generator=gen)
        _, td = env.step_and_maybe_reset(td)
        return td

    for _ in range(warmup):
        td = one(td)
    done_steps = 0
    t0 = time.perf_counter()
    while done_steps < steps:
        td = one(td)
        done_steps += 1
        if time.perf_counter() - t0 > max_seconds and done_steps >= 3:
            break
    elapsed = time.perf_counter() - t0
    return dict(env_steps=done_steps, env_sps=B * done_steps / elapsed)


# ------------------------------------------------------------------------ reference (RVO2)
def bench_reference(cfg: CrowdConfig, total_steps: int, seed: int) -> dict | None:
    try:
        from crowdrl_testing.reference import ReferenceCrowdSim  # noqa: PLC0415
        import pyrvo  # noqa: F401, PLC0415
    except ImportError as exc:
        log(f"reference column skipped: {exc}")
        return None
    episodes = 64
    pool = initial_states(cfg, episode_keys("train", seed, torch.arange(episodes)))
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, NUM_ACTIONS, size=total_steps + 1)
    rates, waypoint_shares = [], []
    waypoint_time = 0.0

    def build(index: int, ep_seed: int) -> ReferenceCrowdSim:
        sim = ReferenceCrowdSim.from_state(cfg, pool, index, seed=ep_seed)
        if cfg.scenario == "doorway":  # time the waypoint rule (crowd.preferred_velocities on tensors)
            inner = sim.preferred_velocities

            def timed():
                nonlocal waypoint_time
                t = time.perf_counter()
                out = inner()
                waypoint_time += time.perf_counter() - t
                return out
            sim.preferred_velocities = timed
        return sim

    for _ in range(3):  # short runs on a shared machine: the median of three
        steps, ep = 0, 0
        waypoint_time = 0.0
        t0 = time.perf_counter()
        sim = build(0, seed)
        while steps < total_steps:
            _, terminated, truncated, _ = sim.step(int(actions[steps]))
            steps += 1
            if terminated or truncated:
                ep += 1
                sim = build(ep % episodes, seed + ep)
        elapsed = time.perf_counter() - t0
        rates.append(steps / elapsed)
        waypoint_shares.append(waypoint_time / elapsed)
    out = dict(ref_steps=steps, ref_sps=float(np.median(rates)), ref_sps_runs=rates, ref_episodes=ep)
    if cfg.scenario == "doorway":
        out["ref_waypoint_share"] = float(np.median(waypoint_shares))
    return out


# ------------------------------------------------------------------------------ memory probe
def _proc_status_mib(field: str) -> float | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    """Reset the kernel's RSS high-water mark (VmHWM) of this process (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def memory_probe(cfg: CrowdConfig, B: int, seed: int, step_fn) -> dict:
    """Run in a fresh process: resident memory (MiB) of building the state and of stepping it.

    Uses the kernel's peak-RSS counter (VmHWM), reset just before what is measured, so the
    peak of the import phase does not hide it; falls back to ``ru_maxrss`` (which then may).
    """
    table = action_table(cfg.robot_v_pref)
    gen = torch.Generator().manual_seed(seed)

    def one(state):
        speed_rot = table[torch.randint(0, NUM_ACTIONS, (state.batch_size,), generator=gen)]
        heading, velocity = unicycle_step(state.robot_heading, speed_rot[:, 0], speed_rot[:, 1])
        return step_fn(cfg, state, velocity, heading)[0]

    one(initial_states(cfg, episode_keys("train", seed, torch.arange(8))))  # lazy allocations at small B
    exact = _reset_peak_rss()
    rss0 = _proc_status_mib("VmRSS")
    state = initial_states(cfg, episode_keys("train", seed, torch.arange(B)))
    peak_init = _proc_status_mib("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rss1 = _proc_status_mib("VmRSS")
    exact = exact and _reset_peak_rss()
    for _ in range(2):
        state = one(state)
    peak_step = _proc_status_mib("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out = dict(B=B, N=cfg.num_humans, state_mb=state_bytes(state) / 2**20, method="VmHWM" if exact else "ru_maxrss",
               rss_init_delta_mb=peak_init - rss0, rss_step_delta_mb=peak_step - rss1,
               peak_rss_mb=max(peak_init, peak_step))
    del state
    # the same through CrowdNavEnv and TorchRL's step_and_maybe_reset (observations, rewards, resets)
    from crowdrl.envs.crowd_nav import CrowdNavEnv  # noqa: PLC0415 - TorchRL import only when needed

    exact = exact and _reset_peak_rss()
    rss2 = _proc_status_mib("VmRSS")
    env = CrowdNavEnv(cfg.scenario, num_envs=B, num_humans=cfg.num_humans, seed=seed, split="train", config=cfg)
    td = env.reset()
    for _ in range(2):
        td["action"] = torch.randint(0, NUM_ACTIONS, (B,), generator=gen)
        _, td = env.step_and_maybe_reset(td)
    peak_env = _proc_status_mib("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out.update(env_peak_rss_mb=peak_env, env_rss_delta_mb=peak_env - rss2)
    return out


def run_memory_probe(args) -> dict | None:
    cmd = [sys.executable, os.path.abspath(__file__), "--_memprobe", "--threads", str(args.threads[0]),
           "--backend", args.backend, "--scenario", args.scenario, "--seed", str(args.seed),
           "--memory-batch-size", str(args.memory_batch_size)]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=1800)
        return json.loads(out.stdout.strip().splitlines()[-1])
    except (subprocess.SubprocessError, ValueError, IndexError) as exc:
        log(f"memory probe failed: {exc}")
        return None


# ------------------------------------------------------------------------------------ main
def sweep(args, step_fn) -> tuple[list[dict], dict]:
    """The (threads, N, B) grid of one scenario."""
    rows = []
    ref_cache: dict[int, dict | None] = {}
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n in args.num_humans:
            cfg = CrowdConfig(scenario=args.scenario, num_humans=n, orca_backend=orca_backend(args.backend))
            if n not in ref_cache:
                ref_cache[n] = bench_reference(cfg, args.ref_steps, args.seed)
                if ref_cache[n]:
                    log(f"ref N={n}: {ref_cache[n]['ref_sps']:.0f} steps/s")
            ref = ref_cache[n]
            for b in args.batch_sizes:
                row = dict(threads=threads, N=n, B=b)
                row.update(bench_core(cfg, b, args.steps, args.warmup, args.seed, step_fn, args.max_seconds))
                if not args.no_env:
                    row.update(bench_env(cfg, b, args.steps, args.warmup, args.seed, args.max_seconds))
                if ref:
                    row.update(ref_sps=ref["ref_sps"], speedup_vs_ref=row["core_sps"] / ref["ref_sps"])
                rows.append(row)
                log(f"threads={threads} N={n} B={b}: core {row['core_sps']:.0f} env {row.get('env_sps', 0):.0f} steps/s")
    return rows, ref_cache


def compare_obstacles(args, step_fn) -> tuple[list[dict], dict]:
    """``circle`` and the obstacle scenario ``args.compare_obstacles`` at every (threads, N, B): each
    measurement (reference, core, env) taken for both scenarios back to back; the obstacle row gets
    its rates' ratios to circle's."""
    scenarios = ("circle", args.compare_obstacles)
    rows = []
    ref_cache: dict[str, dict | None] = {}  # by "scenario N=n"
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n in args.num_humans:
            cfgs = {s: CrowdConfig(scenario=s, num_humans=n, orca_backend=orca_backend(args.backend)) for s in scenarios}
            for s in scenarios:
                if f"{s} N={n}" not in ref_cache:
                    ref_cache[f"{s} N={n}"] = ref = bench_reference(cfgs[s], args.ref_steps, args.seed)
                    if ref:
                        log(f"ref {s} N={n}: {ref['ref_sps']:.0f} steps/s")
            for b in args.batch_sizes:
                pair = {s: dict(scenario=s, edges=cfgs[s].num_obstacle_edges, threads=threads, N=n, B=b)
                        for s in scenarios}
                for s in scenarios:
                    pair[s].update(bench_core(cfgs[s], b, args.steps, args.warmup, args.seed, step_fn, args.max_seconds))
                if not args.no_env:
                    for s in scenarios:
                        pair[s].update(bench_env(cfgs[s], b, args.steps, args.warmup, args.seed, args.max_seconds))
                for s in scenarios:
                    ref = ref_cache[f"{s} N={n}"]
                    if ref:
                        pair[s].update(ref_sps=ref["ref_sps"], speedup_vs_ref=pair[s]["core_sps"] / ref["ref_sps"])
                        if "ref_waypoint_share" in ref:  # and xref against the reference without that time
                            share = ref["ref_waypoint_share"]
                            pair[s].update(ref_waypoint_share=share,
                                           speedup_vs_ref_no_wp=pair[s]["speedup_vs_ref"] * (1 - share))
                circle, obst = pair["circle"], pair[args.compare_obstacles]
                obst["core_vs_circle"] = obst["core_sps"] / circle["core_sps"]
                if not args.no_env:
                    obst["env_vs_circle"] = obst["env_sps"] / circle["env_sps"]
                rows += [circle, obst]
                log(f"threads={threads} N={n} B={b}: {args.compare_obstacles}/circle core {obst['core_vs_circle']:.2f} "
                    f"env {obst.get('env_vs_circle', float('nan')):.2f}")
    return rows, ref_cache


HUMAN_CELLS = (("orca", False), ("orca", True), ("social_force", False), ("social_force", True), ("linear", False),
               ("mixed", False))
MIXED_SHARES = {"social_force_share": 0.3, "linear_share": 0.3}  # the mixed cell: ORCA the other 0.4 (as human_model_transfer.py)


def human_cell_name(model: str, visible: bool) -> str:
    shares = f" ({MIXED_SHARES['social_force_share']} social force, {MIXED_SHARES['linear_share']} linear)"
    return model + (shares if model == "mixed" else "") + (" (robot visible)" if visible else "")


def compare_humans(args, step_fn) -> tuple[list[dict], dict]:
    """The humans' models (:data:`HUMAN_CELLS`: model, robot visible) in ``args.scenario`` at every
    (threads, N, B), each measurement taken for every cell back to back, ``args.rounds`` times in turn; each
    row is its cell's median round (``core_sps_rounds``: every round's rate) and gets its rates' ratios to
    invisible ORCA's (``core/orca``: of the medians; ``core_vs_orca_rounds``: round by round; ``env/orca``).
    No reference column (it simulates ORCA only)."""
    rows = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for n in args.num_humans:
            cfgs = {c: CrowdConfig(scenario=args.scenario, num_humans=n, orca_backend=orca_backend(args.backend),
                                   human_model=c[0], robot_visible=c[1], **(MIXED_SHARES if c[0] == "mixed" else {}))
                    for c in HUMAN_CELLS}
            for b in args.batch_sizes:
                cells = {c: dict(humans=human_cell_name(*c), threads=threads, N=n, B=b) for c in HUMAN_CELLS}
                rounds = {c: [] for c in HUMAN_CELLS}
                for _ in range(args.rounds):  # the cells in turn, so that a drift of the machine reaches them all
                    for c in HUMAN_CELLS:
                        rounds[c].append(bench_core(cfgs[c], b, args.steps, args.warmup, args.seed, step_fn,
                                                    args.max_seconds))
                for c in HUMAN_CELLS:
                    ranked = sorted(rounds[c], key=lambda r: r["core_sps"])
                    cells[c].update(ranked[(len(ranked) - 1) // 2], rounds=args.rounds,
                                    core_sps_rounds=[r["core_sps"] for r in rounds[c]])
                orca_rounds = cells[HUMAN_CELLS[0]]["core_sps_rounds"]
                for c in HUMAN_CELLS:
                    cells[c]["core_vs_orca_rounds"] = [r / o for r, o in zip(cells[c]["core_sps_rounds"], orca_rounds)]
                if not args.no_env:
                    for c in HUMAN_CELLS:
                        cells[c].update(bench_env(cfgs[c], b, args.steps, args.warmup, args.seed, args.max_seconds))
                orca = cells[HUMAN_CELLS[0]]
                for row in cells.values():
                    row["core_vs_orca"] = row["core_sps"] / orca["core_sps"]
                    if not args.no_env:
                        row["env_vs_orca"] = row["env_sps"] / orca["env_sps"]
                    log(f"threads={threads} N={n} B={b} {row['humans']}: core {row['core_sps']:.0f} steps/s "
                        f"({row['core_vs_orca']:.2f} x orca)")
                rows += list(cells.values())
    return rows, {}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help=f"B in {QUICK_B}, N in {QUICK_N}, fewer steps (< 1 min)")
    add_json_argument(p)
    p.add_argument("--threads", default="1", help="torch threads, or a comma list to compare (e.g. 1,2)")
    p.add_argument("--steps", type=int, default=None, help="timed steps per (B, N) (default 30, quick 10)")
    p.add_argument("--warmup", type=int, default=3, help="untimed steps first")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="stop timing a (B, N) after this long once 3 steps are done (default 15, quick 4)")
    p.add_argument("--ref-steps", type=int, default=None, help="reference steps per N (default 400, quick 150)")
    p.add_argument("--batch-sizes", default=None, help="comma list overriding the B values")
    p.add_argument("--num-humans", default=None, help="comma list overriding the N values")
    p.add_argument("--scenario", default="circle", choices=SCENARIOS)
    p.add_argument("--compare-obstacles", nargs="?", const="doorway", default=None, choices=OBSTACLE_SCENARIOS,
                   metavar="SCENARIO", help="measure circle and SCENARIO (default doorway) in the same run, at "
                   "B = 1024, N = 10 unless --batch-sizes/--num-humans are given, with the rate ratios")
    p.add_argument("--compare-humans", action="store_true",
                   help="measure the humans' models (orca, orca seeing the robot, social_force, social_force seeing "
                   "the robot, linear) in --scenario in the same run, at B = 1024, N = 10 unless "
                   "--batch-sizes/--num-humans are given, with the rate ratios to invisible orca")
    p.add_argument("--rounds", type=int, default=1,
                   help="--compare-humans: measure every cell this many times in turn; rows show the median round")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-env", action="store_true", help="skip the CrowdNavEnv column")
    p.add_argument("--no-memory", action="store_true", help="skip the memory probe subprocess")
    p.add_argument("--memory-batch-size", type=int, default=MEM_B, help=f"B of the memory probe (default {MEM_B})")
    p.add_argument("--backend", default="torch", choices=("torch", "compiled"),
                   help="'compiled' steps with crowdrl.sim.orca_compiled when it can be imported")
    p.add_argument("--_memprobe", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.memory_batch_size < 1:
        p.error(f"--memory-batch-size must be >= 1, got {args.memory_batch_size}")
    if args.rounds < 1:
        p.error(f"--rounds must be >= 1, got {args.rounds}")
    if args.rounds > 1 and not args.compare_humans:
        p.error("--rounds applies to --compare-humans only")
    args.threads = [int(t) for t in str(args.threads).split(",")]
    args.steps = args.steps or (10 if args.quick else 30)
    args.max_seconds = args.max_seconds or (4.0 if args.quick else 15.0)
    args.ref_steps = args.ref_steps or (150 if args.quick else 400)
    default_b, default_n = (QUICK_B, QUICK_N) if args.quick else (FULL_B, FULL_N)
    if args.compare_obstacles and args.compare_humans:
        p.error("--compare-obstacles and --compare-humans are separate runs")
    if args.compare_obstacles or args.compare_humans:
        default_b, default_n = COMPARE_B, COMPARE_N
    args.batch_sizes = [int(b) for b in args.batch_sizes.split(",")] if args.batch_sizes else list(default_b)
    args.num_humans = [int(n) for n in args.num_humans.split(",")] if args.num_humans else list(default_n)
    return args


COLUMNS = [Column("threads", "thr"), Column("N"), Column("B"), Column("core_sps", "core sps", ".0f"),
           Column("core_ms_per_step", "ms/step", ".2f"), Column("reset_share", "reset%", lambda v: f"{100 * v:.1f}"),
           Column("resets_per_1k", "rst/1k", ".1f"), Column("step_only_sps", "no-reset", ".0f"),
           Column("env_sps", "env sps", ".0f"), Column("ref_sps", "ref sps", ".0f"),
           Column("speedup_vs_ref", "xref", ".1f"), Column("state_mb", "state MB", ".3f")]
# --compare-obstacles: the scenario and its obstacle edges first, the ratios to circle last
COMPARE_COLUMNS = [Column("scenario"), Column("edges"), *COLUMNS,
                   Column("ref_waypoint_share", "ref wp%", lambda v: f"{100 * v:.0f}"),
                   Column("speedup_vs_ref_no_wp", "xref-wp", ".1f"),
                   Column("core_vs_circle", "core/circ", ".2f"), Column("env_vs_circle", "env/circ", ".2f")]


# --compare-humans: the humans' model first, the ratios to invisible ORCA last
HUMANS_COLUMNS = [Column("humans"), *(c for c in COLUMNS if c.key not in ("ref_sps", "speedup_vs_ref")),
                  Column("core_vs_orca", "core/orca", ".2f"),
                  Column("core_vs_orca_rounds", "core/orca by round", lambda v: f"{min(v):.2f}–{max(v):.2f}"),
                  Column("env_vs_orca", "env/orca", ".2f")]


def memory_note(memory: dict) -> str:
    return (f"Memory at B={memory['B']}, N={memory['N']} (fresh process, peak RSS by {memory['method']}): "
            f"state tensors {memory['state_mb']:.2f} MiB; peak RSS above the prior RSS: "
            f"{memory['rss_init_delta_mb']:.1f} MiB building the state (initial_states), "
            f"{memory['rss_step_delta_mb']:.1f} MiB during two steps; process peak RSS "
            f"{memory['peak_rss_mb']:.0f} MiB (core), {memory['env_peak_rss_mb']:.0f} MiB (CrowdNavEnv: "
            f"+{memory['env_rss_delta_mb']:.0f} MiB building it and stepping twice)")


def main(argv=None) -> int:
    args = parse_args(argv)
    step_fn = select_step(args.backend)
    if step_fn is None:
        if args.json:
            print(json.dumps({"meta": {"backend": args.backend, "available": False}, "rows": []}))
        return 2
    torch.set_num_threads(args.threads[0])

    if args._memprobe:
        cfg = CrowdConfig(scenario=args.scenario, num_humans=MEM_N, orca_backend=orca_backend(args.backend))
        print(json.dumps(memory_probe(cfg, args.memory_batch_size, args.seed, step_fn)))
        return 0

    if args.compare_obstacles:
        rows, ref_cache = compare_obstacles(args, step_fn)
    elif args.compare_humans:
        rows, ref_cache = compare_humans(args, step_fn)
    else:
        rows, ref_cache = sweep(args, step_fn)
    memory = None if args.no_memory else run_memory_probe(args)
    meta = dict(backend=args.backend, scenario=args.scenario, torch=torch.__version__, cpus=os.cpu_count(),
                python=platform.python_version(), machine=platform.machine(), seed=args.seed,
                steps=args.steps, warmup=args.warmup, ref_steps=args.ref_steps)
    scenarios = f"scenario {args.scenario}"
    if args.compare_obstacles:
        meta.update(scenario=f"circle,{args.compare_obstacles}", compare_obstacles=args.compare_obstacles)
        scenarios = f"scenarios circle and {args.compare_obstacles}"
    if args.compare_humans:
        meta.update(compare_humans=True, rounds=args.rounds)
        scenarios += ", the humans' models"
    columns = COMPARE_COLUMNS if args.compare_obstacles else HUMANS_COLUMNS if args.compare_humans else COLUMNS
    emit(rows, columns=columns, meta=meta, as_json=args.json,
         extra=dict(memory=memory, reference=ref_cache),
         notes=[memory_note(memory)] if memory else [],
         title=f"Simulator throughput: {meta['backend']} backend, {scenarios}, torch {meta['torch']}, "
               f"{meta['cpus']} CPUs, random actions, env-steps/s = B * steps / s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
