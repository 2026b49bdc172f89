"""The paper's table with one command: train the exploration variants (of SG-D3QN, or of any
encoders) over seeds at a named budget, test every best checkpoint on circle and square (1000 cases each), run ORCA on the
same cases, and write ``table.md`` (+ ``.json``, ``.csv``) with 95 % confidence intervals over
seeds (rliable), the paper's values and each variant's probability of improving on ε-greedy,
next to the figures (learning curves over seeds, interval plot, ORCA and the agent side by side,
a GIF of a test episode).

Run as ``crowdrl-reproduce``, ``python -m crowdrl.cli.reproduce`` or, in a checkout, ``python experiments/reproduce.py``:

    python experiments/reproduce.py budget=smoke 'variants=[egreedy,re3]' 'seeds=[0,1]' out=/tmp/repro
    python experiments/reproduce.py budget=demo jobs=2          # SG-D3QN with its online planning, 5 variants
    python experiments/reproduce.py budget=demo planning=false jobs=2 out=results/demo   # without (results/demo/)
    python experiments/reproduce.py budget=paper launcher=slurm # the runs as SLURM jobs (submitit)
    python experiments/reproduce.py budget=demo 'encoders=[sarl,lstm_rl,mp_rgl]' 'variants=[egreedy,icm]'

Every run is an independent Hydra job (``python -m crowdrl.cli.train``, with this interpreter and in the
current directory) in ``<out>/runs/<variant>-s<seed>`` (SG-D3QN) or ``<out>/runs/<encoder>-<variant>-s<seed>``; its method
is ``<variant>`` or
``<encoder>+<variant>``, compared with the ε-greedy run of the same encoder.
A rerun skips finished runs and resumes killed ones from their last checkpoint; a folder made by
another budget, test-case count or code version is refused. Finished runs' records (not their
checkpoints) are kept in git, so a clone rebuilds the table and curves without training.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from crowdrl.cli import exit_with_error, hydra_command
from crowdrl.resources import config_dir
from crowdrl.tables import interval_cell, markdown_table

CONF_DIR = str(config_dir())
BUDGETS = tuple(sorted(p.stem for p in (config_dir() / "preset").glob("*.yaml")))  # conf/preset/<budget>.yaml
TRAIN = [sys.executable, "-m", "crowdrl.cli.train"]  # the training runs: this interpreter, crowdrl's own train
LAUNCHERS = ("local", "slurm")
MANIFEST_FORMAT = 1
METRICS = ("success_rate", "collision_rate", "navigation_time", "average_return")
KEYS = {"budget", "encoders", "variants", "seeds", "train_scenario", "scenarios", "episodes", "jobs", "launcher",
        "threads", "reps", "out", "planning", "counterfactual"}
COUNTERFACTUAL_OFF = {"mode": "off", "actions": "topk", "k": 5, "weight": 0.5}  # train.counterfactual's defaults


class PlanError(ValueError):
    """A reproduce.py setting is unknown or out of range."""


DEFAULT_ENCODER = "sgd3qn"  # the paper's architecture: its runs and rows are named by the variant alone


@dataclass(frozen=True)
class Method:
    """One architecture and exploration variant: a row of the table."""

    encoder: str
    variant: str

    @property
    def name(self) -> str:
        return self.variant if self.encoder == DEFAULT_ENCODER else f"{self.encoder}+{self.variant}"

    @property
    def baseline(self) -> "Method":
        """The ε-greedy method of the same encoder, which the variant is compared with."""
        return Method(self.encoder, "egreedy")


@dataclass(frozen=True)
class Plan:
    budget: str
    encoders: tuple[str, ...]
    variants: tuple[str, ...]
    seeds: tuple[int, ...]
    train_scenario: str
    scenarios: tuple[str, ...]
    episodes: int
    jobs: int
    launcher: str
    threads: int
    reps: int
    out: Path
    planning: bool = True  # every run acts with SG-D3QN's online planning (planning.enabled), as the paper's did
    counterfactual: tuple[tuple[str, Any], ...] = tuple(COUNTERFACTUAL_OFF.items())  # every run's train.counterfactual

    @property
    def methods(self) -> tuple[Method, ...]:
        return tuple(Method(e, v) for e in self.encoders for v in self.variants)

    def run_dir(self, method: Method, seed: int) -> Path:
        return self.out / "runs" / f"{method.name.replace('+', '-')}-s{seed}"

    def manifest(self) -> dict[str, Any]:
        import crowdrl

        out = {"format": MANIFEST_FORMAT, "crowdrl_version": crowdrl.__version__, "budget": self.budget,
               "train_scenario": self.train_scenario, "episodes": self.episodes}
        return {**out, "planning": self.planning, "counterfactual": dict(self.counterfactual)}


def make_plan(cfg: dict[str, Any]) -> Plan:
    """Validate the settings (each error names its key)."""
    from crowdrl.models import ENCODERS
    from crowdrl.sim.config import SCENARIOS
    from crowdrl.sim.rng import MAX_SEED
    from crowdrl.training.config import EXPLORATIONS

    unknown = sorted(set(cfg) - KEYS)
    if unknown:
        raise PlanError(f"unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(KEYS))}")

    def names(key: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
        value = cfg[key]
        if isinstance(value, str) or not value:
            raise PlanError(f"{key}: give a non-empty list, e.g. {key}=[{allowed[0]}]")
        bad = [v for v in value if v not in allowed]
        if bad:
            raise PlanError(f"{key}: unknown {', '.join(map(str, bad))}; allowed: {', '.join(allowed)}")
        if len(set(value)) != len(value):
            raise PlanError(f"{key}: listed twice: {value}")
        return tuple(value)

    def integer(key: str, low: int) -> int:
        value = cfg[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise PlanError(f"{key}: must be an integer >= {low}, got {value!r}")
        return value

    if cfg["budget"] not in BUDGETS:
        raise PlanError(f"budget: unknown {cfg['budget']!r}; allowed: {', '.join(BUDGETS)}")
    if cfg["launcher"] not in LAUNCHERS:
        raise PlanError(f"launcher: unknown {cfg['launcher']!r}; allowed: {', '.join(LAUNCHERS)}")
    if cfg["train_scenario"] not in SCENARIOS:
        raise PlanError(f"train_scenario: unknown {cfg['train_scenario']!r}; allowed: {', '.join(SCENARIOS)}")
    seeds = cfg["seeds"]
    if isinstance(seeds, (int, str)) or not seeds:
        raise PlanError("seeds: give a non-empty list, e.g. seeds=[0,1,2]")
    if (any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= MAX_SEED for s in seeds)
            or len(set(seeds)) != len(seeds)):
        raise PlanError(f"seeds: must be distinct integers in 0..2**63-1, got {seeds}")
    planning = cfg.get("planning", True)
    if not isinstance(planning, bool):
        raise PlanError(f"planning: must be true or false, got {planning!r}")
    counterfactual = cfg.get("counterfactual") or {}
    if not isinstance(counterfactual, dict) or set(counterfactual) - set(COUNTERFACTUAL_OFF):
        raise PlanError(f"counterfactual: give train.counterfactual's keys ({', '.join(COUNTERFACTUAL_OFF)}), e.g. "
                        f"counterfactual.mode=second_update; got {counterfactual!r}")
    counterfactual = {**COUNTERFACTUAL_OFF, **counterfactual}
    return Plan(counterfactual=tuple(counterfactual.items()), planning=planning, budget=cfg["budget"],
                encoders=names("encoders", tuple(sorted(ENCODERS))),
                variants=names("variants", EXPLORATIONS), seeds=tuple(seeds),
                train_scenario=cfg["train_scenario"], scenarios=names("scenarios", SCENARIOS),
                episodes=integer("episodes", 1), jobs=integer("jobs", 1), launcher=cfg["launcher"],
                threads=integer("threads", 1), reps=integer("reps", 100), out=Path(cfg["out"]))


def check_runs(plan: Plan) -> None:
    """Validate every method's run configuration (what ``train.py`` will be given, memory bounds
    included) before anything is trained or written; an error names the method and the key."""
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from hydra.core.global_hydra import GlobalHydra

    from crowdrl.training.config import ConfigError, RunConfig
    from crowdrl.training.resolvers import register_resolvers
    from crowdrl.training.validation import validate

    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    register_resolvers()
    for method in plan.methods:
        overrides = [*run_overrides(plan, method), f"seed={plan.seeds[0]}"]
        if GlobalHydra.instance().is_initialized():  # inside main(): Hydra already reads conf/
            cfg = compose(config_name="config", overrides=overrides)
        else:
            with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
                cfg = compose(config_name="config", overrides=overrides)
        try:
            validate(cfg)
        except ConfigError as exc:
            raise PlanError(f"the {method.name} runs ({' '.join(overrides)}): {exc}") from None


def lock_out(plan: Plan):
    """An exclusive lock on ``<out>/.lock`` (released when this process exits, even on a kill): a
    second reproduce.py on the same ``out=`` is refused before it writes anything."""
    from crowdrl.training.run_folder import RunFolderBusy
    from crowdrl.training.pipeline import lock_run_dir

    try:
        return lock_run_dir(plan.out)
    except RunFolderBusy:
        raise PlanError(f"out: {plan.out} is being written by another reproduce.py (it holds {plan.out / '.lock'}); "
                        f"wait for it to end, or pass another out=<folder>") from None


def check_manifest(plan: Plan) -> None:
    """Refuse to mix results of another budget, test-case count or code version in one folder."""
    path = plan.out / "manifest.json"
    want = plan.manifest()
    if path.exists():
        have = json.loads(path.read_text())
        have.setdefault("planning", False)  # folders made before the key trained without planning
        have.setdefault("counterfactual", COUNTERFACTUAL_OFF)  # ... and without counterfactual experience
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        if diff:
            said = ", ".join(f"{k}: folder {a!r} vs now {b!r}" for k, (a, b) in diff.items())
            raise PlanError(f"out: {plan.out} holds results made with other settings ({said}); "
                            f"pass a fresh out=<folder> or delete {plan.out} to start again")
        return
    from crowdrl.files import atomic_write_json

    atomic_write_json(path, want)


# ----------------------------------------------------------------------------- jobs


def run_overrides(plan: Plan, method: Method) -> list[str]:
    """The Hydra overrides of one training run (its seed and folder are added by the launcher)."""
    return [f"preset={plan.budget}", f"encoder={method.encoder}", f"exploration={method.variant}",
            f"env={plan.train_scenario}", "logger=csv", "logger.progress_bar=false", "logger.render=false",
            f"train.test_episodes={plan.episodes}", f"threads={plan.threads}",
            f"planning.enabled={str(plan.planning).lower()}",
            *[f"train.counterfactual.{k}={v}" for k, v in plan.counterfactual
              if dict(plan.counterfactual)["mode"] != "off"]]


def is_trained(run_dir: Path) -> bool:
    status = run_dir / "status.json"
    return status.exists() and json.loads(status.read_text()).get("state") == "completed"


def eval_path(run_dir: Path, scenario: str) -> Path:
    return run_dir / f"eval-{scenario}" / "eval.json"


def has_eval(path: Path, episodes: int) -> bool:
    from crowdrl.evaluation.report import read_eval_record

    return path.exists() and read_eval_record(path)["episodes"] == episodes


def _run(cmd: list[str], log: Path) -> None:
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a", encoding="utf-8") as f:
        f.write(f"\n$ {' '.join(cmd)}\n")
        f.flush()
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)  # in this process's directory, as out= is
    if proc.returncode != 0:
        raise RuntimeError(f"exit {proc.returncode}: {' '.join(cmd[1:4])} ... (log: {log})")


EVAL_LOCK = threading.Lock()  # evaluations run in this process, one at a time (torchrl keeps global state)


def evaluate_into(folder: Path, *, checkpoint: Path | None = None, policy: str | None = None, scenario: str,
                  episodes: int) -> None:
    """Test a checkpoint or a baseline on ``episodes`` cases (test seed 0) and write ``folder/eval.json``
    (in this process, while other runs train in theirs: the evaluation is short next to training)."""
    from crowdrl.evaluation.report import write_records
    from crowdrl.training.pipeline import evaluate_spec

    with EVAL_LOCK:
        record, _ = evaluate_spec(checkpoint=checkpoint, policy=policy, scenario=scenario, episodes=episodes)
    write_records(folder, [record])


def reuse_training_test(run_dir: Path, scenario: str, episodes: int) -> bool:
    """The training run already tested its best checkpoint on its own scenario (test seed 0): copy
    that record instead of evaluating the same cases again. False when it does not match."""
    from crowdrl.evaluation import EpisodeMetrics
    from crowdrl.evaluation.report import eval_record, read_summary, write_records
    from crowdrl.training.pipeline import TEST_SEED

    summary = run_dir / "summary.json"
    config = run_dir / "config.yaml"
    if not (summary.exists() and config.exists()):
        return False
    test = read_summary(summary)["test"]
    run_cfg = OmegaConf.load(config)
    if test.get("test_seed") != TEST_SEED or run_cfg.env.scenario != scenario or test["metrics"]["episodes"] != episodes:
        return False
    metrics = EpisodeMetrics(**test["metrics"])
    write_records(eval_path(run_dir, scenario).parent,
                  [eval_record(metrics, scenario=scenario, seed=TEST_SEED,
                               policy=f"{run_cfg.encoder.name}+{run_cfg.exploration.name}"
                               + ("+planning" if OmegaConf.select(run_cfg, "planning.enabled", default=False) else ""),
                               checkpoint=str(run_dir / "checkpoints" / "best.pt"),
                               checkpoint_frames=test.get("checkpoint_frames"), train_scenario=run_cfg.env.scenario,
                               train_seed=int(run_cfg.seed), reused_from="summary.json")])
    return True


def train_and_evaluate(plan: Plan, method: Method, seed: int) -> None:
    """One run: train (resuming a killed run from its last checkpoint), then every test scenario."""
    run_dir = plan.run_dir(method, seed)
    log = run_dir.parent / f"{run_dir.name}.log"
    if not is_trained(run_dir):
        _run([*TRAIN, *run_overrides(plan, method), f"seed={seed}",
              f"hydra.run.dir={run_dir}"], log)
    evaluate_run(plan, run_dir)


def evaluate_run(plan: Plan, run_dir: Path) -> None:
    for scenario in plan.scenarios:
        path = eval_path(run_dir, scenario)
        if not has_eval(path, plan.episodes) and not reuse_training_test(run_dir, scenario, plan.episodes):
            evaluate_into(path.parent, checkpoint=run_dir, scenario=scenario, episodes=plan.episodes)


def launch_slurm(plan: Plan, pending: list[tuple[Method, int]]) -> None:
    """The pending runs as one Hydra multirun per method on the submitit SLURM launcher."""
    for method in plan.methods:
        seeds = [s for m, s in pending if m == method]
        if not seeds:
            continue
        prefix = "" if method.encoder == DEFAULT_ENCODER else "${encoder.name}-"
        _run([*TRAIN, "-m", "hydra/launcher=slurm",
              *run_overrides(plan, method), f"seed={','.join(map(str, seeds))}",
              f"hydra.sweep.dir={plan.out / 'runs'}", f"hydra.sweep.subdir={prefix}${{exploration.name}}-s${{seed}}"],
             plan.out / "runs" / f"slurm-{method.name.replace('+', '-')}.log")


# ----------------------------------------------------------------------------- table


def collect(plan: Plan) -> dict[str, Any]:
    """Every eval record: ``{method: {scenario: [record per seed]}}`` (ORCA: one record)."""
    from crowdrl.evaluation.report import read_eval_record

    records: dict[str, dict[str, list[dict]]] = {}
    for method in plan.methods:
        for scenario in plan.scenarios:
            records.setdefault(method.name, {})[scenario] = [
                read_eval_record(eval_path(plan.run_dir(method, s), scenario)) for s in plan.seeds]
    records["orca"] = {sc: [read_eval_record(plan.out / "orca" / f"eval-{sc}" / "eval.json")]
                       for sc in plan.scenarios}
    return records


def table_rows(plan: Plan, records: dict[str, Any]) -> list[dict[str, Any]]:
    """Per method and scenario: mean and 95 % CI over seeds of each metric, the paper's value,
    and P(improvement over the same encoder's ε-greedy) on success rate."""
    import numpy as np

    from crowdrl.evaluation.report import paper_value
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


def _cell(row: dict[str, Any], key: str, digits: int) -> str:
    """The mean over seeds with its interval (from two seeds on), then the paper's value if it has one."""
    text = interval_cell(row, key, digits, interval=row["seeds"] > 1)
    paper = row[f"{key}_paper"]
    return text if text == "–" or math.isnan(paper) else f"{text} ({paper:.{digits}f})"


TABLE_HEADER = ("method", "seeds", "success", "collision", "nav time (s)", "avg return", "P(improve on ε-greedy)")


def markdown(plan: Plan, rows: list[dict[str, Any]], wall_s: float | None) -> str:
    from crowdrl.evaluation.report import read_summary
    from crowdrl.sim.config import OPEN_SCENARIOS

    seeds = ", ".join(map(str, plan.seeds))
    what = ("SG-D3QN exploration variants" if plan.encoders == (DEFAULT_ENCODER,)
            else f"exploration variants of the encoders {', '.join(plan.encoders)}")
    planning = " with online planning" if plan.planning else ""
    transfer = [sc for sc in plan.scenarios if sc != plan.train_scenario]
    paper = " (paper, one seed)" if set(plan.scenarios) & set(OPEN_SCENARIOS) else ""  # the paper has open space only
    zero_shot = f"; {' and '.join(transfer)} {'is' if len(transfer) == 1 else 'are'} zero-shot" if transfer else ""
    lines = [f"# crowdrl reproduction: {what}{planning}, budget `{plan.budget}`",
             "",
             f"Trained on {plan.train_scenario} with seeds {seeds}; each best validation checkpoint tested on "
             f"{plan.episodes} cases per scenario (test seed 0{zero_shot}). Cells: mean over seeds "
             f"[95 % stratified-bootstrap CI, rliable, {plan.reps} resamples]{paper}. "
             "P(improve): probability that the variant's success rate beats ε-greedy's (same encoder) on a random "
             "pair of seeds "
             "[95 % CI]. ORCA is deterministic: one evaluation.",
             ""]
    run_minutes = [read_summary(plan.run_dir(m, s) / "summary.json")["wall_s"] / 60
                   for m in plan.methods for s in plan.seeds if (plan.run_dir(m, s) / "summary.json").exists()]
    if run_minutes:
        lines += [f"Training + validation + {plan.train_scenario} test per run (`summary.json`): {min(run_minutes):.1f}–"
                  f"{max(run_minutes):.1f} min."]
    if wall_s is not None:
        how = f"jobs={plan.jobs}" if plan.launcher == "local" else "launcher=slurm"
        lines += [f"Wall-clock of the `reproduce.py` call ({how}) that trained or tested the last runs: "
                  f"{wall_s / 60:.1f} min."]
    lines.append("")
    for scenario in plan.scenarios:
        cells = [[r["method"], r["seeds"], _cell(r, "success_rate", 3), _cell(r, "collision_rate", 3),
                  _cell(r, "navigation_time", 2), _cell(r, "average_return", 4), interval_cell(r, "p_improve", 2)]
                 for r in rows if r["scenario"] == scenario]
        lines += [f"## {scenario}", "", markdown_table(TABLE_HEADER, cells), ""]
    return "\n".join(lines)


def recorded_wall_s(plan: Plan) -> float | None:
    """The wall-clock ``table.json`` in ``out=`` records for the call that trained its last runs, if any."""
    path = plan.out / "table.json"
    if not path.exists():
        return None
    wall_s = json.loads(path.read_text()).get("wall_s")
    return float(wall_s) if isinstance(wall_s, (int, float)) else None


def write_table(plan: Plan, rows: list[dict[str, Any]], wall_s: float | None) -> None:
    import csv
    import io

    from crowdrl.files import atomic_write_bytes, atomic_write_json

    atomic_write_bytes(plan.out / "table.md", markdown(plan, rows, wall_s).encode())
    atomic_write_json(plan.out / "table.json", {"manifest": plan.manifest(), "seeds": list(plan.seeds),
                                                "wall_s": wall_s, "rows": rows})
    flat = [{k: v for k, v in r.items() if not k.endswith("_per_seed")} for r in rows]
    fields = list(dict.fromkeys(k for r in flat for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    writer.writerows(flat)
    atomic_write_bytes(plan.out / "table.csv", buf.getvalue().encode())


def write_figures(plan: Plan, rows: list[dict[str, Any]]) -> None:
    """Learning curves over seeds, the interval plot, ORCA vs the first variant on test case 0."""
    from crowdrl.training.pipeline import evaluate_spec
    from crowdrl.viz import plot_intervals, plot_seed_curves, plot_side_by_side

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
    from crowdrl.viz import animate_trajectory

    animate_trajectory(agent, plan.out / f"{first.name.replace('+', '-')}_s{plan.seeds[0]}_{scenario}_case0.gif")


# ----------------------------------------------------------------------------- main


def reproduce(plan: Plan) -> dict[str, Any]:
    import torch

    start = time.perf_counter()
    torch.set_num_threads(plan.threads)
    check_runs(plan)
    lock = lock_out(plan)  # before the first write: one reproduce.py per out folder
    try:
        return _reproduce(plan, start)
    finally:
        lock.release()


def _reproduce(plan: Plan, start: float) -> dict[str, Any]:
    check_manifest(plan)
    pending = [(m, s) for m in plan.methods for s in plan.seeds
               if not (is_trained(plan.run_dir(m, s)) and all(has_eval(eval_path(plan.run_dir(m, s), sc), plan.episodes)
                                                               for sc in plan.scenarios))]
    done = len(plan.methods) * len(plan.seeds) - len(pending)
    print(f"{len(pending)} run(s) to train or finish, {done} already done -> {plan.out}", flush=True)
    failures: list[str] = []
    if plan.launcher == "slurm" and pending:
        launch_slurm(plan, pending)  # blocks until the SLURM jobs end; evaluation follows here
    with ThreadPoolExecutor(max_workers=plan.jobs) as pool:
        jobs = {pool.submit(train_and_evaluate, plan, m, s): (m.name, s) for m, s in pending}
        jobs.update({pool.submit(evaluate_into, plan.out / "orca" / f"eval-{sc}", policy="orca", scenario=sc,
                                 episodes=plan.episodes): ("orca", sc)
                     for sc in plan.scenarios if not has_eval(plan.out / "orca" / f"eval-{sc}" / "eval.json",
                                                               plan.episodes)})
        for future, (what, which) in jobs.items():
            try:
                future.result()
                print(f"  done: {what} {which}", flush=True)
            except Exception as exc:  # keep the other runs going; report at the end
                print(f"  FAILED: {what} {which}:\n{traceback.format_exc()}", file=sys.stderr, flush=True)
                failures.append(f"{what} {which}: {exc!r}")
    if failures:
        raise RuntimeError("some runs failed (rerun to resume them):\n  " + "\n  ".join(failures))
    rows = table_rows(plan, collect(plan))
    wall_s = time.perf_counter() - start
    # a call that trained nothing keeps the wall-clock of the call that did (recorded in table.json)
    write_table(plan, rows, wall_s if pending else recorded_wall_s(plan))
    write_figures(plan, rows)
    return {"rows": rows, "wall_s": wall_s, "trained": len(pending)}


# the default out= keeps planning and plain tables apart: results/<budget>-planning, results/<budget>
if not OmegaConf.has_resolver("crowdrl_counterfactual_suffix"):
    OmegaConf.register_new_resolver("crowdrl_counterfactual_suffix",
                                    lambda mode: "" if mode in (None, "off") else "-counterfactual")
if not OmegaConf.has_resolver("crowdrl_planning_suffix"):
    OmegaConf.register_new_resolver("crowdrl_planning_suffix", lambda planning: "-planning" if planning is True else "")


@hydra_command("reproduce", "reproduce")
def main(cfg: DictConfig) -> None:
    from crowdrl.evaluation.report import RecordError

    try:
        plan = make_plan(OmegaConf.to_container(cfg, resolve=True))
        result = reproduce(plan)
    except (PlanError, RuntimeError, RecordError) as exc:  # RecordError: a record read back names file and field
        from crowdrl.training.run_folder import discard_new_folders

        discard_new_folders(cfg.out)  # the out= folder Hydra made for this call, and only while empty
        exit_with_error("reproduce", str(exc))
    print((plan.out / "table.md").read_text())
    print(f"{result['trained']} run(s) trained or finished in {result['wall_s'] / 60:.1f} min; "
          f"table, figures and runs in {plan.out.resolve()}")


if __name__ == "__main__":  # python -m crowdrl.cli.reproduce
    main()
