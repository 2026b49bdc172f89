"""Why does an agent time out? Roll out a checkpoint greedily on validation cases, with and without
its online planner, and describe the episodes that ran out of time.

    python experiments/diagnose_timeouts.py results/intrinsic/runs/greedy-s0/checkpoints/last.pt
    python experiments/diagnose_timeouts.py RUN/checkpoints/best.pt --episodes 200 --planning on --json

The checkpoint is a ``best.pt`` or a training checkpoint (``last.pt``: its online network). Cases are
those of the run's validation stream (``split=val``, the run's seed), never test cases. For the
timed-out episodes it reports where the robot ended (goal distance; the closest it came), whether it
stood still over its last 40 steps, the goal's bearing in its heading frame at the end (behind it:
|bearing| > 90°), and the value gap ``max_a Q(s, a) - Q(s, stop)`` at the last state (near 0: the
network values standing still about as much as anything else).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import torch

from benchkit import Column, add_json_argument, emit  # noqa: E402

STILL_STEPS = 40  # "stood still": mean speed below STILL_SPEED over the last STILL_STEPS steps
STILL_SPEED = 0.1  # m/s


def load(path: Path):
    """The run config, the Q network (eval mode) and the crowd predictor of a best.pt or last.pt."""
    from crowdrl.training.checkpoint import CheckpointError, load_checkpoint, load_trained_predictor
    from crowdrl.training.compat import stored_config
    from crowdrl.training.validation import validate
    from crowdrl.training.loss import D3QNLoss
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import make_network

    data = load_checkpoint(path)
    if "config" not in data:
        raise CheckpointError(f"{path} holds no run config")
    run = validate(stored_config(data["config"]), resources=False)  # a key it predates: what it ran with
    net = make_network(run, strategy=make_strategy(run.exploration))
    net.load_state_dict(data["net"] if "net" in data else D3QNLoss.online_state_dict(data["loss"]))
    return run, net.eval(), load_trained_predictor(run, data, path)


def rollout(run, net, predictor, *, planning: bool, episodes: int):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from crowdrl.evaluation.rollout import crowd_env_of
    from crowdrl.training.factories import make_actor, make_env

    run = replace(run, planning=replace(run.planning, enabled=planning),
                  train=replace(run.train, compile_acting=False))  # eager acting computes what compiled does
    env = make_env(run, split="val", num_envs=episodes, seed=run.seed)
    actor = make_actor(run, env, net, predictor if planning else None)
    crowd = crowd_env_of(env)
    crowd.load_episodes(torch.arange(episodes))
    start = env.reset()
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        return env.rollout(crowd.config.max_steps, actor, auto_reset=False, tensordict=start,
                           break_when_any_done=False, break_when_all_done=True)


def describe(ro) -> dict:
    """Outcome counts and the timed-out episodes' statistics of a rollout ``[episodes, steps]``."""
    event = ro["next", "event"][..., 0]  # 0 running, 1 success, 2 collision, 3 timeout
    outcome = event.amax(dim=1)
    length = (event == 0).sum(dim=1) + 1
    robot = ro["next", "robot"]  # world frame: px, py, vx, vy, r, gx, gy, v_pref, theta
    goal_distance = (robot[..., 0:2] - robot[..., 5:7]).norm(dim=-1)
    speed = robot[..., 2:4].norm(dim=-1)
    out = {"episodes": int(outcome.numel()), "success": int((outcome == 1).sum()),
           "collision": int((outcome == 2).sum()), "timeout": int((outcome == 3).sum())}
    timed_out = (outcome == 3).nonzero().flatten().tolist()
    if not timed_out:
        return out
    final_d, closest, still, behind, gap = [], [], [], [], []
    for i in timed_out:
        t = int(length[i]) - 1
        final_d.append(float(goal_distance[i, t]))
        closest.append(float(goal_distance[i, :t + 1].min()))
        still.append(float(speed[i, max(0, t + 1 - STILL_STEPS):t + 1].mean()) < STILL_SPEED)
        r = ro["robot"][i, t]
        bearing = math.atan2(float(r[6] - r[1]), float(r[5] - r[0])) - float(r[8])
        behind.append(abs(math.remainder(bearing, 2 * math.pi)) > math.pi / 2)
        q = ro["action_value"][i, t]
        gap.append(float(q.max() - q[0]))

    def median(xs):
        return float(torch.tensor(xs).median())

    return {**out, "timeout_goal_distance_median": median(final_d), "timeout_closest_median": median(closest),
            "timeout_stood_still": sum(still) / len(still), "timeout_goal_behind": sum(behind) / len(behind),
            "timeout_q_gap_to_stop_median": median(gap)}


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path, help="a best.pt or last.pt")
    p.add_argument("--episodes", type=int, default=100, help="validation cases 0..episodes-1 (default 100)")
    p.add_argument("--planning", choices=("on", "off", "both"), default="both",
                   help="act through the run's planner, the Q network alone, or both (default)")
    p.add_argument("--threads", type=int, default=1)
    add_json_argument(p)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.threads < 1:
        p.error("--episodes and --threads must be >= 1")
    from crowdrl.training.checkpoint import CheckpointError

    torch.set_num_threads(args.threads)
    try:
        run, net, predictor = load(args.checkpoint)
    except CheckpointError as exc:
        p.error(f"checkpoint: {exc}")
    modes = {"on": [True], "off": [False], "both": [True, False]}[args.planning]
    if not run.planning.enabled:
        modes = [False]  # a run trained without planning has no predictor to plan with
    rows = [{"checkpoint": str(args.checkpoint), "planning": m, **describe(rollout(run, net, predictor, planning=m,
                                                                                    episodes=args.episodes))}
            for m in modes]
    pct = lambda v: f"{v:.0%}"  # noqa: E731
    emit(rows, columns=[Column(lambda r: "on" if r["planning"] else "off", "planning"),
                        *[Column(lambda r, k=k: r[k] / r["episodes"], k, ".2f") for k in ("success", "collision", "timeout")],
                        Column("timeout_goal_distance_median", "goal dist. at end (m)", ".2f"),
                        Column("timeout_closest_median", "closest (m)", ".2f"),
                        Column("timeout_stood_still", "stood still", pct), Column("timeout_goal_behind", "goal behind", pct),
                        Column("timeout_q_gap_to_stop_median", "max Q − Q(stop)", ".4f")],
         title=f"{args.checkpoint}: {args.episodes} validation cases (seed {run.seed}); timed-out episodes described",
         meta={"checkpoint": str(args.checkpoint), "episodes": args.episodes, "seed": run.seed}, as_json=args.json)
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
