"""Typed run configuration: the Hydra tree in ``conf/`` is checked against these dataclasses.

``validate(cfg)`` turns a Hydra/OmegaConf tree into a :class:`RunConfig` and fails at once on
an unknown key, a wrong type or an out-of-range value, naming the key and what is allowed.

Budgets are counted in frames (env steps of the robot). The paper counts episodes; an episode
of the trained policy lasts about 45–50 steps (11–12 s at 0.25 s), early ones fewer, so the
paper's 10k episodes are ≈ 0.5M frames and its schedules convert at 50 frames per episode
(ε-greedy over 4000 episodes = 200k frames, target copy every 500 episodes = 25k frames).

One set of defaults: the schema's defaults are ``conf/config.yaml`` composed with no overrides
(``preset=demo``; ``tests/test_defaults.py`` keeps the two equal), so the Python API and the CLI
train the same algorithm: SG-D3QN with its online planner (``planning.enabled``, as upstream) at the
demo budget. The budget keys (``train.*`` frames and ratios, ``exploration.anneal_frames``) are a
preset's choice: ``preset=paper``/``episodes``/``smoke`` override them. ``train.compile_acting`` is
off in both (it only buys speed; ``make demo`` and the paper/episodes presets turn it on). A stored
config that predates a key whose default has changed keeps the value it ran with
(:data:`STORED_DEFAULTS`, :func:`stored_config`).
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

from crowdrl.models import ENCODERS
from crowdrl.models.predictor import PREDICTORS
from crowdrl.sim.crowd import HUMAN_OBS_DIM, ROBOT_OBS_DIM
from crowdrl.sim.kinematics import NUM_ACTIONS
from crowdrl.sim.config import (HUMAN_KEYS, LIDAR_KEYS, MAX_HUMANS, OBSTACLE_KEYS, OBSTACLE_SCENARIOS, ORCA_BACKENDS,
                                SCENARIOS, CrowdConfig)
from crowdrl.sim.rng import MAX_SEED

FRAMES_PER_EPISODE = 50  # the paper's episode -> frame conversion (documented above)
EVAL_BATCH = 1000  # episodes stepped at once by the final test (and experiments/evaluate.py's eval.batch)
EXPLORATIONS = ("egreedy", "noisy", "dropout", "icm", "re3")  # the shipped variants; any registered strategy is valid
INTRINSIC = ("icm", "re3")
LOGGERS = ("wandb", "csv")
WANDB_MODES = ("offline", "online", "disabled")


class ConfigError(ValueError):
    """A configuration value is missing, unknown or out of range."""


@dataclass
class EnvConfig:
    """The scenario and its crowd: ``num_humans`` humans, or, with ``min_humans``/``max_humans``
    (each defaults to ``num_humans``), a size drawn per episode from ``min_humans..max_humans``."""

    scenario: str = "circle"
    num_humans: int = 10
    min_humans: int | None = None
    max_humans: int | None = None
    orca_backend: str = "eager"  # "compiled": the torch.compile ORCA (same numbers; compiles once per shape)
    # obstacle geometry of corridor / doorway / room (CrowdConfig's keys and defaults; conf/env/*.yaml)
    corridor_width: float = CrowdConfig.corridor_width
    corridor_length: float = CrowdConfig.corridor_length
    doorway_gap: float = CrowdConfig.doorway_gap
    doorway_width: float = CrowdConfig.doorway_width
    room_pillars: int = CrowdConfig.room_pillars
    room_pillar_min: float = CrowdConfig.room_pillar_min
    room_pillar_max: float = CrowdConfig.room_pillar_max
    orca_time_horizon_obst: float = CrowdConfig.orca_time_horizon_obst
    obstacle_tokens: int = CrowdConfig.obstacle_tokens  # the nearest obstacle edges the robot observes
    # a 2-D lidar scan in the observation, every scenario ("lidar" [B, lidar_rays]; 0: none): for users,
    # no network of crowdrl reads it
    lidar_rays: int = CrowdConfig.lidar_rays
    lidar_range: float = CrowdConfig.lidar_range  # m, readings clipped to it
    # how the humans move (orca, social_force, linear) and whether they see the robot; the social-force
    # parameters (socialforce 0.2.3's defaults) are read by human_model=social_force only
    human_model: str = CrowdConfig.human_model
    robot_visible: bool = CrowdConfig.robot_visible
    sf_tau: float = CrowdConfig.sf_tau
    sf_v0: float = CrowdConfig.sf_v0
    sf_sigma: float = CrowdConfig.sf_sigma
    sf_substeps: int = CrowdConfig.sf_substeps


@dataclass
class EncoderConfig:
    name: str = "sgd3qn"


@dataclass
class ExplorationConfig:
    """Exploration variant (``docs/mdp.md``, "Exploration variants"). ``anneal_frames`` is the
    length of the ε schedule and of the dropout-p schedule; ``eps_*`` apply to every variant (the
    non-ε variants set them to 0)."""

    name: str = "egreedy"
    eps_start: float = 0.5
    eps_end: float = 0.1
    anneal_frames: int = 100_000  # the demo's; the paper's 4000 episodes (200k) in exploration/*.yaml
    sigma0: float = 0.5  # noisy: factorised NoisyLinear σ0
    dropout_start: float = 0.5  # dropout: p decays linearly start -> end over anneal_frames
    dropout_end: float = 0.01
    beta: float = 0.01  # icm/re3: r = r_ext + β r_in
    beta_end: float | None = None  # icm/re3, linear schedule: β -> beta_end over anneal_frames
    # icm/re3: constant | linear (needs beta_end) | exp (needs beta_decay: β (1 - beta_decay)^frames);
    # null: linear when beta_end is given, else constant
    beta_schedule: str | None = None
    beta_decay: float | None = None
    icm_lr: float = 1e-4
    re3_k: int = 3
    # icm/re3, stable-bonus options of IntrinsicRewardTransform (docs/mdp.md, "Intrinsic-reward options");
    # the defaults are the method as published
    reward_norm: str = "none"  # none | std: r_in divided by its running std | batch: standardised over the sampled batch
    reward_center: bool = False  # r_in minus its mean (running, or the batch's with reward_norm=batch): no net per-step bonus
    reward_clip: float | None = None  # clip the normalised r_in to [-c, c]
    obs_norm: bool = False  # the bonus's input observations whitened by running mean/std, clipped to ±obs_clip
    obs_clip: float = 5.0
    terminal_value: bool = False  # terminal transitions get β γ^m mean(r_in) / (1 - γ): ending never forgoes the bonus
    icm_feature_norm: str = "none"  # none | layernorm: ICM's φ ends with a LayerNorm without gain (fixed scale)
    icm_detach_target: bool = True  # false: the forward loss's gradient reaches φ(s') too (Pathak et al.'s code)


@dataclass
class LoggerConfig:
    name: str = "wandb"
    mode: str = "offline"  # wandb mode; WANDB_MODE in the environment, when set, wins over it
    project: str = "crowdrl"
    progress_bar: bool = True
    render: bool = True  # after the test: learning_curves.png and a PNG + GIF of test case 0


COUNTERFACTUAL_MODES = ("off", "second_update", "merged")
COUNTERFACTUAL_ACTIONS = ("topk", "all", "random")


@dataclass
class CounterfactualConfig:
    """Counterfactual experience (``docs/mdp.md``, "Counterfactual experience"): for each sampled
    state, ``k`` alternative actions (``topk`` by the online Q, ``all`` 81, or ``random`` distinct
    ones) stepped exactly by the simulator's one-step model against the humans' real next state.
    ``second_update``: a second double-DQN step on them after each real one (SG-D3QN's trainer);
    ``merged``: one step on the real and counterfactual terms, the latter weighted ``weight``."""

    mode: str = "off"
    actions: str = "topk"
    k: int = 5  # alternatives per sampled state (actions=all: every action, k is not read)
    weight: float = 0.5  # merged: loss = (1 - weight) * real + weight * counterfactual


@dataclass
class TrainConfig:
    num_envs: int = 64  # environments stepped at once by the collector
    steps_per_batch: int = 8  # steps per environment per collected batch
    total_frames: int = 200_000  # the demo's budget; the paper's 10k episodes (500k frames): preset=paper
    buffer_size: int = 100_000
    batch_size: int = 100
    n_step: int = 1
    gamma: float = 0.9 ** 0.25  # 0.974 per 0.25 s step at v_pref 1
    lr: float = 1e-3
    updates_per_frame: float = 0.125
    warmup_frames: int = 2_000  # collect this many frames before the first update
    target_update_frames: int = 10_000  # the paper's 500 episodes (25k frames): preset=paper
    val_every_frames: int = 10_000
    val_episodes: int = 100
    checkpoint_every_frames: int = 10_000
    save_buffer: bool = False  # the replay buffer in last.pt: a resume is then bit-exact (its size: docs/reliability.md)
    test_episodes: int = 1000
    # the acting Q network (collection, planning, validation, test) through torch.compile; off here and
    # in conf/ (speed only); make demo and the paper/episodes presets turn it on (bench_train.py --acting)
    compile_acting: bool = False
    # the D3QN update (target, forwards, backward), and the planner's predictor update, each as one
    # torch.compile graph (bench_train.py --loss)
    compile_loss: bool = True
    counterfactual: CounterfactualConfig = field(default_factory=CounterfactualConfig)


@dataclass
class PlanningConfig:
    """SG-D3QN's online planning (``docs/mdp.md``, "Online planning"): act by re-scoring the top
    ``width`` actions by Q with a ``depth``-step look-ahead through a crowd ``predictor``
    (``learned``: trained alongside Q by MSE, Adam ``lr``; ``const_vel``: no parameters)."""

    enabled: bool = True  # as upstream SG-D3QN; false: the plain dueling double DQN
    depth: int = 1
    width: int = 10
    predictor: str = "learned"
    lr: float = 1e-3


@dataclass
class RunConfig:
    """One run's whole configuration: the groups of ``conf/`` as typed sections.

    Build it with :func:`validate` from a Hydra tree, a plain dict of overrides or a
    ``RunConfig``; keys left out take the schema's defaults.

    Examples:
        >>> from crowdrl.training import ConfigError, RunConfig, validate
        >>> run = validate({"seed": 3, "encoder": {"name": "sarl"}, "train": {"batch_size": 32}})
        >>> type(run).__name__, run.seed, run.encoder.name, run.train.batch_size
        ('RunConfig', 3, 'sarl', 32)
        >>> run = RunConfig(seed=1)
        >>> run.train.lr = 5e-4
        >>> validate(run).train.lr
        0.0005

        An unknown key or a value out of range fails at once, naming the key:

        >>> validate({"train": {"batch_sise": 32}})
        Traceback (most recent call last):
            ...
        crowdrl.training.config.ConfigError: Key 'batch_sise' not in 'TrainConfig' (key 'train.batch_sise'; ...)
        >>> validate({"train": {"gamma": 1.5}})
        Traceback (most recent call last):
            ...
        crowdrl.training.config.ConfigError: train.gamma: must lie in (0, 1], got 1.5
    """

    env: EnvConfig = field(default_factory=EnvConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    planning: PlanningConfig = field(default_factory=PlanningConfig)
    preset: str = "demo"
    seed: int = 0
    threads: int = 1
    device: str = "cpu"
    resume: str | None = None
    # never used: kept (null only) so that the config.yaml of older run folders, which hold
    # ``run_dir: null``, still loads; a value is refused (the folder is hydra.run.dir or --out)
    run_dir: str | None = None


def run_uid() -> str:
    """Six random hex digits: the unique part of a default run folder's name."""
    import secrets

    return secrets.token_hex(3)


def register_resolvers() -> None:
    """``${crowdrl_uid:}`` for ``conf/``: :func:`run_uid`, the same for every use within one
    config (run folder names: two runs started in the same second never share a folder)."""
    if not OmegaConf.has_resolver("crowdrl_uid"):
        OmegaConf.register_new_resolver("crowdrl_uid", run_uid, use_cache=True)


def _check(cond: bool, key: str, msg: str) -> None:
    if not cond:
        raise ConfigError(f"{key}: {msg}")


def _one_of(value: Any, key: str, allowed: tuple | list) -> None:
    _check(value in allowed, key, f"got {value!r}; allowed: {', '.join(map(str, allowed))}")


# Keys whose schema default changed after run folders were recorded, at the value those folders ran
# with: a stored config (a run folder's config.yaml, a checkpoint's config) that lacks one ran with
# this value, not with today's default. planning.enabled: off before planning was the default (the
# schema's default was off until one set of defaults); train.compile_acting: off in the schema before.
STORED_DEFAULTS = {"planning": {"enabled": False}, "train": {"compile_acting": False}}


def sees_obstacles(run: RunConfig) -> bool:
    """Whether the run's networks read obstacles: trained in an obstacle scenario, they take the humans
    and the observed obstacle edges as entity tokens (:func:`crowdrl.envs.robot_centric.entity_tokens`),
    wherever they are evaluated."""
    return run.env.scenario in OBSTACLE_SCENARIOS


def stored_config(cfg: DictConfig | dict) -> dict:
    """A stored config with :data:`STORED_DEFAULTS` filled in where it lacks them: what that run ran with.

    >>> stored_config({"seed": 1})["planning"]
    {'enabled': False}
    >>> stored_config({"planning": {"enabled": True}})["planning"]
    {'enabled': True}
    """
    out = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    for group, keys in STORED_DEFAULTS.items():
        node = out.get(group)
        node = dict(node) if isinstance(node, dict) else {}
        for key, value in keys.items():
            node.setdefault(key, value)
        out[group] = node
    return out


def resume_conflicts(current: DictConfig, saved: DictConfig, overrides: list[str]) -> list[str]:
    """The command-line ``overrides`` that disagree with a run folder's ``saved`` config.

    ``current`` is the config Hydra composed with those overrides. A key the saved file lacks (it
    predates the key) takes the schema's default, which is what ``validate(saved)`` runs with, except
    for :data:`STORED_DEFAULTS` (the value it ran with: :func:`stored_config`).
    ``resume`` and ``hydra.*`` are not compared; a config group (``env=...``) compares its content.

    >>> from omegaconf import OmegaConf
    >>> resume_conflicts(OmegaConf.create({"seed": 0}), OmegaConf.create({"seed": 1}), ["seed=0"])
    ['seed=0 (the run has seed=1)']
    """
    def complete(cfg: DictConfig) -> DictConfig:  # every schema key, the file's values over the defaults
        return OmegaConf.merge(OmegaConf.structured(RunConfig), OmegaConf.to_container(cfg, resolve=True))

    now, then = complete(current), complete(OmegaConf.create(stored_config(saved)))
    conflicts = []
    for item in overrides:
        key = item.split("=", 1)[0].lstrip("+~")
        if key == "resume" or key.startswith("hydra"):
            continue
        had = OmegaConf.select(then, key, default=None)
        same = OmegaConf.select(now, key, default=None) == had
        if not same:
            conflicts.append(f"{item} (the run has {key}={had})")
    return conflicts


def validate(cfg: DictConfig | dict | RunConfig, *, resources: bool = True) -> RunConfig:
    """Check a config tree against the schema and the allowed values; return it typed.

    With ``resources`` (the default) also what the run would need of this machine's memory
    (:func:`check_resources`); a checkpoint's stored config is read with ``resources=False``."""
    if isinstance(cfg, RunConfig):
        cfg = OmegaConf.structured(cfg)
    schema = OmegaConf.structured(RunConfig)
    try:
        merged = OmegaConf.merge(schema, OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg)
    except Exception as exc:  # omegaconf's messages name the key; keep them
        raise ConfigError(str(exc).splitlines()[0] + _hint(exc)) from None
    run: RunConfig = OmegaConf.to_object(merged)
    for key, value in _floats(run):
        _check(math.isfinite(value), key, f"must be a finite number, got {value}")
    e, t, x = run.env, run.train, run.exploration
    _one_of(e.scenario, "env.scenario", SCENARIOS)
    _check(1 <= e.num_humans <= MAX_HUMANS, "env.num_humans", f"must lie in 1..{MAX_HUMANS}, got {e.num_humans}")
    for key in ("min_humans", "max_humans"):
        value = getattr(e, key)
        _check(value is None or 1 <= value <= MAX_HUMANS, f"env.{key}", f"must lie in 1..{MAX_HUMANS} or be null, got {value}")
    low, high = crowd_range(e)
    _check(low <= high, "env.min_humans/env.max_humans",
           f"need min_humans <= max_humans, got {low} > {high} (each defaults to env.num_humans = {e.num_humans})")
    _one_of(e.orca_backend, "env.orca_backend", ORCA_BACKENDS)
    try:  # the obstacle geometry, the lidar, the humans' model: CrowdConfig's checks, whose messages start with the key
        CrowdConfig(scenario=e.scenario, **{k: getattr(e, k) for k in (*OBSTACLE_KEYS, *LIDAR_KEYS, *HUMAN_KEYS)})
    except ValueError as exc:
        raise ConfigError(f"env.{exc}") from None
    _one_of(run.encoder.name, "encoder.name", sorted(ENCODERS))
    from crowdrl.exploration.strategy import strategy_names

    _one_of(x.name, "exploration.name", strategy_names())
    _check(0 <= x.eps_end <= x.eps_start <= 1, "exploration.eps_start/eps_end",
           f"need 0 <= eps_end <= eps_start <= 1, got {x.eps_start} -> {x.eps_end}")
    _check(x.anneal_frames >= 1, "exploration.anneal_frames", f"must be >= 1, got {x.anneal_frames}")
    _check(x.sigma0 > 0, "exploration.sigma0", f"must be > 0, got {x.sigma0}")
    for key in ("dropout_start", "dropout_end"):
        _check(0 <= getattr(x, key) < 1, f"exploration.{key}", f"must lie in [0, 1), got {getattr(x, key)}")
    _check(x.beta >= 0, "exploration.beta", f"must be >= 0, got {x.beta}")
    _check(x.beta_end is None or x.beta_end >= 0, "exploration.beta_end", f"must be >= 0 or null, got {x.beta_end}")
    _check_intrinsic_options(x)
    _check(x.icm_lr > 0, "exploration.icm_lr", f"must be > 0, got {x.icm_lr}")
    _check(x.re3_k >= 1, "exploration.re3_k", f"must be >= 1, got {x.re3_k}")
    _check(x.name != "re3" or x.re3_k < run.train.batch_size, "exploration.re3_k",
           f"must lie in 1..train.batch_size-1 ({run.train.batch_size - 1}), got {x.re3_k}")
    _one_of(run.logger.name, "logger.name", LOGGERS)
    _one_of(run.logger.mode, "logger.mode", WANDB_MODES)
    for key in ("num_envs", "steps_per_batch", "total_frames", "buffer_size", "batch_size", "n_step",
                "target_update_frames", "val_every_frames", "val_episodes", "checkpoint_every_frames", "test_episodes"):
        value = getattr(t, key)
        _check(value >= 1, f"train.{key}", f"must be >= 1, got {value}")
    _check(t.warmup_frames >= 0, "train.warmup_frames", f"must be >= 0, got {t.warmup_frames}")
    _check(t.n_step <= t.steps_per_batch, "train.n_step",
           f"({t.n_step}) must not exceed train.steps_per_batch ({t.steps_per_batch}): windows end with the batch")
    _check(t.batch_size <= t.buffer_size, "train.batch_size",
           f"({t.batch_size}) must not exceed train.buffer_size ({t.buffer_size})")
    _check(0 < t.gamma <= 1, "train.gamma", f"must lie in (0, 1], got {t.gamma}")
    _check(not x.terminal_value or t.gamma < 1, "exploration.terminal_value",
           f"values the forgone bonus as mean / (1 - gamma): needs train.gamma < 1, got {t.gamma}")
    _check(t.lr > 0, "train.lr", f"must be > 0, got {t.lr}")
    _check(t.updates_per_frame >= 0, "train.updates_per_frame", f"must be >= 0, got {t.updates_per_frame}")
    check_counterfactual(run)
    p = run.planning
    _check(p.depth >= 1, "planning.depth", f"must be >= 1, got {p.depth}")
    _check(1 <= p.width <= NUM_ACTIONS, "planning.width", f"must lie in 1..{NUM_ACTIONS}, got {p.width}")
    _one_of(p.predictor, "planning.predictor", PREDICTORS)
    _check(p.lr > 0, "planning.lr", f"must be > 0, got {p.lr}")
    _check(0 <= run.seed <= MAX_SEED, "seed", f"must lie in 0..2**63-1 ({MAX_SEED}), got {run.seed}")
    check_threads(run.threads)
    _check(t.updates_per_frame == 0 or t.total_frames > max(t.batch_size, t.warmup_frames), "train.total_frames",
           f"({t.total_frames}) must exceed train.batch_size ({t.batch_size}) and train.warmup_frames "
           f"({t.warmup_frames}): with this budget not a single update could run")
    _check(run.resume is None or run.resume.strip() != "", "resume",
           "is empty (resume= with nothing after it, e.g. resume=$RUN with RUN unset): give the run folder to "
           "continue, resume=runs/<folder>, or leave resume out to start a new run")
    _check(run.run_dir is None, "run_dir", f"is not used (got {run.run_dir!r}): choose the run folder with "
           f"hydra.run.dir=<folder> (train.py), out=<folder> (demo.py) or resume=<folder>")
    check_device(run.device)
    if resources:
        check_resources(run)
        check_logger(run)
    return run


def check_logger(run: RunConfig) -> None:
    """Refuse (naming ``logger.mode``) a wandb run to start online without credentials: wandb would
    fail, or wait for a key, once the run folder is written."""
    from crowdrl.training.scalars import has_wandb_credentials, wandb_mode

    if run.logger.name == "wandb" and wandb_mode(run.logger.mode) == "online" and not has_wandb_credentials():
        raise ConfigError("logger.mode: online, but wandb has no credentials (no WANDB_API_KEY, no netrc entry): "
                          "run `wandb login` first, or use logger.mode=offline and `wandb sync` later")


# Bytes per planned state (robot + N humans: n = N + 1 nodes) when the planner scores it: n·(a + b·n),
# the rise of the resident memory's high-water mark (VmHWM) over one OnlinePlanner.plan call divided by
# the states it expanded (float32, learned predictor, 64 states, depth 2, width 10, N = 10 and N = 64,
# eager attention kernels: the fallback when compiling fails; the compiled ones need less,
# docs/benchmarks.md), rounded up by ~10 %. An upper estimate, not a measurement.
PLANNED_STATE_BYTES = {"sgd3qn": (1450, 500), "sarl": (2700, 12), "lstm_rl": (960, 40), "mp_rgl": (780, 42)}


def acting_batch(run: RunConfig) -> int:
    """The most states the run acts on at once: ``train.num_envs`` (collection),
    ``train.val_episodes`` (validation) or ``min(train.test_episodes, EVAL_BATCH)`` (the test)."""
    t = run.train
    return max(t.num_envs, t.val_episodes, min(t.test_episodes, EVAL_BATCH))


def planned_states(run: RunConfig, batch: int | None = None) -> int:
    """States the online planner expands per step for ``batch`` environments (default
    :func:`acting_batch`): ``width`` per state at each of ``depth`` levels, ``batch·Σ_k width^k``."""
    p = run.planning
    batch = acting_batch(run) if batch is None else batch
    return batch * sum(p.width ** k for k in range(1, p.depth + 1)) if p.enabled else 0


def planner_bytes(run: RunConfig, batch: int | None = None) -> int:
    """Upper estimate of the planner's memory per step (:data:`PLANNED_STATE_BYTES`), which scales
    with the states it expands and, per state, with the crowd (its largest size, ``env.max_humans``)."""
    a, b = PLANNED_STATE_BYTES.get(run.encoder.name, PLANNED_STATE_BYTES["sgd3qn"])  # sgd3qn: the largest
    n = crowd_range(run.env)[1] + 1
    return planned_states(run, batch) * n * (a + b * n)


def transition_bytes(run: RunConfig) -> int:
    """Bytes of one transition in the replay buffer (``factories.stored_keys``): the robot-centric
    state and successor (float32, plus the humans' bool mask when the crowd size varies), the
    action, ``index`` and ``steps_to_next_obs`` (int64), the reward (float32), ``done`` and
    ``terminated`` (bool), and with the learned predictor the world-frame state and next humans."""
    low, high = crowd_range(run.env)
    obs = 4 * (ROBOT_OBS_DIM + HUMAN_OBS_DIM * high) + (high if low < high else 0)
    out = 2 * obs + 3 * 8 + 4 + 2
    if (run.planning.enabled and run.planning.predictor == "learned") or counterfactual_on(run):
        out += 4 * (ROBOT_OBS_DIM + 2 * HUMAN_OBS_DIM * high)
    if counterfactual_on(run) and sees_obstacles(run):  # the episode's map: P polygons of V vertices and their mask
        P, V = CrowdConfig(scenario=run.env.scenario, **{k: getattr(run.env, k) for k in OBSTACLE_KEYS}).obstacles_shape
        out += P * V * (2 * 4 + 1)
    return out


def buffer_bytes(run: RunConfig) -> int:
    """Peak memory of the replay buffer: ``train.buffer_size`` transitions (the storage is allocated
    whole at the first write), and with ``train.save_buffer`` two more copies while a checkpoint is
    serialised (``torch.save`` into memory, then its bytes)."""
    return run.train.buffer_size * transition_bytes(run) * (3 if run.train.save_buffer else 1)


def available_memory(device: str = "cpu") -> int | None:
    """Bytes of memory available now: ``MemAvailable`` of ``/proc/meminfo`` (else free pages by
    ``os.sysconf``) for ``cpu``, the free memory of the CUDA device otherwise; ``None``: unknown."""
    import os

    if device.startswith("cuda"):
        import torch

        return int(torch.cuda.mem_get_info(torch.device(device))[0])
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _gib(n: float) -> str:
    return f"{n / 2**30:,.1f} GiB"


def check_resources(run: RunConfig) -> None:
    """Refuse (:class:`ConfigError`, naming the key) a run whose replay buffer (:func:`buffer_bytes`),
    or whose buffer plus the planner's states per step (:func:`planner_bytes`), would not fit in the
    memory available now (:func:`available_memory`)."""
    free = available_memory(run.device)
    if free is None:
        return
    t, p = run.train, run.planning
    buffer = buffer_bytes(run)
    copies = " (x3 with train.save_buffer=true: the checkpoint is serialised in memory)" if t.save_buffer else ""
    _check(buffer <= free, "train.buffer_size",
           f"{t.buffer_size} transitions of {transition_bytes(run)} bytes need ~{_gib(buffer)}{copies}, more than the "
           f"{_gib(free)} of memory available on this machine; lower train.buffer_size"
           + (" or set train.save_buffer=false" if t.save_buffer else ""))
    planner = planner_bytes(run)
    _check(planner <= free - buffer, "planning.depth/planning.width",
           f"the planner expands {planned_states(run)} states per step (B x sum of width^k, k = 1..depth: width "
           f"{p.width}, depth {p.depth}, B = {acting_batch(run)}, the largest of train.num_envs, train.val_episodes and "
           f"min(train.test_episodes, {EVAL_BATCH})) of up to {crowd_range(run.env)[1]} humans: ~{_gib(planner)} per "
           f"step, more than the {_gib(max(free - buffer, 0))} of memory available on this machine next to the replay "
           f"buffer; lower planning.depth or planning.width")


INTRINSIC_OPTIONS = ("beta_schedule", "beta_decay", "reward_norm", "reward_center", "reward_clip", "obs_norm",
                     "obs_clip", "terminal_value", "icm_feature_norm", "icm_detach_target")


def _check_intrinsic_options(x: ExplorationConfig) -> None:
    from crowdrl.exploration.icm import FEATURE_NORMS
    from crowdrl.exploration.normalize import REWARD_SCALES
    from crowdrl.exploration.schedule import SCHEDULES, beta_schedule_of

    if x.name not in INTRINSIC:
        defaults = ExplorationConfig()
        for key in INTRINSIC_OPTIONS:
            _check(getattr(x, key) == getattr(defaults, key), f"exploration.{key}",
                   f"applies to the intrinsic variants ({', '.join(INTRINSIC)}) only; exploration.name is {x.name!r}")
    _check(x.beta_schedule is None or x.beta_schedule in SCHEDULES, "exploration.beta_schedule",
           f"got {x.beta_schedule!r}; allowed: {', '.join(SCHEDULES)} or null")
    schedule = beta_schedule_of(x)
    _check(schedule != "linear" or x.beta_end is not None, "exploration.beta_end",
           "beta_schedule=linear needs exploration.beta_end (the value reached after exploration.anneal_frames)")
    _check(schedule == "linear" or x.beta_end is None, "exploration.beta_end",
           f"is set ({x.beta_end}) but beta_schedule={schedule} does not use it; use beta_schedule=linear or beta_end=null")
    _check(schedule != "exp" or x.beta_decay is not None, "exploration.beta_decay",
           "beta_schedule=exp needs exploration.beta_decay (β_t = β (1 - beta_decay)^frames)")
    _check(schedule == "exp" or x.beta_decay is None, "exploration.beta_decay",
           f"is set ({x.beta_decay}) but beta_schedule={schedule} does not use it; use beta_schedule=exp or beta_decay=null")
    _check(x.beta_decay is None or 0 <= x.beta_decay < 1, "exploration.beta_decay",
           f"must lie in [0, 1), got {x.beta_decay}")
    _one_of(x.reward_norm, "exploration.reward_norm", REWARD_SCALES)
    _check(x.reward_clip is None or x.reward_clip > 0, "exploration.reward_clip", f"must be > 0 or null, got {x.reward_clip}")
    _check(x.obs_clip > 0, "exploration.obs_clip", f"must be > 0, got {x.obs_clip}")
    _one_of(x.icm_feature_norm, "exploration.icm_feature_norm", FEATURE_NORMS)


def check_counterfactual(run: RunConfig) -> None:
    """``train.counterfactual``'s keys; it needs humans that ignore the robot (their real next state is
    then the next state after any action) and the unicycle's discrete actions."""
    c = run.train.counterfactual
    _one_of(c.mode, "train.counterfactual.mode", COUNTERFACTUAL_MODES)
    _one_of(c.actions, "train.counterfactual.actions", COUNTERFACTUAL_ACTIONS)
    _check(isinstance(c.k, int) and 1 <= c.k <= NUM_ACTIONS, "train.counterfactual.k",
           f"must be an integer in 1..{NUM_ACTIONS}, got {c.k!r}")
    _check(0 <= c.weight <= 1, "train.counterfactual.weight", f"must lie in [0, 1], got {c.weight}")
    humans = CrowdConfig(human_model=run.env.human_model, robot_visible=run.env.robot_visible)
    if c.mode != "off" and humans.humans_react_to_robot:
        raise ConfigError(f"train.counterfactual.mode: counterfactual experience replays the humans' real next state "
                          f"after another action, which is exact only while they ignore the robot; with "
                          f"env.robot_visible=true the {run.env.human_model} humans react to it (set "
                          f"train.counterfactual.mode=off or env.robot_visible=false)")


def counterfactual_on(run: RunConfig) -> bool:
    """Whether ``run`` learns from counterfactual experience."""
    return run.train.counterfactual.mode != "off"


def crowd_range(env: EnvConfig) -> tuple[int, int]:
    """The smallest and largest crowd of ``env`` (equal for a fixed crowd)."""
    low = env.num_humans if env.min_humans is None else env.min_humans
    high = env.num_humans if env.max_humans is None else env.max_humans
    return low, high


def check_threads(threads: Any, key: str = "threads") -> None:
    """An integer >= 1 (torch threads), otherwise a :class:`ConfigError` naming ``key``."""
    _check(isinstance(threads, int) and not isinstance(threads, bool) and threads >= 1, key,
           f"must be an integer >= 1, got {threads!r}")


def unknown_keys(cfg: Any, reference: Any, prefix: str = "") -> list[str]:
    """The dotted keys of the nested dict ``cfg`` that the nested dict ``reference`` lacks (a key
    added with ``+key=value`` that nothing reads); below a key whose reference is not a dict, nothing.

    >>> unknown_keys({"eval": {"episods": 5, "seed": 0}, "encoder": {"name": "sarl"}}, {"eval": {"seed": 0}})
    ['eval.episods', 'encoder']
    """
    if not (isinstance(cfg, dict) and isinstance(reference, dict)):
        return []
    out = []
    for key, value in cfg.items():
        if key not in reference:
            out.append(f"{prefix}{key}")
        else:
            out += unknown_keys(value, reference[key], f"{prefix}{key}.")
    return out


def check_device(device: str, key: str = "device") -> None:
    """``cpu``, or a CUDA device that exists on this machine; otherwise a :class:`ConfigError`."""
    import torch

    _check(device == "cpu" or re.fullmatch(r"cuda(:\d+)?", device) is not None, key,
           f"got {device!r}; allowed: cpu, cuda, cuda:<index>")
    if device.startswith("cuda"):
        _check(torch.cuda.is_available(), key, f"{device!r} requested but CUDA is not available on this machine "
                                               f"(torch.cuda.is_available() is False); use {key}=cpu")
        index = int(device.split(":")[1]) if ":" in device else 0
        count = torch.cuda.device_count()
        _check(index < count, key, f"{device!r} does not exist: this machine has {count} CUDA device(s)")


def _floats(node: Any, prefix: str = "") -> list[tuple[str, float]]:
    """Every float field of a (nested) config dataclass, with its dotted key."""
    out = []
    for f in dataclasses.fields(node):
        value, key = getattr(node, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += _floats(value, f"{key}.")
        elif isinstance(value, float):
            out.append((key, value))
    return out


def _hint(exc: Exception) -> str:
    key = getattr(exc, "full_key", None)
    if not key:
        return ""
    parent = key.rsplit(".", 1)[0] if "." in key else ""
    node: Any = RunConfig()
    for part in filter(None, parent.split(".")):
        node = getattr(node, part, None)
    if dataclasses.is_dataclass(node):
        return f" (key {key!r}; allowed keys here: {', '.join(f.name for f in dataclasses.fields(node))})"
    return f" (key {key!r})"


def to_dict(run: RunConfig) -> dict:
    """Plain nested dict of a run config (for logging and checkpoints)."""
    return dataclasses.asdict(run)
