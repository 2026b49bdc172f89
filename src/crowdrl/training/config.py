"""Typed run configuration: the Hydra tree in ``conf/`` is checked against these dataclasses.

The schema only; :func:`crowdrl.training.validation.validate` turns a Hydra/OmegaConf tree into a
:class:`RunConfig`, failing at once on an unknown key, a wrong type or an out-of-range value. Stored
configs of older runs: :mod:`crowdrl.training.compat`; memory bounds: :mod:`crowdrl.training.resources`.

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
(:data:`crowdrl.training.compat.STORED_DEFAULTS`, :func:`crowdrl.training.compat.stored_config`).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field

import crowdrl.exploration  # noqa: F401  (registers the shipped strategies and their schemas)
from crowdrl.exploration.strategy import exploration_config_class
from crowdrl.sim.config import HUMAN_KEYS, LIDAR_KEYS, OBSTACLE_KEYS, OBSTACLE_SCENARIOS, CrowdConfig

FRAMES_PER_EPISODE = 50  # the paper's episode -> frame conversion (documented above)
EVAL_BATCH = 1000  # episodes stepped at once by the final test (and experiments/evaluate.py's eval.batch)
LOGGERS = ("wandb", "csv")
WANDB_MODES = ("offline", "online", "disabled")


class ConfigError(ValueError):
    """A configuration value is missing, unknown or out of range."""


def _crowd_fields(keys: tuple[str, ...]) -> list[tuple[str, type, dataclasses.Field]]:
    """:class:`~crowdrl.sim.config.CrowdConfig`'s ``keys`` as fields of the same names, types and defaults: each
    key of the simulator is defined once, in ``CrowdConfig`` (whose comments say what it does)."""
    hints = typing.get_type_hints(CrowdConfig)
    return [(key, hints[key], field(default=getattr(CrowdConfig, key))) for key in keys]


# The scenario and its crowd: ``num_humans`` humans, or, with ``min_humans``/``max_humans`` (each defaults to
# ``num_humans``), a size drawn per episode from ``min_humans..max_humans``; ``orca_backend`` runs the humans'
# step (ORCA and social force alike) through torch.compile ("compiled": same numbers, compiled once per shape) or
# as plain torch ("eager"); then CrowdConfig's keys: the obstacle geometry of corridor / doorway / room (and the
# edges the robot observes), the lidar scan (read by the networks with encoder.lidar) and the humans' model
# (orca, social_force, linear or mixed, whether they see the robot, and the social force's parameters, read only
# where such humans may be present).
EnvConfig = dataclasses.make_dataclass("EnvConfig", [
    ("scenario", str, field(default="circle")),
    ("num_humans", int, field(default=10)),
    ("min_humans", typing.Optional[int], field(default=None)),
    ("max_humans", typing.Optional[int], field(default=None)),
    ("orca_backend", str, field(default="eager")),
    *_crowd_fields((*OBSTACLE_KEYS, *LIDAR_KEYS, *HUMAN_KEYS)),
    # one agent for several scenarios: training batches mix them in these proportions (scenario -> share of
    # train.num_envs' rows, each on its own stream; crowdrl.envs.mix); {}: env.scenario alone. Tests and the
    # evaluation default stay on env.scenario, one of the mix's.
    ("mix", typing.Dict[str, float], field(default_factory=dict)),
])
EnvConfig.__module__ = __name__
EnvConfig.__doc__ = ("The scenario and its crowd (``num_humans``, or a size drawn per episode from ``min_humans.."
                     "max_humans``), the humans' step backend, and the simulator's keys of "
                     ":class:`~crowdrl.sim.config.CrowdConfig` (obstacle geometry, lidar, the humans' model) with "
                     "its names, types and defaults.")


@dataclass
class EncoderConfig:
    name: str = "sgd3qn"
    # the lidar scan as tokens beside the humans' (crowdrl.models.scan): off | mlp | conv; needs env.lidar_rays >= 1
    lidar: str = "off"


# The exploration section: the keys every strategy reads and those of each registered strategy's own schema
# (crowdrl.exploration.strategy.register_strategy; importing crowdrl.exploration registers the shipped ones).
ExplorationConfig = exploration_config_class()


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

    mode: str = "second_update"  # the recommended learner's (conf/learner/); a stored config without the key: COUNTERFACTUAL_OFF
    actions: str = "topk"
    k: int = 5  # alternatives per sampled state (actions=all: every action, k is not read)
    weight: float = 0.5  # merged: loss = (1 - weight) * real + weight * counterfactual


# counterfactual experience off (the plain learner, conf/learner/plain.yaml): what a stored config that
# predates the key ran with, and a fingerprint leaves out (so older run folders keep theirs)
COUNTERFACTUAL_OFF = {"mode": "off", "actions": "topk", "k": 5, "weight": 0.5}


@dataclass
class DemonstrationConfig:
    """The oracle as a teacher (:mod:`crowdrl.training.demonstrations`; docs/ceiling.md): before the first
    collected batch of a fresh run, ``cases`` cases of the run's train stream (episode ids ``2**62 + i``, which
    the collector never reaches) are solved by the oracle's beam search at ``widths`` (the first on every case,
    each wider one on those still unsolved), and each path found, played through the training env, is stored in
    the replay buffer as collected transitions are. Not counted as frames. 0: off."""

    cases: int = 0
    widths: list[int] = field(default_factory=lambda: [16, 64])


@dataclass
class TrainConfig:
    num_envs: int = 64  # environments stepped at once by the collector
    steps_per_batch: int = 8  # steps per environment per collected batch
    total_frames: int = 80_000  # the demo's budget; the paper's 10k episodes (500k frames): preset=paper
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
    # every validation also keeps its network as checkpoints/val-<frames>.pt, with the run's timers then
    # (experiments/time_to_quality.py tests them in order); off: best.pt and last.pt only
    keep_val_checkpoints: bool = False
    # the acting Q network (collection, planning, validation, test; and the counterfactual top-k's ranking) through
    # torch.compile; off here and
    # in conf/ (speed only); make demo and the paper/episodes presets turn it on (bench_train.py --acting)
    compile_acting: bool = False
    # the D3QN update (target, forwards, backward), and the planner's predictor update, each as one
    # torch.compile graph (bench_train.py --loss)
    compile_loss: bool = True
    counterfactual: CounterfactualConfig = field(default_factory=CounterfactualConfig)
    demonstrations: DemonstrationConfig = field(default_factory=DemonstrationConfig)
    # stability levers (LEVERS_OFF: each off, the paper's learner): Polyak target updates after every
    # update (1: a hard copy every target_update_frames; 0.005 in the recommended learner, the default),
    # a Huber loss of this delta (null: squared error), the Q gradients' norm clipped (null: not), the
    # learning rate decayed linearly to lr_end over total_frames (null: constant), LayerNorm in the Q
    # head's hidden layers (crowdrl.models.DuelingHead)
    target_tau: float = 0.005
    huber_delta: float | None = None
    grad_clip_norm: float | None = None
    lr_end: float | None = None
    q_layer_norm: bool = False


# train's stability levers: read by the fingerprint (left out when off, so folders made before them keep
# theirs) and given to every run of a reproduction
LEVER_KEYS = ("target_tau", "huber_delta", "grad_clip_norm", "lr_end", "q_layer_norm")
# each lever off (the paper's learner; the default learner sets target_tau 0.005): what a stored config
# without a lever's key ran with
LEVERS_OFF = {"target_tau": 1.0, "huber_delta": None, "grad_clip_norm": None, "lr_end": None, "q_layer_norm": False}


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
    # a run-time safety check (crowdrl.policies.planning): act by no action that collides with the predicted crowd
    # within this many steps when held; 0: off (as upstream, and every run recorded before the key)
    safety_horizon: int = 0
    # the step's progress counted (1 + progress_bias) times in the planner's scores (crowdrl.policies.planning): shorter
    # paths for some of the learned value's caution, at act time; 0: off (as upstream, and every run recorded before the key)
    progress_bias: float = 0.0


@dataclass
class RunConfig:
    """One run's whole configuration: the groups of ``conf/`` as typed sections.

    Build it with :func:`~crowdrl.training.validation.validate` from a Hydra tree, a plain dict of overrides or a
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



