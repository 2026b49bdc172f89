"""The reproduction's table: per method and test scenario, the mean over seeds of each metric with
its 95 % interval (rliable), the paper's value and the probability of improving on ε-greedy, written
as ``table.md``, ``table.json`` and ``table.csv``."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from crowdrl.evaluation.report import paper_value, read_eval_record, read_run_eval_record, read_summary
from crowdrl.reproduction.plan import DEFAULT_ENCODER, Plan, eval_path
from crowdrl.tables import interval_cell, markdown_table
from crowdrl.training.config import MIX

METRICS = ("success_rate", "collision_rate", "navigation_time", "average_return")


def collect(plan: Plan) -> dict[str, Any]:
    """Every eval record: ``{method: {scenario: [record per seed]}}`` (ORCA: one record); a run's record of
    the test its ``summary.json`` holds too must agree with it (:func:`~crowdrl.evaluation.report.read_run_eval_record`)."""
    records: dict[str, dict[str, list[dict]]] = {}
    for method in plan.methods:
        for scenario in plan.scenarios:
            records.setdefault(method.name, {})[scenario] = [
                read_run_eval_record(eval_path(plan.run_dir(method, s), scenario), plan.run_dir(method, s))
                for s in plan.seeds]
    records["orca"] = {sc: [read_eval_record(plan.out / "orca" / f"eval-{sc}" / "eval.json")]
                       for sc in plan.scenarios}
    return records


def table_rows(plan: Plan, records: dict[str, Any]) -> list[dict[str, Any]]:
    """Per method and scenario: mean and 95 % CI over seeds of each metric, the paper's value,
    and P(improvement over the same encoder's ε-greedy) on success rate."""
    import numpy as np

    from crowdrl.evaluation.stats import mean_interval, probability_of_improvement

    baselines = {m.name: m.baseline.name for m in plan.methods}
    rows = []
    for scenario in plan.scenarios:
        for method, by_scenario in records.items():
            recs = by_scenario[scenario]
            row: dict[str, Any] = {"method": method, "scenario": scenario, "seeds": len(recs),
                                   "episodes": recs[0]["episodes"]}
            for key in METRICS:
                values = np.array([r[key] for r in recs], dtype=np.float64)
                mean, lo, hi = mean_interval({method: values}, reps=plan.reps)[method]
                row.update({key: mean, f"{key}_lo": lo, f"{key}_hi": hi, f"{key}_paper": paper_value(method, scenario, key),
                            f"{key}_per_seed": values.tolist()})
            base_name = baselines.get(method)
            if base_name is not None and base_name != method and base_name in records:
                base = np.array([r["success_rate"] for r in records[base_name][scenario]])
                ours = np.array([r["success_rate"] for r in recs])
                p, plo, phi = probability_of_improvement(ours, base, reps=plan.reps)
                row.update({"p_improve": p, "p_improve_lo": plo, "p_improve_hi": phi})
            rows.append(row)
    return rows


GAP_METRICS = ("avoidable_failures", "unavoidable_failures", "time_over_ceiling")


def gap_path(eval_json: Path) -> Path:
    """Where the gap record to the ceiling lives beside an eval record (``gap.json``)."""
    return eval_json.parent / "gap.json"


def add_gaps(plan: Plan, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``rows`` with the gap to the ceiling where every seed of a row has its ``gap.json`` (mean and 95 % CI over
    seeds of :data:`GAP_METRICS`), and a ``ceiling`` row per scenario with a ceiling file (its success and mean
    time); ``rows`` unchanged without ``plan.ceiling``."""
    import numpy as np

    from crowdrl.evaluation.ceiling import read_ceiling
    from crowdrl.evaluation.stats import mean_interval

    if plan.ceiling is None:
        return rows
    by_method = {m.name: m for m in plan.methods}
    out = []
    for scenario in plan.scenarios:
        file = plan.ceiling_file(scenario)
        for row in (r for r in rows if r["scenario"] == scenario):
            if file is not None:
                method = by_method.get(row["method"])
                evals = ([eval_path(plan.run_dir(method, s), scenario) for s in plan.seeds] if method is not None
                         else [plan.out / "orca" / f"eval-{scenario}" / "eval.json"])
                gaps = [gap_path(e) for e in evals]
                if all(g.exists() for g in gaps):
                    recs = [read_eval_record(g) for g in gaps]
                    for key in GAP_METRICS:
                        values = np.array([r[key] if r[key] is not None else np.nan for r in recs], dtype=np.float64)
                        mean, lo, hi = mean_interval({key: values}, reps=plan.reps)[key]
                        row = {**row, key: mean, f"{key}_lo": lo, f"{key}_hi": hi, f"{key}_per_seed": values.tolist()}
            out.append(row)
        if file is not None:
            c = read_ceiling(file)
            n = c.counts()
            out.append({"method": "ceiling", "scenario": scenario, "seeds": 1, "episodes": c.cases,
                        "success_rate": n["solved"] / c.cases, "navigation_time": c.mean_time(),
                        "unavoidable_failures": float(n["infeasible"]), "unknown": n["unknown"],
                        "ceiling_file": str(file)})
    return out


def _cell(row: dict[str, Any], key: str, digits: int) -> str:
    """The mean over seeds with its interval (from two seeds on), then the paper's value if it has one."""
    if key not in row:
        return "–"
    text = interval_cell(row, key, digits, interval=row["seeds"] > 1 and f"{key}_lo" in row)
    paper = row.get(f"{key}_paper", math.nan)
    return text if text == "–" or math.isnan(paper) else f"{text} ({paper:.{digits}f})"


TABLE_HEADER = ("method", "seeds", "success", "collision", "nav time (s)", "avg return", "P(improve on ε-greedy)")
GAP_HEADER = ("avoidable failures", "unavoidable", "time over ceiling (s)")


def launch_mode(plan: Plan) -> str:
    """How ``plan``'s runs are launched, as the table names it: ``jobs=<n>`` locally, else ``launcher=slurm``."""
    return f"jobs={plan.jobs}" if plan.launcher == "local" else f"launcher={plan.launcher}"


def markdown(plan: Plan, rows: list[dict[str, Any]], wall_s: float | None, wall_how: str | None = None) -> str:
    """``table.md``: what was run and how the cells read, then one table per test scenario. ``wall_s`` and
    ``wall_how`` (:func:`launch_mode`): the wall-clock of the call that trained or tested the last runs and
    how that call launched them (``None``: not recorded)."""
    from crowdrl.sim.config import OPEN_SCENARIOS

    seeds = ", ".join(map(str, plan.seeds))
    what = ("SG-D3QN exploration variants" if plan.encoders == (DEFAULT_ENCODER,)
            else f"exploration variants of the encoders {', '.join(plan.encoders)}")
    planning = " with online planning" if plan.planning else ""
    if plan.lidar[0] != "off":
        planning += f", reading the lidar scan ({plan.lidar[0]}, {plan.lidar[1]} rays)"
    mixed = plan.train_scenario == MIX  # trained on every scenario at once: none is zero-shot
    transfer = [] if mixed else [sc for sc in plan.scenarios if sc != plan.train_scenario]
    paper = " (paper, one seed)" if set(plan.scenarios) & set(OPEN_SCENARIOS) else ""  # the paper has open space only
    zero_shot = f"; {' and '.join(transfer)} {'is' if len(transfer) == 1 else 'are'} zero-shot" if transfer else ""
    lines = [f"# crowdrl reproduction: {what}{planning}, budget `{plan.budget}`",
             "",
             f"Trained on {'every scenario in one batch (env=mix)' if mixed else plan.train_scenario} with seeds "
             f"{seeds}; each best validation checkpoint tested on "
             f"{plan.episodes} cases per scenario (test seed 0{zero_shot}). Cells: mean over seeds "
             f"[95 % stratified-bootstrap CI, rliable, {plan.reps} resamples]{paper}. "
             "P(improve): probability that the variant's success rate beats ε-greedy's (same encoder) on a random "
             "pair of seeds "
             "[95 % CI]. ORCA is deterministic: one evaluation.",
             ""]
    summaries = [read_summary(plan.run_dir(m, s) / "summary.json")
                 for m in plan.methods for s in plan.seeds if (plan.run_dir(m, s) / "summary.json").exists()]
    # run_s: the whole run, resumes included; a summary written before it has wall_s, its last segment only
    run_minutes = [d.get("run_s", d["wall_s"]) / 60 for d in summaries]
    if run_minutes:
        older = sum("run_s" not in d for d in summaries)
        said = ("" if older == len(summaries) else
                "; every segment of a resumed run" + (f", but {older} recorded before `run_s`: their last segment"
                                                      if older else ""))
        lines += [f"Training + validation + {plan.train_scenario} test per run (`summary.json`{said}): "
                  f"{min(run_minutes):.1f}–{max(run_minutes):.1f} min."]
    if wall_s is not None:
        how = f" ({wall_how})" if wall_how else ""
        lines += [f"Wall-clock of the `reproduce.py` call{how} that trained or tested the last runs: "
                  f"{wall_s / 60:.1f} min."]
    lines.append("")
    for scenario in plan.scenarios:
        mine = [r for r in rows if r["scenario"] == scenario]
        gaps = any(r["method"] == "ceiling" for r in mine)
        cells = [[r["method"], r["seeds"], _cell(r, "success_rate", 3), _cell(r, "collision_rate", 3),
                  _cell(r, "navigation_time", 2), _cell(r, "average_return", 4), interval_cell(r, "p_improve", 2),
                  *((_cell(r, "avoidable_failures", 1), _cell(r, "unavoidable_failures", 1),
                     _cell(r, "time_over_ceiling", 2)) if gaps else ())] for r in mine]
        lines += [f"## {scenario}", "", markdown_table(TABLE_HEADER + (GAP_HEADER if gaps else ()), cells), ""]
        if gaps:
            c = next(r for r in mine if r["method"] == "ceiling")
            lines += [f"Ceiling: {c['ceiling_file']} (experiments/ceiling.py; {c['unknown']} cases unknown). Avoidable "
                      "failures: failed where a path exists; unavoidable: proven infeasible; time over the ceiling: "
                      "the mean over the cases both solve (docs/ceiling.md). A dash: no gap.json for every seed.", ""]
    return "\n".join(lines)


def recorded_wall(plan: Plan) -> tuple[float | None, str | None]:
    """The wall-clock ``table.json`` in ``out=`` records for the call that trained its last runs, and how
    that call launched them (``None`` where not recorded: tables written before ``wall_how``)."""
    path = plan.out / "table.json"
    if not path.exists():
        return None, None
    data = json.loads(path.read_text())
    wall_s, how = data.get("wall_s"), data.get("wall_how")
    return (float(wall_s) if isinstance(wall_s, (int, float)) else None), (how if isinstance(how, str) else None)


def write_table(plan: Plan, rows: list[dict[str, Any]], wall_s: float | None, wall_how: str | None = None) -> None:
    """``table.md``, ``table.json`` (with the manifest, the wall-clock and how that call launched its runs)
    and ``table.csv`` in ``out=``."""
    import csv
    import io

    from crowdrl.files import atomic_write_bytes, atomic_write_json

    atomic_write_bytes(plan.out / "table.md", markdown(plan, rows, wall_s, wall_how).encode())
    atomic_write_json(plan.out / "table.json", {"manifest": plan.manifest(), "seeds": list(plan.seeds),
                                                "wall_s": wall_s, "wall_how": wall_how, "rows": rows})
    flat = [{k: v for k, v in r.items() if not k.endswith("_per_seed")} for r in rows]
    fields = list(dict.fromkeys(k for r in flat for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    writer.writerows(flat)
    atomic_write_bytes(plan.out / "table.csv", buf.getvalue().encode())
