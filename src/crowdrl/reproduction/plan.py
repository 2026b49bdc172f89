"""A reproduction's plan: the methods (encoder x exploration variant) and seeds to train at a named
budget, checked before anything runs, and where each run's folder and test records live under ``out=``."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crowdrl.reproduction.config import ReproduceConfig
from crowdrl.resources import config_dir
from crowdrl.training.config import COUNTERFACTUAL_OFF, LEVERS_OFF, MIX

CONF_DIR = str(config_dir())
BUDGETS = tuple(sorted(p.stem for p in (config_dir() / "preset").glob("*.yaml")))  # conf/preset/<budget>.yaml
LAUNCHERS = ("local", "slurm")
MANIFEST_FORMAT = 1
OUT_MARKER = "manifest.json"  # written into out= under its lock by the first reproduce.py call: the folder is its own
KEYS = {f.name for f in dataclasses.fields(ReproduceConfig)}  # the settings' keys (the schema's)
# a manifest written before its counterfactual and levers keys: its runs trained without counterfactual
# experience and with every lever off (COUNTERFACTUAL_OFF, LEVERS_OFF: the plain learner, train's defaults then)
LIDAR_OFF = ("off", 0)  # (encoder.lidar, env.lidar_rays) of runs whose networks read no scan, and of manifests before it


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
    """The checked settings of one reproduction (:func:`make_plan`)."""

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
    levers: tuple[tuple[str, Any], ...] = ()  # every run's stability levers that differ from their defaults
    ceiling: Path | None = None  # a folder of ceiling files <scenario>.json (not in the manifest: added at any time)
    lidar: tuple[str, int] = LIDAR_OFF  # every run's (encoder.lidar, env.lidar_rays); off: no scan

    def lidar_overrides(self) -> list[str]:
        """``encoder.lidar=<kind>`` and ``env.lidar_rays=<R>`` when the runs read the scan (nothing when off: the
        runs' commands stay those recorded before the key)."""
        kind, rays = self.lidar
        return [] if kind == "off" else [f"encoder.lidar={kind}", f"env.lidar_rays={rays}"]

    def ceiling_file(self, scenario: str) -> Path | None:
        """The ceiling file of ``scenario`` in the ceiling folder (``None``: no folder, or no file for it)."""
        if self.ceiling is None:
            return None
        path = self.ceiling / f"{scenario}.json"
        return path if path.is_file() else None

    def lever_overrides(self) -> list[str]:
        """``train.<lever>=<value>``: ``target_tau`` always, each other lever this reproduction turns on."""
        def text(value: Any) -> str:
            return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)

        levers = {**LEVERS_OFF, **dict(self.levers)}  # target_tau always: the budget preset may select a learner
        return [f"train.{key}={text(value)}" for key, value in levers.items()
                if key == "target_tau" or value != LEVERS_OFF[key]]

    def counterfactual_overrides(self) -> list[str]:
        """``train.counterfactual.<key>=<value>``: the mode always (the budget preset may select a learner), and
        its settings when on."""
        counterfactual = dict(self.counterfactual)
        if counterfactual["mode"] == "off":
            return ["train.counterfactual.mode=off"]
        return [f"train.counterfactual.{k}={v}" for k, v in counterfactual.items()]

    @property
    def methods(self) -> tuple[Method, ...]:
        return tuple(Method(e, v) for e in self.encoders for v in self.variants)

    def run_dir(self, method: Method, seed: int) -> Path:
        return self.out / "runs" / f"{method.name.replace('+', '-')}-s{seed}"

    def manifest(self) -> dict[str, Any]:
        import crowdrl

        out = {"format": MANIFEST_FORMAT, "crowdrl_version": crowdrl.__version__, "budget": self.budget,
               "train_scenario": self.train_scenario, "episodes": self.episodes}
        return {**out, "planning": self.planning, "counterfactual": dict(self.counterfactual),
                "levers": {**LEVERS_OFF, **dict(self.levers)},
                "lidar": {"encoder": self.lidar[0], "rays": self.lidar[1]}}


