"""The reproduction's figures: learning curves over seeds, the interval plot, ORCA and the first
method side by side on test case 0, and a GIF of that episode. Figures take results: the runs'
``scalars.jsonl``, the table's rows and recorded trajectories; they run no evaluation."""

from __future__ import annotations

from typing import Any

from crowdrl.evaluation.trajectory import Trajectory
from crowdrl.files import read_json_lines
from crowdrl.reproduction.plan import DEFAULT_ENCODER, Plan


def write_figures(plan: Plan, rows: list[dict[str, Any]], case0: tuple[Trajectory, Trajectory] | None = None) -> None:
    """Learning curves over seeds, the interval plot and, given ``case0`` (ORCA's and the first method's
    first seed's recorded test case 0 of the first scenario), the two side by side and the agent's GIF."""
    from crowdrl.viz import animate_trajectory, plot_intervals, plot_seed_curves, plot_side_by_side

    curves = {}
    for method in plan.methods:
        curves[method.name] = []
        for seed in plan.seeds:
            path = plan.run_dir(method, seed) / "scalars.jsonl"
            curves[method.name].append(read_json_lines(path))
    arch = "SG-D3QN" if plan.encoders == (DEFAULT_ENCODER,) else ", ".join(plan.encoders)
    plot_seed_curves(curves, plan.out / "curves.png", title=f"{arch} on {plan.train_scenario}, budget {plan.budget}")
    plot_intervals(rows, plan.out / "intervals.png", title=f"test success over seeds, budget {plan.budget}")
    if case0 is None:
        return
    orca, agent = case0
    first, scenario = plan.methods[0], plan.scenarios[0]
    label = f"SG-D3QN + {first.variant}" if first.encoder == DEFAULT_ENCODER else f"{first.encoder} + {first.variant}"
    plot_side_by_side([orca, agent], ["ORCA", f"{label} (seed {plan.seeds[0]})"],
                      plan.out / "side_by_side.png", suptitle=f"{scenario} test case 0")
    animate_trajectory(agent, plan.out / f"{first.name.replace('+', '-')}_s{plan.seeds[0]}_{scenario}_case0.gif")