MIX = "mix"  # the env group option (conf/env/mix.yaml) that trains on every scenario in one batch (env.mix)


def trained_scenarios(run: RunConfig) -> tuple[str, ...]:
    """The scenarios ``run`` trains on: ``env.mix``'s of a proportion above 0, or ``env.scenario`` alone."""
    mixed = tuple(name for name, share in run.env.mix.items() if share > 0)
    return mixed or (run.env.scenario,)


def trained_on(run: RunConfig) -> str:
    """What a record names as the run's training scenario: ``mix`` for a run over several scenarios
    (``env.mix``), else ``env.scenario``."""
    names = trained_scenarios(run)
    return MIX if len(names) > 1 else names[0]


def sees_obstacles(run: RunConfig) -> bool:
    """Whether the run's networks read obstacles: trained in an obstacle scenario (one of its mix), they take the
    humans and the observed obstacle edges as entity tokens (:func:`crowdrl.envs.robot_centric.entity_tokens`),
    wherever they are evaluated."""
    return any(name in OBSTACLE_SCENARIOS for name in trained_scenarios(run))


def map_extent(run: RunConfig) -> tuple[int, tuple[int, int]]:
    """``(K, (P, V))`` of the training batches: the most obstacle edges observed and the largest map (polygons,
    vertices) among the trained scenarios (a mix pads the others to them; ``(0, (0, 0))`` in open space)."""
    configs = [crowd_config(run, scenario=name) for name in trained_scenarios(run)]
    return (max(c.num_obstacle_tokens for c in configs),
            (max(c.obstacles_shape[0] for c in configs), max(c.obstacles_shape[1] for c in configs)))


def counterfactual_on(run: RunConfig) -> bool:
    """Whether ``run`` learns from counterfactual experience."""
    return run.train.counterfactual.mode != "off"


def crowd_range(env: EnvConfig) -> tuple[int, int]:
    """The smallest and largest crowd of ``env`` (equal for a fixed crowd)."""
    low = env.num_humans if env.min_humans is None else env.min_humans
    high = env.num_humans if env.max_humans is None else env.max_humans
    return low, high


def crowd_config(run: RunConfig, *, scenario: str | None = None, num_humans: int | None = None,
                 robot_kinematics: str = "unicycle") -> CrowdConfig:
    """The simulator constants of ``run``, built from its ``env`` section here only (``scenario``/``num_humans``
    override the run's; a given ``num_humans`` is a fixed crowd even when the run's varies)."""
    low, high = crowd_range(run.env)
    if num_humans is not None:
        low = high = num_humans
    return CrowdConfig(scenario=scenario or run.env.scenario, num_humans=high, min_humans=low if low < high else None,
                       orca_backend=run.env.orca_backend, robot_kinematics=robot_kinematics,
                       **{k: getattr(run.env, k) for k in (*OBSTACLE_KEYS, *LIDAR_KEYS, *HUMAN_KEYS)})


def to_dict(run: RunConfig) -> dict:
    """Plain nested dict of a run config (for logging and checkpoints)."""
    return dataclasses.asdict(run)
