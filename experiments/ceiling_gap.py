"""How far trained agents fall short of the ceiling, and where their extra time goes.

    python experiments/ceiling_gap.py --ceiling results/ceiling/circle.json \
        --checkpoints pretrained/sgd3qn-planning-egreedy-counterfactual-polyak-episodes-s{0,1,2}
    python experiments/ceiling_gap.py --ceiling val.json --checkpoints ... --depth 2 --width 10   # act-time planning
    python experiments/ceiling_gap.py --ceiling val.json --checkpoints ... --safety 2             # the safety check
    python experiments/ceiling_gap.py --ceiling val.json --checkpoints ... --depth 2 --progress-bias 0.5   # shorter paths

Each checkpoint acts through its own actor (``make_actor``: the planner it was trained with, or the depth and
width given) on the ceiling file's cases, by ``env.rollout`` on the training env maker, under the deterministic
exploration type: the one rollout path of ``crowdrl.evaluation``. Per checkpoint it prints the success, the
collisions (and how many touched a wall, no human), the failures where a path exists (avoidable) or none does,
the time over the ceiling on the cases both solve, and that time split in two: the longer path (detour) and the
lower mean speed, with the share of slow steps (speed at most 0.2 m/s, hesitation) of the agent and of the
ceiling's paths, and the acting cost per step. ``--json FILE`` writes the numbers.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from crowdrl.evaluation.ceiling import check_stream, gap, read_ceiling
from crowdrl.evaluation.rollout import crowd_env_of, episode_records
from crowdrl.sim.crowd import COLLISION, SUCCESS
from crowdrl.sim.kinematics import action_table
from crowdrl.sim.oracle import SOLVED
from crowdrl.tables import markdown_table
from crowdrl.training.checkpoint import checkpoint_path, load_trained_network, load_trained_predictor
from crowdrl.training.config import crowd_config
from crowdrl.training.factories import make_actor, make_env
from crowdrl.training.pipeline import act_with

SLOW = 0.2  # m/s: a step at or below this speed counts as hesitation


@torch.no_grad()
def rollout_cases(run, net, predictor, ceiling, cases: int, batch: int) -> dict[str, list]:
    """Events, lengths, and per case the path length (m) and slow steps of the agent, case by case."""
    env = make_env(run, split=ceiling.split, num_envs=min(batch, cases), seed=ceiling.seed,
                   scenario=ceiling.scenario)
    actor = make_actor(run, env, net, predictor)
    crowd = crowd_env_of(env)
    max_steps = crowd.config.max_steps
    out: dict[str, list] = {"events": [], "lengths": [], "path": [], "slow": [], "steps_s": [], "last_separation": []}
    B = crowd.num_envs
    for first in range(0, cases, B):
        n = min(B, cases - first)
        crowd.load_episodes(torch.arange(first, first + B).clamp_max(cases - 1))
        start = env.reset()
        began = time.perf_counter()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            roll = env.rollout(max_steps, actor, auto_reset=False, tensordict=start, break_when_any_done=False,
                               break_when_all_done=True)
        seconds = time.perf_counter() - began
        rec = episode_records(roll, max_steps)
        speed = torch.linalg.vector_norm(roll.get(("next", "robot"))[..., 2:4], dim=-1)  # [B, T]
        inside = torch.arange(speed.shape[1]).unsqueeze(0) < rec["lengths"].unsqueeze(1)
        out["events"] += rec["events"][:n].tolist()
        out["lengths"] += rec["lengths"][:n].tolist()
        out["path"] += (torch.where(inside, speed, 0.0).sum(1) * crowd.config.time_step)[:n].tolist()
        out["slow"] += (inside & (speed <= SLOW + 1e-6)).sum(1)[:n].tolist()
        # the closest robot-human surface distance in the episode's last step: a collision with it >= 0 touched no
        # human, so the robot hit a wall (crowdrl.sim.crowd.step_reward: a human contact is a separation < 0)
        last = roll.get(("next", "min_separation")).reshape(speed.shape).gather(1, (rec["lengths"] - 1).unsqueeze(1))
        out["last_separation"] += last.squeeze(1)[:n].tolist()
        out["steps_s"].append(seconds / (B * speed.shape[1]))
    return out


def analyse(ceiling, agent: dict[str, list]) -> dict[str, float]:
    """The gap and the split of the extra time on the cases both solve."""
    dt = ceiling.time_step
    speeds = action_table()[:, 0]
    both = [i for i, (lab, ev) in enumerate(zip(ceiling.labels, agent["events"])) if lab == SOLVED and ev == SUCCESS]
    t_a = [agent["lengths"][i] * dt for i in both]
    t_o = [ceiling.steps[i] * dt for i in both]
    l_a = [agent["path"][i] for i in both]
    l_o = [float(speeds[torch.tensor(ceiling.actions[i])].sum()) * dt for i in both]
    slow_o = [int((speeds[torch.tensor(ceiling.actions[i])] <= SLOW + 1e-6).sum()) for i in both]
    v_a = [length / t for length, t in zip(l_a, t_a)]
    # T_a - T_o = (L_a - L_o) / v_a  +  L_o (1/v_a - 1/v_o): the detour at the agent's speed, then the speed
    detour = [(la - lo) / va for la, lo, va in zip(l_a, l_o, v_a)]
    slower = [(ta - to) - d for ta, to, d in zip(t_a, t_o, detour)]
    g = gap(ceiling, agent["events"], agent["lengths"])
    mean = statistics.fmean
    walls = sum(e == COLLISION and sep >= 0 for e, sep in zip(agent["events"], agent["last_separation"]))
    return {"success": sum(e == SUCCESS for e in agent["events"]) / ceiling.cases,
            "collisions": sum(e == COLLISION for e in agent["events"]), "wall_collisions": walls,
            "avoidable": g["avoidable_failures"], "unavoidable": g["unavoidable_failures"],
            "unknown": g["unknown_failures"], "beyond": g["beyond_ceiling"], "both_solved": len(both),
            "time_agent": mean(t_a), "time_ceiling": mean(t_o), "time_over": mean(t_a) - mean(t_o),
            "path_agent": mean(l_a), "path_ceiling": mean(l_o), "speed_agent": mean(v_a),
            "speed_ceiling": mean(lo / to for lo, to in zip(l_o, t_o)),
            "over_from_detour": mean(detour), "over_from_speed": mean(slower),
            "slow_steps_agent": mean(s / (t / dt) for s, t in zip((agent["slow"][i] for i in both), t_a)),
            "slow_steps_ceiling": mean(s / (t / dt) for s, t in zip(slow_o, t_o)),
            "ms_per_step": 1000 * mean(agent["steps_s"])}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ceiling", required=True, help="a ceiling file (experiments/ceiling.py)")
    p.add_argument("--checkpoints", nargs="+", required=True, help="run folders or .pt files")
    p.add_argument("--cases", type=int, default=None, help="the first cases of the file (default: all)")
    p.add_argument("--depth", type=int, default=None, help="act with this planning depth (default: the checkpoint's)")
    p.add_argument("--width", type=int, default=None, help="act with this planning width (default: the checkpoint's)")
    p.add_argument("--safety", type=int, default=None,
                   help="act with this safety-check horizon in steps (planning.safety_horizon; default: the checkpoint's)")
    p.add_argument("--progress-bias", type=float, default=None,
                   help="act with this progress bias (planning.progress_bias; default: the checkpoint's)")
    p.add_argument("--batch", type=int, default=250, help="episodes stepped at once")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", type=Path, default=None, help="write the rows here")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    try:
        ceiling = read_ceiling(a.ceiling)
    except ValueError as exc:
        p.error(f"--ceiling: {exc}")
    cases = a.cases or ceiling.cases
    if not 1 <= cases <= ceiling.cases:
        p.error(f"--cases: must lie in 1..{ceiling.cases}, got {cases}")
    ceiling = dataclasses.replace(ceiling, labels=ceiling.labels[:cases], steps=ceiling.steps[:cases],
                                  actions=ceiling.actions[:cases])
    rows = []
    for ck in a.checkpoints:
        run, net, data = load_trained_network(ck)
        given = {k: v for k, v in (("depth", a.depth), ("width", a.width), ("safety_horizon", a.safety),
                                   ("progress_bias", a.progress_bias)) if v is not None}
        if given:
            try:
                run = act_with(run, given, prefix="--")
            except ValueError as exc:
                p.error(f"{ck}: {exc}")
        try:
            check_stream(ceiling, crowd_config(run, scenario=ceiling.scenario), split=ceiling.split, seed=ceiling.seed,
                         cases=cases)
        except ValueError as exc:
            p.error(f"--ceiling: {exc}")
        predictor = load_trained_predictor(run, data, checkpoint_path(ck))
        agent = rollout_cases(run, net, predictor, ceiling, cases, a.batch)
        rows.append({"checkpoint": str(ck), "depth": run.planning.depth, "width": run.planning.width,
                     "safety_horizon": run.planning.safety_horizon, "progress_bias": run.planning.progress_bias,
                     **analyse(ceiling, agent)})
        print(f"done {ck}", file=sys.stderr, flush=True)
    keys = ["success", "collisions", "wall_collisions", "avoidable", "unavoidable",
            "time_over", "over_from_detour", "over_from_speed", "path_agent",
            "path_ceiling", "speed_agent", "speed_ceiling", "slow_steps_agent", "slow_steps_ceiling", "ms_per_step"]
    print(f"{cases} {ceiling.scenario} {ceiling.split} cases, seed {ceiling.seed}; ceiling: "
          f"{ceiling.counts()[SOLVED]} solved, mean time {ceiling.mean_time():.2f} s")
    print(markdown_table(["checkpoint", "depth x width", "safety", "progress bias", *keys],
                         [[Path(r["checkpoint"]).name, f"{r['depth']}x{r['width']}", str(r["safety_horizon"]),
                           f"{r['progress_bias']:g}",
                           *(f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k in keys)] for r in rows]))
    if a.json:
        a.json.write_text(json.dumps({"ceiling": str(a.ceiling), "cases": cases, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
