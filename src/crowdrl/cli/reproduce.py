"""The paper's table with one command: train the exploration variants (of SG-D3QN, or of any
encoders) over seeds at a named budget, test every best checkpoint on circle and square (1000 cases each), run ORCA on the
same cases, and write ``table.md`` (+ ``.json``, ``.csv``) with 95 % confidence intervals over
seeds (rliable), the paper's values and each variant's probability of improving on ε-greedy,
next to the figures (learning curves over seeds, interval plot, ORCA and the agent side by side,
a GIF of a test episode).

Run as ``crowdrl-reproduce``, ``python -m crowdrl.cli.reproduce`` or, in a checkout, ``python experiments/reproduce.py``:

    python experiments/reproduce.py budget=smoke 'variants=[egreedy,re3]' 'seeds=[0,1]' out=/tmp/repro
    python experiments/reproduce.py budget=demo jobs=2          # SG-D3QN with its online planning, 5 variants
    python experiments/reproduce.py budget=demo planning=false train_learner=plain jobs=2 out=results/demo   # results/demo/
    python experiments/reproduce.py budget=paper launcher=slurm # the runs as SLURM jobs (submitit)
    python experiments/reproduce.py budget=demo 'encoders=[sarl,lstm_rl,mp_rgl]' 'variants=[egreedy,icm]'

Every run is an independent Hydra job (``python -m crowdrl.cli.train``, with this interpreter and in the
current directory) in ``<out>/runs/<variant>-s<seed>`` (SG-D3QN) or ``<out>/runs/<encoder>-<variant>-s<seed>``; its method
is ``<variant>`` or
``<encoder>+<variant>``, compared with the ε-greedy run of the same encoder.
A rerun skips finished runs and resumes killed ones from their last checkpoint; a folder made by
another budget, test-case count or code version is refused, and so is one reproduce.py did not make
(it holds files but no ``manifest.json``) or ``out=''``. Finished runs' records (not their
checkpoints) are kept in git, so a clone rebuilds the table and curves without training.

This module launches the runs; the plan is :mod:`crowdrl.reproduction.plan`, the table
:mod:`crowdrl.reproduction.table`, the figures :mod:`crowdrl.viz.reproduction`.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from crowdrl.cli import exit_with_error, hydra_command
# the plan's names are this module's too (experiments/reproduce.py and the tests use them from here)
from crowdrl.reproduction.plan import (BUDGETS, COUNTERFACTUAL_OFF, DEFAULT_ENCODER, KEYS, LAUNCHERS,  # noqa: F401
                                       MANIFEST_FORMAT, Method, Plan, PlanError, check_budget_of_new_runs, check_manifest,
                                       check_out, check_runs, eval_path, has_eval, is_trained, make_plan, run_overrides)

TRAIN = [sys.executable, "-m", "crowdrl.cli.train"]  # the training runs: this interpreter, crowdrl's own train


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


# ----------------------------------------------------------------------------- jobs


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
    from crowdrl.agents import evaluate_spec

    with EVAL_LOCK:
        record, _ = evaluate_spec(checkpoint=checkpoint, policy=policy, scenario=scenario, episodes=episodes)
    write_records(folder, [record])


def reuse_training_test(run_dir: Path, scenario: str, episodes: int) -> bool:
    """The training run already tested its best checkpoint on its own scenario (test seed 0): copy
    that record instead of evaluating the same cases again. False when it does not match."""
    from crowdrl.evaluation import EpisodeMetrics
    from crowdrl.evaluation.report import eval_record, read_summary, write_records
    from crowdrl.training.compat import stored_config
    from crowdrl.training.config import trained_on
    from crowdrl.training.pipeline import TEST_SEED, policy_name
    from crowdrl.training.validation import validate

    summary = run_dir / "summary.json"
    config = run_dir / "config.yaml"
    if not (summary.exists() and config.exists()):
        return False
    test = read_summary(summary)["test"]
    # typed, as a checkpoint's config is read: keys a folder predates (env.mix, ...) at what it ran with
    run = validate(stored_config(OmegaConf.load(config)), resources=False)
    if test.get("test_seed") != TEST_SEED or run.env.scenario != scenario or test["metrics"]["episodes"] != episodes:
        return False
    metrics = EpisodeMetrics(**test["metrics"])
    write_records(eval_path(run_dir, scenario).parent,
                  [eval_record(metrics, scenario=scenario, seed=TEST_SEED,
                               policy=policy_name(run),
                               checkpoint=str(run_dir / "checkpoints" / "best.pt"),
                               checkpoint_frames=test.get("checkpoint_frames"), train_scenario=trained_on(run),
                               train_seed=run.seed, reused_from="summary.json")])
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


def measure_gaps(plan: Plan) -> None:
    """With ``ceiling=``: each run's (and ORCA's) gap to the ceiling on each scenario that has a ceiling file,
    as ``gap.json`` beside its ``eval.json`` (the same cases evaluated again with the file: the per-case outcomes
    are not in the records); existing ones are kept."""
    from crowdrl.reproduction.table import gap_path
    from crowdrl.evaluation.report import write_records
    from crowdrl.agents import evaluate_spec

    for scenario in plan.scenarios:
        file = plan.ceiling_file(scenario)
        if file is None:
            continue
        targets = [(eval_path(plan.run_dir(m, s), scenario), {"checkpoint": plan.run_dir(m, s)})
                   for m in plan.methods for s in plan.seeds]
        targets.append((plan.out / "orca" / f"eval-{scenario}" / "eval.json", {"policy": "orca"}))
        for path, what in targets:
            if gap_path(path).exists():
                continue
            with EVAL_LOCK:
                record, _ = evaluate_spec(**what, scenario=scenario, episodes=plan.episodes, record_episode=None,
                                          ceiling=file)
            write_records(path.parent, [record], stem="gap")
            print(f"  gap: {path.parent} ({record['avoidable_failures']} avoidable failures)", flush=True)


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


# ----------------------------------------------------------------------------- main


def reproduce(plan: Plan) -> dict[str, Any]:
    import torch

    start = time.perf_counter()
    torch.set_num_threads(plan.threads)
    check_runs(plan)
    check_out(plan)  # a folder reproduce.py did not make is refused, before the lock writes .lock into it
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
    check_budget_of_new_runs(plan, [(m, s) for m, s in pending if not is_trained(plan.run_dir(m, s))])
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
    from crowdrl.reproduction.table import add_gaps, collect, launch_mode, recorded_wall, table_rows, write_table
    from crowdrl.viz.reproduction import write_figures

    measure_gaps(plan)
    rows = table_rows(plan, collect(plan))
    wall_s = time.perf_counter() - start
    # a call that trained nothing keeps the wall-clock of the call that did, and how it launched its runs
    # (recorded in table.json), not its own jobs=
    write_table(plan, add_gaps(plan, rows), *((wall_s, launch_mode(plan)) if pending else recorded_wall(plan)))
    write_figures(plan, rows, case0_trajectories(plan))
    return {"rows": rows, "wall_s": wall_s, "trained": len(pending)}


def case0_trajectories(plan):
    """ORCA's and the first method's (first seed) recorded test case 0 of the first scenario, for the figures;
    ``None`` where the run folder holds no checkpoint (a clone holds the runs' records, not checkpoints)."""
    from crowdrl.agents import evaluate_spec

    agent_dir = plan.run_dir(plan.methods[0], plan.seeds[0])
    if not (agent_dir / "checkpoints" / "best.pt").exists():
        print(f"no checkpoint in {agent_dir}: side_by_side.png and the GIF are left as they are", flush=True)
        return None
    _, orca = evaluate_spec(policy="orca", scenario=plan.scenarios[0], episodes=1, record_episode=0)
    _, agent = evaluate_spec(checkpoint=agent_dir, scenario=plan.scenarios[0], episodes=1, record_episode=0)
    return orca, agent


def _register_schema() -> None:
    """The typed schema of ``conf/reproduce.yaml`` (its defaults list's ``reproduce_schema``): Hydra
    refuses an unknown key or a value of the wrong type, naming it."""
    from hydra.core.config_store import ConfigStore

    from crowdrl.reproduction.config import ReproduceConfig

    ConfigStore.instance().store(name="reproduce_schema", node=ReproduceConfig)


_register_schema()


def allowed_hint(key: str = "") -> str:
    """The keys reproduce.py reads (its schema's), for its messages."""
    from crowdrl.reproduction.config import ReproduceConfig
    from crowdrl.schema import allowed_keys

    return ", ".join(allowed_keys(ReproduceConfig))

# the default out= names the learner: results/<budget>[-planning][-counterfactual][-polyak][-lidar-<kind>]
if not OmegaConf.has_resolver("crowdrl_learner_suffix"):
    from crowdrl.reproduction.plan import learner_suffix

    OmegaConf.register_new_resolver("crowdrl_learner_suffix", learner_suffix)
if not OmegaConf.has_resolver("crowdrl_planning_suffix"):
    OmegaConf.register_new_resolver("crowdrl_planning_suffix", lambda planning: "-planning" if planning is True else "")
if not OmegaConf.has_resolver("crowdrl_lidar_suffix"):  # -lidar-<kind> when the networks read the scan
    OmegaConf.register_new_resolver("crowdrl_lidar_suffix", lambda lidar: "" if lidar == "off" else f"-lidar-{lidar}")


@hydra_command("reproduce", "reproduce", allowed=allowed_hint)
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
