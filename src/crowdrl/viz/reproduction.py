"""The reproduction's figures: learning curves over seeds, the interval plot, ORCA and the first
method side by side on test case 0, and a GIF of that episode."""

from __future__ import annotations

import json
from typing import Any

from crowdrl.reproduction.plan import DEFAULT_ENCODER, Plan


def write_figures(plan: Plan, rows: list[dict[str, Any]]) -> None:
    """Learning curves over seeds, the interval plot, ORCA vs the first variant on test case 0."""
    from crowdrl.training.pipeline import evaluate_spec
    from crowdrl.viz import animate_trajectory, plot_intervals, plot_seed_curves, plot_side_by_side

    curves = {}
    for method in plan.methods:
        curves[method.name] = []
        for seed in plan.seeds:
            path = plan.run_dir(method, seed) / "scalars.jsonl"
            curves[method.name].append([json.loads(line) for line in path.read_text().splitlines() if line.strip()])
    arch = "SG-D3QN" if plan.encoders == (DEFAULT_ENCODER,) else ", ".join(plan.encoders)
    plot_seed_curves(curves, plan.out / "curves.png", title=f"{arch} on {plan.train_scenario}, budget {plan.budget}")
    plot_intervals(rows, plan.out / "intervals.png", title=f"test success over seeds, budget {plan.budget}")
    first = plan.methods[0]
    agent_dir = plan.run_dir(first, plan.seeds[0])
    scenario = plan.scenarios[0]
    if not (agent_dir / "checkpoints" / "best.pt").exists():  # a clone holds the runs' records, not checkpoints
        print(f"no checkpoint in {agent_dir}: side_by_side.png and the GIF are left as they are", flush=True)
        return
    _, orca = evaluate_spec(policy="orca", scenario=scenario, episodes=1, record_episode=0)
    _, agent = evaluate_spec(checkpoint=agent_dir, scenario=scenario, episodes=1, record_episode=0)
    label = f"SG-D3QN + {first.variant}" if first.encoder == DEFAULT_ENCODER else f"{first.encoder} + {first.variant}"
    plot_side_by_side([orca, agent], ["ORCA", f"{label} (seed {plan.seeds[0]})"],
                      plan.out / "side_by_side.png", suptitle=f"{scenario} test case 0")
    animate_trajectory(agent, plan.out / f"{first.name.replace('+', '-')}_s{plan.seeds[0]}_{scenario}_case0.gif")