def make_plan(cfg: dict[str, Any]) -> Plan:
    """Validate the settings (each error names its key): read into the typed schema
    (:class:`~crowdrl.reproduction.config.ReproduceConfig`: an unknown key, a value of the wrong type;
    keys left out take its defaults), then the allowed names and ranges."""
    from crowdrl.models import ENCODERS
    from crowdrl.schema import SchemaError, read_typed
    from crowdrl.sim.config import SCENARIOS
    from crowdrl.sim.rng import MAX_SEED
    from crowdrl.exploration.strategy import strategy_names

    try:
        s = read_typed(ReproduceConfig, cfg, reader="reproduce.py")
    except SchemaError as exc:
        raise PlanError(str(exc)) from None

    def names(key: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
        value = getattr(s, key)
        if not value:
            raise PlanError(f"{key}: give a non-empty list, e.g. {key}=[{allowed[0]}]")
        bad = [v for v in value if v not in allowed]
        if bad:
            raise PlanError(f"{key}: unknown {', '.join(map(str, bad))}; allowed: {', '.join(allowed)}")
        if len(set(value)) != len(value):
            raise PlanError(f"{key}: listed twice: {value}")
        return tuple(value)

    def at_least(key: str, low: int) -> int:
        value = getattr(s, key)
        if value < low:
            raise PlanError(f"{key}: must be an integer >= {low}, got {value!r}")
        return value

    if not s.out.strip():  # out='' (out=$DIR with DIR unset) would write into the current directory
        raise PlanError("out: is empty; give the folder for the table and its runs, e.g. out=results/mine")
    if s.budget not in BUDGETS:
        raise PlanError(f"budget: unknown {s.budget!r}; allowed: {', '.join(BUDGETS)}")
    if s.launcher not in LAUNCHERS:
        raise PlanError(f"launcher: unknown {s.launcher!r}; allowed: {', '.join(LAUNCHERS)}")
    if s.train_scenario not in (*SCENARIOS, MIX):
        raise PlanError(f"train_scenario: unknown {s.train_scenario!r}; allowed: {', '.join(SCENARIOS)}, {MIX} (every "
                        "scenario in one batch, conf/env/mix.yaml)")
    seeds = list(s.seeds)
    if not seeds:
        raise PlanError("seeds: give a non-empty list, e.g. seeds=[0,1,2]")
    if any(not 0 <= seed <= MAX_SEED for seed in seeds) or len(set(seeds)) != len(seeds):
        raise PlanError(f"seeds: must be distinct integers in 0..2**63-1, got {seeds}")
    from crowdrl.models.scan import SCAN_KINDS
    from crowdrl.sim.config import MAX_LIDAR_RAYS

    if s.lidar not in SCAN_KINDS:
        raise PlanError(f"lidar: unknown {s.lidar!r}; allowed: {', '.join(SCAN_KINDS)}")
    if s.lidar != "off" and not 1 <= s.lidar_rays <= MAX_LIDAR_RAYS:
        raise PlanError(f"lidar_rays: must be an integer in 1..{MAX_LIDAR_RAYS} when lidar={s.lidar}, got {s.lidar_rays}")
    counterfactual, lever_values = resolve_learner(s)
    levers = tuple((k, v) for k, v in lever_values.items() if v != LEVERS_OFF[k])
    scenarios = names("scenarios", SCENARIOS)
    ceiling = None if s.ceiling is None else Path(s.ceiling)
    if ceiling is not None:
        check_ceilings(ceiling, scenarios, s.episodes)
    return Plan(counterfactual=tuple(counterfactual.items()), levers=levers, planning=s.planning, budget=s.budget,
                ceiling=ceiling, lidar=(s.lidar, s.lidar_rays) if s.lidar != "off" else LIDAR_OFF,
                encoders=names("encoders", tuple(sorted(ENCODERS))),
                variants=names("variants", strategy_names()), seeds=tuple(seeds),
                train_scenario=s.train_scenario, scenarios=scenarios,
                episodes=at_least("episodes", 1), jobs=at_least("jobs", 1), launcher=s.launcher,
                threads=at_least("threads", 1), reps=at_least("reps", 100), out=Path(s.out))



def check_ceilings(folder: Path, scenarios: tuple[str, ...], episodes: int) -> None:
    """Refuse (naming ``ceiling``) a ceiling folder that is missing, holds no file for any test scenario, or
    holds one of another stream than the tests' (test seed 0, ``episodes`` cases, its scenario); each run's
    crowd is checked against the file when it is evaluated."""
    from crowdrl.evaluation.ceiling import read_ceiling

    if not folder.is_dir():
        raise PlanError(f"ceiling: {folder} is not a folder (give the folder of <scenario>.json ceiling files)")
    found = [sc for sc in scenarios if (folder / f"{sc}.json").is_file()]
    if not found:
        raise PlanError(f"ceiling: {folder} holds none of {', '.join(f'{sc}.json' for sc in scenarios)}")
    for sc in found:
        try:
            c = read_ceiling(folder / f"{sc}.json")
        except ValueError as exc:
            raise PlanError(f"ceiling: {exc}") from None
        asked = {"scenario": sc, "split": "test", "seed": 0, "cases": episodes}
        have = {"scenario": c.scenario, "split": c.split, "seed": c.seed, "cases": c.cases}
        for key in asked:
            if asked[key] != have[key]:
                raise PlanError(f"ceiling: {folder / f'{sc}.json'} has {key} {have[key]!r}; the tests' is {asked[key]!r}")


def resolve_learner(s: ReproduceConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Every run's ``train.counterfactual`` and stability levers: ``train_learner`` (null: the budget preset's,
    :func:`crowdrl.training.learners.learner_of_preset`) with the keys set one by one over it."""
    from crowdrl.training.learners import learner_of_preset, learner_settings

    if s.budget not in BUDGETS:
        raise PlanError(f"budget: unknown {s.budget!r}; allowed: {', '.join(BUDGETS)}")
    try:
        settings = learner_settings(s.train_learner if s.train_learner is not None else learner_of_preset(s.budget))
    except ValueError as exc:
        raise PlanError(f"train_{exc}") from None  # learner: unknown ... -> train_learner: unknown ...
    counterfactual = {**COUNTERFACTUAL_OFF, **settings["counterfactual"],
                      **{k: v for k, v in dataclasses.asdict(s.counterfactual).items() if k != "mode"}}
    if s.counterfactual.mode is not None:
        counterfactual["mode"] = s.counterfactual.mode
    levers = dataclasses.asdict(s.train)
    if levers["target_tau"] is None:
        levers["target_tau"] = settings["target_tau"]
    return counterfactual, levers


def learner_suffix(budget: str, learner: str | None, mode: str | None, tau: float | None) -> str:
    """The default ``out=``'s suffix naming the learner: ``-counterfactual`` and ``-polyak`` (``target_tau`` < 1)."""
    from crowdrl.training.learners import learner_of_preset, learner_settings

    try:
        settings = learner_settings(learner if learner is not None else learner_of_preset(budget))
    except (ValueError, FileNotFoundError):  # an unknown budget or learner: make_plan names it
        return ""
    mode = settings["counterfactual"]["mode"] if mode is None else mode
    tau = settings["target_tau"] if tau is None else tau
    return ("" if mode == "off" else "-counterfactual") + ("-polyak" if isinstance(tau, (int, float)) and tau < 1 else "")


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



def check_out(plan: Plan) -> None:
    """Refuse ``out=`` a file, or a folder that holds files but no ``manifest.json`` (one reproduce.py
    did not make: its ``table.md`` and figures would be written over); a new or empty folder, or one
    an earlier reproduce.py made (resumed), is fine. Before anything is written, the lock included."""
    from crowdrl.training.run_folder import RunFolderRefused, check_folder

    try:  # the lock comes before the manifest: a folder holding nothing but .lock is a call stopped in between
        check_folder(plan.out, (OUT_MARKER,), kind="reproduce.py folder", ignore=(".lock",))
    except RunFolderRefused as exc:
        raise PlanError(f"out: {exc}") from None


def check_manifest(plan: Plan) -> None:
    """Refuse to mix results of another budget, test-case count or code version in one folder, and a
    ``manifest.json`` that is not the JSON object reproduce.py writes (naming the file)."""
    from crowdrl.evaluation.report import RecordError, read_json_record

    path = plan.out / OUT_MARKER
    want = plan.manifest()
    if path.exists():
        try:
            have = read_json_record(path)
        except RecordError as exc:
            raise PlanError(f"out: {exc}; restore the manifest.json reproduce.py wrote, or pass a fresh "
                            f"out=<folder>") from None
        have.setdefault("planning", False)  # folders made before the key trained without planning
        have.setdefault("counterfactual", COUNTERFACTUAL_OFF)  # ... and without counterfactual experience
        have.setdefault("levers", LEVERS_OFF)  # ... and without stability levers
        have.setdefault("lidar", {"encoder": LIDAR_OFF[0], "rays": LIDAR_OFF[1]})  # ... and without the scan
        diff = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
        if diff:
            said = ", ".join(f"{k}: folder {a!r} vs now {b!r}" for k, (a, b) in diff.items())
            raise PlanError(f"out: {plan.out} holds results made with other settings ({said}); "
                            f"pass a fresh out=<folder> or delete {plan.out} to start again")
        return
    from crowdrl.files import atomic_write_json

    atomic_write_json(path, want)



def budget_frames(budget: str) -> int | None:
    """``train.total_frames`` of ``conf/preset/<budget>.yaml`` as it reads now (``None``: the preset leaves it out)."""
    from omegaconf import OmegaConf

    node = OmegaConf.load(config_dir() / "preset" / f"{budget}.yaml")
    value = OmegaConf.select(node, "train.total_frames", default=None)
    return None if value is None else int(value)


def check_budget_of_new_runs(plan: Plan, pending: list[tuple[Method, int]]) -> None:
    """Refuse (naming ``budget``) to train ``pending`` runs at another frame budget than the runs already in
    ``plan.out`` (trained, or killed and resumable): a budget preset whose frames changed since the folder was
    made (``budget=demo`` was 200k frames before issue 50, 80k after) would otherwise put runs of two budgets in
    one table. A rerun that trains nothing (a table rebuilt from its records) is not refused."""
    from omegaconf import OmegaConf

    if not pending:
        return
    frames = budget_frames(plan.budget)
    made = {}
    for config in sorted((plan.out / "runs").glob("*/config.yaml")):
        value = OmegaConf.select(OmegaConf.load(config), "train.total_frames", default=None)
        if value is not None:
            made[config.parent.name] = int(value)
    other = {name: value for name, value in made.items() if value != frames}
    if frames is not None and other:
        name, value = next(iter(other.items()))
        raise PlanError(f"budget: {plan.budget} trains {frames} frames now, but the runs in {plan.out} were trained at "
                        f"{value} (e.g. {name}; the preset changed since the folder was made): new runs would not "
                        f"compare with them; pass a fresh out=<folder> (with the budget whose frames they used, e.g. "
                        f"budget=demo200k for the tables recorded as budget=demo before issue 50)")


def run_overrides(plan: Plan, method: Method) -> list[str]:
    """The Hydra overrides of one training run (its seed and folder are added by the launcher)."""
    return [f"preset={plan.budget}", f"encoder={method.encoder}", f"exploration={method.variant}",
            f"env={plan.train_scenario}", "logger=csv", "logger.progress_bar=false", "logger.render=false",
            f"train.test_episodes={plan.episodes}", f"threads={plan.threads}",
            f"planning.enabled={str(plan.planning).lower()}",
            *plan.counterfactual_overrides(), *plan.lever_overrides(), *plan.lidar_overrides()]


def is_trained(run_dir: Path) -> bool:
    """Whether the run in ``run_dir`` finished training (its ``status.json`` says completed)."""
    status = run_dir / "status.json"
    return status.exists() and json.loads(status.read_text()).get("state") == "completed"


def train_to_completion(run_dir: Path, overrides: Sequence[str], *, cwd: Path | None = None) -> int:
    """Train the run in ``run_dir`` to its budget in a child ``python -m crowdrl.cli.train``; its exit code.

    A finished run (:func:`is_trained`) is skipped, a killed one resumes from ``checkpoints/last.pt`` (its own
    ``config.yaml``: ``overrides`` are not passed again), a new one starts with ``overrides``. The child's
    output is appended to ``<run_dir>.log`` beside the folder.

    Example::

        train_to_completion(Path("out/runs/egreedy-s0"), ["seed=0", "preset=demo", "logger=csv"])
    """
    if is_trained(run_dir):
        return 0
    cmd = [sys.executable, "-m", "crowdrl.cli.train"]
    if (run_dir / "checkpoints" / "last.pt").exists():
        cmd.append(f"resume={run_dir}")
    else:
        cmd += [f"hydra.run.dir={run_dir}", *overrides]
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    with open(run_dir.parent / f"{run_dir.name}.log", "ab") as log:
        return subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=cwd)


def eval_path(run_dir: Path, scenario: str) -> Path:
    """Where a run's test record on ``scenario`` lives."""
    return run_dir / f"eval-{scenario}" / "eval.json"


def has_eval(path: Path, episodes: int) -> bool:
    """Whether the record at ``path`` exists and covers ``episodes`` test cases."""
    from crowdrl.evaluation.report import read_eval_record

    return path.exists() and read_eval_record(path)["episodes"] == episodes
