"""Acting cost per env-step with and without online planning (target: planning costs ≤ 3× plain acting).

    python experiments/bench_planning.py                          # B = 256 and 1024, d = 1, w = 10
    python experiments/bench_planning.py --num-envs 256 --depth 2 --width 5 --json

For each batch size ``B``, in one process and one thread: the acting policy of training (the
plain greedy Q actor, or the :class:`~crowdrl.policies.OnlinePlanner` with a learned predictor,
each followed by ε-greedy) on ``B`` circle episodes of SG-D3QN with 10 humans. Two costs per
env-step: the policy alone (``policy``, one call on a ``[B]`` tensordict, no gradient) and a
collection step (``act+step``: the policy, then the env's step with ORCA humans and the
robot-centric transform, as a collector pays per frame). Untrained networks: the cost does not
depend on the weights. Both policies share the env and are timed in alternation, round after
round, after a warm-up (which also compiles the pairwise attention kernels); medians over
``--rounds``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchkit import Column, add_json_argument, emit, log


def build(num_envs: int, depth: int, width: int):
    """The env and both acting policies (greedy Q and the planner, each then ε-greedy) on one Q network."""
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import TransformedEnv
    from torchrl.modules import EGreedyModule

    from crowdrl.envs import CrowdNavEnv, RobotCentric
    from crowdrl.models import make_q_actor, make_q_network
    from crowdrl.models.predictor import make_predictor
    from crowdrl.policies import OnlinePlanner

    torch.manual_seed(0)
    env = TransformedEnv(CrowdNavEnv("circle", num_envs=num_envs, seed=0), RobotCentric())
    cfg = env.base_env.config
    net = make_q_network("sgd3qn")
    actors = {"greedy": make_q_actor("sgd3qn", env.action_spec, net=net),
              "planning": OnlinePlanner(net, make_predictor("learned", cfg.time_step), cfg, gamma=0.9 ** 0.25,
                                        depth=depth, width=width)}
    return env, {k: TensorDictSequential(a, EGreedyModule(env.action_spec, eps_init=0.1, eps_end=0.1))
                 for k, a in actors.items()}


def measure(num_envs: int, depth: int, width: int, rounds: int, steps: int) -> list[dict]:
    """Both policies timed in alternation, round after round (the machine's load drifts; the ratio
    is taken between neighbouring measurements), medians over ``rounds``."""
    env, policies = build(num_envs, depth, width)
    td = env.reset()
    times: dict[str, dict[str, list[float]]] = {k: {"policy": [], "step": []} for k in policies}
    with torch.no_grad():
        for policy in policies.values():  # warm-up (kernel compilation, allocator)
            for _ in range(3):
                td = env.step_and_maybe_reset(policy(td))[1]
        for _ in range(rounds):
            for name, policy in policies.items():
                start = time.perf_counter()
                policy(td.clone())
                times[name]["policy"].append(time.perf_counter() - start)
                start = time.perf_counter()
                for _ in range(steps):
                    td = env.step_and_maybe_reset(policy(td))[1]
                times[name]["step"].append((time.perf_counter() - start) / steps)
    rows = []
    for name in policies:
        planning = name == "planning"
        rows.append({"num_envs": num_envs, "planning": planning, "depth": depth if planning else 0,
                     "width": width if planning else 0,
                     "policy_us_per_env_step": statistics.median(times[name]["policy"]) / num_envs * 1e6,
                     "act_step_us_per_env_step": statistics.median(times[name]["step"]) / num_envs * 1e6})
    for key in ("policy", "act_step"):
        rows[1][f"{key}_ratio"] = rows[1][f"{key}_us_per_env_step"] / rows[0][f"{key}_us_per_env_step"]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--depth", type=int, default=1)
    parser.add_argument("--width", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=15, help="alternating timed rounds per batch size")
    parser.add_argument("--steps", type=int, default=3, help="collection steps per policy per round")
    parser.add_argument("--threads", type=int, default=1)
    add_json_argument(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for n in args.num_envs:
        rows += measure(n, args.depth, args.width, args.rounds, args.steps)
        log(f"B={n}: act+step ratio {rows[-1]['act_step_ratio']:.2f}")
    columns = [Column("num_envs", "B"),
               Column(lambda r: f"planning d={r['depth']} w={r['width']}" if r["planning"] else "greedy Q", "policy"),
               Column("policy_us_per_env_step", "policy µs", ".1f"),
               Column("act_step_us_per_env_step", "act+step µs", ".1f"),
               Column(lambda r: r.get("policy_ratio", 1.0), "policy ratio", lambda v: f"{v:.2f}×"),
               Column(lambda r: r.get("act_step_ratio", 1.0), "act+step ratio", lambda v: f"{v:.2f}×")]
    emit(rows, columns=columns, as_json=args.json,
         meta={"threads": args.threads, "depth": args.depth, "width": args.width, "rounds": args.rounds,
               "steps": args.steps, "encoder": "sgd3qn", "num_humans": 10, "predictor": "learned"},
         title=f"Acting cost per env-step (µs), {args.threads} thread(s), SG-D3QN, 10 humans; planning d={args.depth} "
               f"w={args.width}, learned predictor; target: planning ≤ 3× greedy Q")


if __name__ == "__main__":
    main()
