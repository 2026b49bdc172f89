"""Acting cost per env-step with and without online planning (issue 13's target: planning ≤ 3×).

    python experiments/bench_planning.py                          # B = 256 and 1024, d = 1, w = 10
    python experiments/bench_planning.py --num-envs 256 --depth 2 --width 5 --json

For each batch size ``B``, in one process and one thread: the acting policy of training (the
plain greedy Q actor, or the :class:`~crowdrl.policies.OnlinePlanner` with a learned predictor,
each followed by ε-greedy) on ``B`` circle episodes of SG-D3QN with 10 humans. Two costs per
env-step: the policy alone (``policy``, one call on a ``[B]`` tensordict, no gradient) and a
collection step (``act+step``: the policy, then the env's step with ORCA humans and the
robot-centric transform, as a collector pays per frame). Untrained networks: the cost does not
depend on the weights. Medians over ``--repeats`` timed runs after a warm-up (which also
compiles the pairwise attention kernels).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def build(num_envs: int, planning: bool, depth: int, width: int):
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import TransformedEnv
    from torchrl.modules import EGreedyModule

    from crowdrl.envs import CrowdNavEnv, RobotCentric
    from crowdrl.models import make_q_actor, make_q_network
    from crowdrl.models.predictor import make_predictor
    from crowdrl.policies import OnlinePlanner

    torch.manual_seed(0)
    env = TransformedEnv(CrowdNavEnv("circle", num_envs=num_envs, seed=0), RobotCentric())
    net = make_q_network("sgd3qn")
    if planning:
        actor = OnlinePlanner(net, make_predictor("learned", env.base_env.config.time_step), env.base_env.config,
                              gamma=0.9 ** 0.25, depth=depth, width=width)
    else:
        actor = make_q_actor("sgd3qn", env.action_spec, net=net)
    policy = TensorDictSequential(actor, EGreedyModule(env.action_spec, eps_init=0.1, eps_end=0.1))
    return env, policy


def time_it(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(num_envs: int, planning: bool, depth: int, width: int, repeats: int, steps: int) -> dict:
    env, policy = build(num_envs, planning, depth, width)
    td = env.reset()
    with torch.no_grad():
        for _ in range(3):  # warm-up (kernel compilation, allocator)
            policy(td.clone())

        def collect():
            nonlocal td
            for _ in range(steps):
                td = env.step_and_maybe_reset(policy(td))[1]

        collect()
        policy_s = time_it(lambda: policy(td.clone()), repeats)
        step_s = time_it(collect, max(1, repeats // 4)) / steps
    return {"num_envs": num_envs, "planning": planning, "depth": depth if planning else 0,
            "width": width if planning else 0, "policy_us_per_env_step": policy_s / num_envs * 1e6,
            "act_step_us_per_env_step": step_s / num_envs * 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--depth", type=int, default=1)
    parser.add_argument("--width", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--steps", type=int, default=5, help="collection steps per timed run")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", action="store_true", help="print the rows as JSON instead of a table")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for n in args.num_envs:
        plain = measure(n, False, args.depth, args.width, args.repeats, args.steps)
        plan = measure(n, True, args.depth, args.width, args.repeats, args.steps)
        for key in ("policy_us_per_env_step", "act_step_us_per_env_step"):
            plan[key.replace("_us_per_env_step", "_ratio")] = plan[key] / plain[key]
        rows += [plain, plan]
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    print(f"acting cost per env-step (µs), {args.threads} thread(s), SG-D3QN, 10 humans; planning d={args.depth} "
          f"w={args.width}, learned predictor")
    print("| B | policy | policy µs | act+step µs | policy ratio | act+step ratio |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        name = f"planning d={r['depth']} w={r['width']}" if r["planning"] else "greedy Q"
        ratios = (f"{r['policy_ratio']:.2f}×", f"{r['act_step_ratio']:.2f}×") if r["planning"] else ("1", "1")
        print(f"| {r['num_envs']} | {name} | {r['policy_us_per_env_step']:.1f} | {r['act_step_us_per_env_step']:.1f} "
              f"| {ratios[0]} | {ratios[1]} |")


if __name__ == "__main__":
    main()
