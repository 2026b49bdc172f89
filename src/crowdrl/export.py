"""Export a trained checkpoint's acting policy to ONNX, to run on a robot without torch
(``docs/export.md``; ``experiments/export.py`` is the command line).

**A checkpoint that acts with online planning** (SG-D3QN's planner, ``planning.enabled``: every shipped
agent) exports its planner whole (:class:`PlannerPolicy`): the Q network, the crowd predictor and the
depth-``d``, width-``w`` look-ahead of :class:`~crowdrl.policies.OnlinePlanner` (top-``w`` by Q, the
one-step model, the simulator's reward, the bootstrap; the safety check when it has one), its depth,
width and safety horizon fixed at export (the checkpoint's, or the export's ``planning_*`` keys). The
planner reads the world-frame observation (its predictor is not invariant to the frame), with a batch
axis ``B``:

* ``robot`` ``[B, 9]`` float32: ``px, py, vx, vy, radius, gx, gy, v_pref, heading``;
* ``humans`` ``[B, N, 5]`` float32: each human's ``px, py, vx, vy, radius``;
* ``humans_mask`` ``[B, N]`` bool: True where a row is a human present.

It returns ``q_values`` ``[B, 81]``, the planner's ``action`` ``[B]`` (int64), its ``command`` ``[B, 2]``,
the ``candidates`` ``[B, w]`` (top-``w`` by Q, best first) and their ``scores`` ``[B, w]``.

**A checkpoint that acts greedily on Q** (or any checkpoint with ``planning_depth=0``, which drops its
planner: labelled in the metadata and printed) exports its greedy Q policy (:class:`GreedyQPolicy`) on
the robot-centric observation (:func:`crowdrl.envs.robot_centric.robot_centric`):

* ``robot_rc`` ``[B, 9]`` float32: ``0, 0, vx, vy, radius, goal distance, 0, v_pref, heading``;
* ``humans_rc`` ``[B, N, 5]`` float32: each human's ``px, py, vx, vy, radius + robot radius``;
* ``humans_mask`` ``[B, N]`` bool (absent rows are ignored: the networks are padding-invariant).

A checkpoint trained among obstacles (corridor, doorway, room) takes the entity tokens of
:func:`crowdrl.envs.robot_centric.entity_tokens` instead of the humans (``entities_rc`` ``[B, N+K, 10]``,
``entities_mask``); its planner reads the observed obstacle edges, and so does its exported planner (layout
``world_obstacles``: ``obstacles`` ``[B, K, 4]`` and ``obstacles_mask`` ``[B, K]`` after the humans; in open space
one masked edge).

A network that reads the lidar scan (``encoder.lidar``) takes it as one more input, last: ``lidar``
``[B, R]`` float32, the env's ``"lidar"`` observation (ray ``r`` at ``heading + 2πr/R``, counter-clockwise,
metres clipped at the range; :mod:`crowdrl.sim.lidar`); its layout's name ends in ``_lidar``. Its planner
computes the scans of predicted states itself, from the predicted humans and the observed edges.

The greedy model returns ``q_values``, the greedy ``action`` (the first of tied maxima, as
``torch.argmax``) and its ``command``: the row of the unicycle action table
(:func:`crowdrl.sim.kinematics.action_table`), ``(speed m/s, rotation rad)``: turn by the rotation, then
move straight at the speed for one time step. ``N`` is free for every encoder but LSTM-RL, whose
recurrence is unrolled over the checkpoint's largest crowd (``N`` is then fixed; pad with absent rows).

The model's ``metadata_props`` hold the format version (:data:`FORMAT_VERSION`), the observation layout
(:data:`LAYOUTS`), the crowd size, the planning settings and the run config; :func:`read_exported`
checks them (a truncated file, another layout or a newer format is refused naming the file).
"""

from __future__ import annotations

import io
import json
import math
import os
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor, nn

from crowdrl.files import atomic_write_bytes
from crowdrl.policies.planning import OnlinePlanner
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table
from crowdrl.training.checkpoint import (CheckpointError, checkpoint_path, config_fingerprint,
                                        load_trained_network, load_trained_predictor)
from crowdrl.envs.robot_centric import ENTITY_DIM
from crowdrl.training.config import RunConfig, map_extent, sees_obstacles, to_dict
from crowdrl.training.config import crowd_config

INPUTS = ("robot_rc", "humans_rc", "humans_mask")
ENTITY_INPUTS = ("robot_rc", "entities_rc", "entities_mask")  # a checkpoint trained among obstacles
PLANNER_INPUTS = ("robot", "humans", "humans_mask")  # the planner: the env's world-frame observation
# the planner of a network trained among obstacles: also the observed obstacle edges [B, K, 4] and their mask [B, K]
PLANNER_OBSTACLE_INPUTS = (*PLANNER_INPUTS, "obstacles", "obstacles_mask")
LIDAR_INPUT = "lidar"  # a network that reads the scan (encoder.lidar) takes it last
OUTPUTS = ("q_values", "action", "command")
PLANNER_OUTPUTS = ("q_values", "action", "command", "candidates", "scores")
# the version of the model's layout and metadata: 1 (no crowdrl.format_version) wrote the greedy Q policy only,
# 2 adds the planner, crowdrl.format_version, crowdrl.observation, crowdrl.policy and crowdrl.planning_*
# (and, later, the *_lidar layouts with crowdrl.lidar_rays and crowdrl.lidar_range: new layouts, same format)
FORMAT_VERSION = 2
# crowdrl.observation: the inputs each layout takes (a network reading the scan: the same, then "lidar")
_BASE_LAYOUTS = {"world": PLANNER_INPUTS, "world_obstacles": PLANNER_OBSTACLE_INPUTS, "robot_centric": INPUTS,
                 "entities": ENTITY_INPUTS}
LAYOUTS = {**_BASE_LAYOUTS, **{f"{k}_lidar": (*v, LIDAR_INPUT) for k, v in _BASE_LAYOUTS.items()}}
FORMATS = ("onnx",)
DEFAULT_OPSET = 17
# encoders whose exported graph holds the crowd size as a constant (a loop unrolled over the humans)
FIXED_CROWD_ENCODERS = ("lstm_rl",)


class GreedyQPolicy(nn.Module):
    """``(robot_rc [B, 9], humans_rc [B, N, 5], humans_mask [B, N]) -> (Q [B, 81], greedy action [B],
    command [B, 2])``: the Q network, its argmax and that action's ``(speed, rotation)`` row of ``table``."""

    def __init__(self, net: nn.Module, table: Tensor) -> None:
        super().__init__()
        if table.shape != (NUM_ACTIONS, 2):
            raise ValueError(f"the action table must be shaped [{NUM_ACTIONS}, 2], got {tuple(table.shape)}")
        self.net = net
        self.register_buffer("table", table.to(torch.float32))

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor, *lidar: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        q = self.net(robot_rc, humans_rc, humans_mask, *lidar)  # lidar: [B, R], for a network that reads the scan
        action = q.argmax(dim=-1)
        return q, action, self.table[action]


class PlannerPolicy(nn.Module):
    """``(robot [B, 9], humans [B, N, 5], humans_mask [B, N][, obstacles [B, K, 4], obstacles_mask [B, K]][,
    lidar [B, R]]) -> (Q [B, 81], action [B], command [B, 2], candidates [B, w], scores [B, w])``:
    :meth:`OnlinePlanner.plan <crowdrl.policies.OnlinePlanner.plan>` on world-frame states (deterministic: the
    network in eval mode), and the action's row of the action table. A planner of a network trained among
    obstacles (``entities``) takes the observed edges, as the env gives them."""

    def __init__(self, planner: OnlinePlanner) -> None:
        super().__init__()
        self.planner = planner

    def forward(self, robot: Tensor, humans: Tensor, humans_mask: Tensor, *rest: Tensor
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        obstacles = obstacles_mask = None
        if self.planner.entities:
            obstacles, obstacles_mask, *rest = rest
        plan = self.planner.plan(robot, humans, humans_mask, obstacles, obstacles_mask,
                                 lidar=rest[0] if rest else None)
        return plan.action_value, plan.action, self.planner.table[plan.action], plan.candidates, plan.scores


@dataclass
class ExportInfo:
    """What :func:`export_onnx` wrote: the file, its metadata, and notes for the user (e.g. planning)."""

    path: Path
    metadata: dict[str, str]
    planning_dropped: bool = False  # the checkpoint plans online; the model is its Q policy without planning
    planner: bool = False  # the model holds the online planner (world-frame inputs, PLANNER_OUTPUTS)
    notes: list[str] = field(default_factory=list)
    max_q_error: float | None = None  # onnxruntime vs torch on random inputs (None: not checked)
    actions_differing: int = 0  # of the check's planner actions, those that differ from torch's on a near-tie


def check_writable(path: Path | str, name: str = "out") -> Path:
    """``path`` as a :class:`Path` if a file can be written there; else ``ValueError`` naming ``name``."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{name}: {path} is a directory; give a file name, e.g. {name}={path / 'policy.onnx'}")
    for folder in (path.parent, *path.parent.parents):  # the nearest that exists must be a folder
        if folder.exists():
            if not folder.is_dir():
                raise ValueError(f"{name}: cannot write {path}: {folder} is a file, not a folder")
            break
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".probe")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ValueError(f"{name}: cannot write {path}: {exc.strerror or exc}") from None
    return path


def export_onnx(checkpoint: Path | str, path: Path | str, *, opset: int = DEFAULT_OPSET, check: bool = True,
                planning: dict[str, int | None] | None = None) -> ExportInfo:
    """Write the acting policy of ``checkpoint`` (a run folder or a ``.pt``) to ``path`` as ONNX: its online
    planner whole when it acts with one (:class:`PlannerPolicy`), else its greedy Q policy.

    ``planning``: the planner settings ``depth``, ``width``, ``safety_horizon``, ``progress_bias`` to export instead of the
    checkpoint's (``None`` values: its own); ``depth`` 0 exports the greedy Q policy of a planning checkpoint
    (it acts differently: noted in :attr:`ExportInfo.notes` and the metadata). Uses torch's TorchScript-based
    exporter (``dynamo=False``). With ``check`` (and onnxruntime installed) the written model is run on random
    observations and compared with the torch policy: Q (and the planner's scores) differing by more than
    1e-4, or a planner action differing where the scores do not tie within 1e-4, raises ``RuntimeError``.
    Raises :class:`~crowdrl.training.CheckpointError` naming the file for a missing, corrupt or unsafe
    checkpoint, ``ValueError`` naming the key for a path that cannot be written (``out``), bad planner
    settings (``planning_<key>``) or a planner the export cannot hold (trained among obstacles).
    """
    try:
        import onnx
    except ImportError:
        raise RuntimeError("exporting needs the onnx package: pip install 'crowdrl[export]'") from None
    from crowdrl.training.pipeline import act_with

    ckpt = checkpoint_path(checkpoint)
    run, net, data = load_trained_network(ckpt)
    trained = run
    acting = {k: v for k, v in (planning or {}).items() if v is not None}
    if acting:
        run = act_with(run, acting, prefix="planning_")
    entities = sees_obstacles(run)
    plans = run.planning.enabled
    path = check_writable(path)
    crowd = crowd_config(run)
    scan = (crowd.lidar_rays, crowd.lidar_range) if run.encoder.lidar != "off" else None  # the network's scan input
    low, high = crowd.min_humans or crowd.num_humans, crowd.num_humans
    fixed_crowd = run.encoder.name in FIXED_CROWD_ENCODERS
    table = action_table(crowd.robot_v_pref)
    if plans:
        predictor = load_trained_predictor(run, data, ckpt)
        p = run.planning
        policy: nn.Module = PlannerPolicy(OnlinePlanner(net, predictor, crowd, gamma=run.train.gamma, depth=p.depth,
                                                        width=p.width, safety_horizon=p.safety_horizon,
                                                        progress_bias=p.progress_bias, entities=entities,
                                                        lidar_key=LIDAR_INPUT if scan else None)).eval()
        outputs, layout, width = PLANNER_OUTPUTS, "world_obstacles" if entities else "world", 5
    else:
        policy = GreedyQPolicy(net, table).eval()
        width = ENTITY_DIM if entities else 5
        outputs, layout = OUTPUTS, "entities" if entities else "robot_centric"
    layout += "_lidar" if scan else ""
    inputs = LAYOUTS[layout]
    edges = map_extent(run)[0] if entities else 0  # the observed edges it trained with (a mix's: the most)
    rows = high + edges  # the slots an unrolled LSTM-RL takes
    if plans:
        example = _random_world(2, high, seed=0) + _random_edges(2, edges if entities else 0, seed=0)
    else:
        example = _random_observations(2, rows, seed=0, width=width)
    example += _random_scans(2, scan, seed=0)
    axes = {name: {0: "batch"} for name in (*inputs, *outputs)}
    if not fixed_crowd:
        axes[inputs[1]][1] = axes[inputs[2]][1] = "entities" if entities and not plans else "humans"
        if plans and entities:
            axes["obstacles"][1] = axes["obstacles_mask"][1] = "edges"
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        # the shape checks of the encoders hold for every input the axes allow; the exporter's
        # deprecation notice is about torch's choice of default, not this call
        warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.onnx")
        torch.onnx.export(policy, example, buf, input_names=list(inputs), output_names=list(outputs),
                          dynamic_axes=axes, opset_version=opset, dynamo=False)
    model = onnx.load_from_string(buf.getvalue())

    notes: list[str] = []
    dropped = trained.planning.enabled and not plans
    p = run.planning
    if plans:
        planning_text = (f"on: the online planner, planning.depth={p.depth}, planning.width={p.width}, "
                         f"planning.safety_horizon={p.safety_horizon}, planning.progress_bias={p.progress_bias!r}, "
                         f"predictor={p.predictor}, gamma={run.train.gamma!r}")
    elif dropped:
        tp = trained.planning
        planning_text = (f"dropped (planning_depth=0): the checkpoint acts with online planning (planning.depth={tp.depth}, "
                         f"planning.width={tp.width}, predictor={tp.predictor}); this model is its greedy Q policy "
                         f"without planning, which acts differently")
        notes.append(f"GREEDY Q ONLY: planning_depth=0 drops the online planner {ckpt} acts with; {path} holds its "
                     f"greedy Q policy, which acts differently (evaluate both: docs/export.md)")
    else:
        planning_text = "off: the checkpoint acts greedily on Q"
    if fixed_crowd:
        notes.append(f"{run.encoder.name}: the model takes exactly {rows} {inputs[1]} rows "
                     f"(pad with {inputs[2]}=false)")
    if plans:
        described = ("robot [B,9] float32 (px, py, vx, vy, radius, gx, gy, v_pref, heading), humans [B,N,5] float32 "
                     "(px, py, vx, vy, radius), humans_mask [B,N] bool (True: present); all in the world frame "
                     "(the env's robot, humans, humans_mask)")
        if entities:
            described += (f", obstacles [B,K,4] float32 (the observed obstacle edges ax, ay, bx, by in the world frame, "
                          f"nearest first; trained with K={edges}), obstacles_mask [B,K] bool (True: present; the env's "
                          f"obstacles, obstacles_mask; an open scenario: one masked row)")
        outputs_text = (f"q_values [B,81] float32 (Q of the state), action [B] int64 (the planner's), command [B,2] "
                        f"float32 (speed m/s, rotation rad), candidates [B,{p.width}] int64 (top-{p.width} by Q, best "
                        f"first), scores [B,{p.width}] float32 (their look-ahead scores)")
    else:
        humans_text = ("humans_rc [B,N,5] float32 (px, py, vx, vy, radius + robot radius), humans_mask [B,N] bool "
                       "(True: present)")
        if entities:
            humans_text = (f"entities_rc [B,N+K,10] float32: N humans (px, py, vx, vy, radius + robot radius, 0, 0, 0, "
                           f"0, 0) then K obstacle edges (cx, cy, 0, 0, robot radius, ax, ay, bx, by, 1: c the edge's "
                           f"point nearest to the robot, a and b its ends; trained with K={crowd.num_obstacle_tokens}, "
                           f"the nearest first), entities_mask [B,N+K] bool (True: present)")
        described = ("robot_rc [B,9] float32 (0, 0, vx, vy, radius, goal distance, 0, v_pref, heading), "
                     f"{humans_text}; all in the robot's frame: origin at the robot, x towards the goal")
        outputs_text = ("q_values [B,81] float32, action [B] int64 (greedy, first of ties), "
                        "command [B,2] float32 (speed m/s, rotation rad)")
    if scan:
        described += (f", lidar [B,{scan[0]}] float32 (the env's lidar: ray r at heading + 2*pi*r/{scan[0]}, "
                      f"counter-clockwise, metres to the first wall or human, clipped at {scan[1]!r})")
    metadata = {
        "crowdrl.format_version": str(FORMAT_VERSION),
        "crowdrl.observation": layout,
        "crowdrl.policy": "planner" if plans else "greedy_q",
        "crowdrl.inputs": described,
        "crowdrl.outputs": outputs_text,
        "crowdrl.command": f"unicycle: turn by rotation, then move straight at speed for one time step of "
                           f"{crowd.time_step} s (angular rate = rotation / time_step)",
        "crowdrl.action_table": json.dumps(table.tolist()),
        "crowdrl.time_step": repr(crowd.time_step),
        "crowdrl.v_pref": repr(crowd.robot_v_pref),
        "crowdrl.humans": f"N={rows} fixed" if fixed_crowd else "N free (at least 1)",
        "crowdrl.num_humans": str(high),
        "crowdrl.trained_humans": f"{low}..{high}" if low < high else str(high),
        "crowdrl.encoder": run.encoder.name,
        "crowdrl.exploration": run.exploration.name,
        "crowdrl.planning": planning_text,
        "crowdrl.planning_depth": str(p.depth if plans else 0),
        "crowdrl.planning_width": str(p.width if plans else 0),
        "crowdrl.planning_safety_horizon": str(p.safety_horizon if plans else 0),
        "crowdrl.planning_progress_bias": repr(float(p.progress_bias) if plans else 0.0),
        "crowdrl.frames": str(data.get("frames", "unknown")),
        "crowdrl.fingerprint": config_fingerprint(to_dict(trained)),
        "crowdrl.config": json.dumps(to_dict(trained), sort_keys=True),
        "crowdrl.checkpoint": ckpt.name,
        **({"crowdrl.lidar_rays": str(scan[0]), "crowdrl.lidar_range": repr(scan[1])} if scan else {}),
    }
    onnx.helper.set_model_props(model, metadata)
    model.producer_name = "crowdrl"
    model.doc_string = (f"online planner (depth {p.depth}, width {p.width}) of a crowdrl checkpoint (docs/export.md)"
                        if plans else "greedy Q policy of a crowdrl checkpoint (docs/export.md)")
    onnx.checker.check_model(model)
    payload = model.SerializeToString()
    max_err, differing = None, 0
    if check and plans:
        max_err, differing = _check_planner_against_torch(payload, policy, high, fixed_crowd, scan, inputs, edges)
    elif check:
        max_err = _check_against_torch(payload, policy, rows, fixed_crowd, inputs, width, scan)
    try:
        atomic_write_bytes(path, payload)
    except OSError as exc:
        raise ValueError(f"out: cannot write {path}: {exc.strerror or exc}") from None
    return ExportInfo(path, metadata, planning_dropped=dropped, planner=plans, notes=notes, max_q_error=max_err,
                      actions_differing=differing)


@dataclass
class ExportedModel:
    """An exported model read back by :func:`read_exported`: its bytes, metadata and what they say."""

    path: Path
    payload: bytes
    metadata: dict[str, str]
    format_version: int
    layout: str  # a key of LAYOUTS
    run: RunConfig  # the checkpoint's config, its planner settings those of the model
    frames: int | None
    fixed_humans: int | None  # the N the model fixes (LSTM-RL), None: free

    @property
    def plans(self) -> bool:
        """Whether the model holds the online planner."""
        return self.metadata.get("crowdrl.policy") == "planner"

    @property
    def inputs(self) -> tuple[str, ...]:
        """The names of the model's inputs, in order."""
        return LAYOUTS[self.layout]

    def session(self, threads: int = 1):
        """An onnxruntime CPU session of the model with ``threads`` intra-op threads (one inter-op)."""
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = int(threads), 1
        return onnxruntime.InferenceSession(self.payload, options, providers=["CPUExecutionProvider"])


def planner_settings(metadata: dict[str, str]) -> dict[str, float]:
    """The planner settings an exported model's ``metadata`` holds (``crowdrl.planning_<key>``, one per
    :data:`~crowdrl.training.pipeline.ACT_KEYS`): integers, and the progress bias as a number >= 0 (0 for models
    written before it existed). ``KeyError`` or ``ValueError`` for a missing or malformed one.

    >>> planner_settings({"crowdrl.planning_depth": "1", "crowdrl.planning_width": "10",
    ...                   "crowdrl.planning_safety_horizon": "0"})
    {'depth': 1, 'width': 10, 'safety_horizon': 0, 'progress_bias': 0.0}
    """
    settings: dict[str, float] = {k: int(metadata[f"crowdrl.planning_{k}"]) for k in ("depth", "width", "safety_horizon")}
    bias = float(metadata.get("crowdrl.planning_progress_bias", "0.0"))
    if not math.isfinite(bias) or bias < 0:
        raise ValueError(f"crowdrl.planning_progress_bias: must be a finite number >= 0, got {bias!r}")
    return settings | {"progress_bias": bias}


def read_exported(path: Path | str) -> ExportedModel:
    """Read and check a model written by :func:`export_onnx`. Refused with
    :class:`~crowdrl.training.CheckpointError` naming the file and what differs: a missing, truncated or
    corrupt file, one without crowdrl's metadata, a newer format version, an observation layout this code
    does not know or inputs other than the layout's; ``ValueError`` when onnx or onnxruntime is missing."""
    try:
        import onnx
        import onnxruntime  # noqa: F401  (the model is run with it)
        from google.protobuf.message import DecodeError
    except ImportError:
        raise ValueError(f"checkpoint: {path}: reading an ONNX model needs onnx and onnxruntime: "
                         "pip install 'crowdrl[export]'") from None
    from crowdrl.training.compat import stored_config
    from crowdrl.training.config import ConfigError
    from crowdrl.training.validation import validate

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no ONNX model at {path} (write one with crowdrl-export)")
    payload = path.read_bytes()
    try:
        model = onnx.load_from_string(payload)
    except (DecodeError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{path} is not a complete ONNX model (truncated or corrupt: {str(exc)[:120]})") from None
    meta = {p.key: p.value for p in model.metadata_props}
    if "crowdrl.config" not in meta:
        raise CheckpointError(f"{path} holds no crowdrl metadata (crowdrl.config): truncated, or not written by "
                              "crowdrl-export")
    text = meta.get("crowdrl.format_version", "1")
    if not text.isdigit():
        raise CheckpointError(f"{path}: crowdrl.format_version {text!r} is not a version number")
    version = int(text)
    if version > FORMAT_VERSION:
        raise CheckpointError(f"{path}: format version {version} is newer than this crowdrl reads (up to "
                              f"{FORMAT_VERSION}); update crowdrl, or export the checkpoint again with this one")
    names = tuple(i.name for i in model.graph.input)
    if version == 1:  # the greedy Q policy; its layout is its inputs'
        layout = next((k for k, v in LAYOUTS.items() if v == names and k != "world"), "unknown")
        meta = {**meta, "crowdrl.policy": "greedy_q", "crowdrl.observation": layout}
    layout = meta.get("crowdrl.observation", "")
    if layout not in LAYOUTS:
        known = "; ".join(f"{k} ({', '.join(v)})" for k, v in LAYOUTS.items())
        raise CheckpointError(f"{path}: observation layout {layout!r} (inputs {', '.join(names)}) is not one this "
                              f"crowdrl reads: {known}")
    if names != LAYOUTS[layout]:
        raise CheckpointError(f"{path}: its inputs {', '.join(names)} differ from its observation layout {layout!r} "
                              f"({', '.join(LAYOUTS[layout])}): edited or foreign file")
    if (meta.get("crowdrl.policy") == "planner") != layout.startswith("world"):
        raise CheckpointError(f"{path}: crowdrl.policy {meta.get('crowdrl.policy')!r} does not fit observation layout "
                              f"{layout!r}: edited or foreign file")
    try:
        run = validate(stored_config(json.loads(meta["crowdrl.config"])), resources=False)
    except (ConfigError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: its config (crowdrl.config) cannot be rebuilt by this code version: "
                              f"{str(exc)[:200]}") from None
    from dataclasses import replace

    if meta.get("crowdrl.policy") == "planner":
        try:
            settings = planner_settings(meta)
        except (KeyError, ValueError):
            raise CheckpointError(f"{path}: its planner settings (crowdrl.planning_depth, _width, _safety_horizon "
                                  "integers, _progress_bias a number >= 0) are missing or malformed") from None
        run = replace(run, planning=replace(run.planning, enabled=True, **settings))
    else:
        run = replace(run, planning=replace(run.planning, enabled=False, safety_horizon=0, progress_bias=0.0))
    humans = meta.get("crowdrl.humans", "")
    fixed = int(humans[2:].split()[0]) if humans.startswith("N=") else None
    frames = meta.get("crowdrl.frames", "")
    return ExportedModel(path, payload, meta, version, layout, run, int(frames) if frames.isdigit() else None, fixed)


def _random_world(batch: int, humans: int, seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """Plausible world-frame observations ``(robot [B, 9], humans [B, N, 5], humans_mask [B, N])``: the robot
    and humans within a few metres, speeds about 1 m/s, goals a few metres away."""
    g = torch.Generator().manual_seed(seed)
    robot = torch.zeros(batch, 9)
    robot[:, 0:2] = torch.randn(batch, 2, generator=g) * 3
    robot[:, 2:4] = torch.randn(batch, 2, generator=g) * 0.5
    robot[:, 4] = 0.3
    robot[:, 5:7] = robot[:, 0:2] + torch.randn(batch, 2, generator=g) * 4
    robot[:, 7] = 1.0
    robot[:, 8] = (torch.rand(batch, generator=g) * 2 - 1) * torch.pi
    crowd = torch.cat((robot[:, None, 0:2] + torch.randn(batch, humans, 2, generator=g) * 3,
                       torch.randn(batch, humans, 2, generator=g) * 0.5, torch.full((batch, humans, 1), 0.3)), dim=-1)
    mask = torch.rand(batch, humans, generator=g) > 0.2
    mask[:, 0] = True
    return robot, crowd, mask


def _random_edges(batch: int, edges: int, seed: int) -> tuple[Tensor, ...]:
    """``(obstacles [B, K, 4], obstacles_mask [B, K])``: wall segments of 1-3 m within a few metres of the origin
    (where :func:`_random_world` puts the robot), some masked; ``()`` for ``edges`` 0."""
    if edges == 0:
        return ()
    g = torch.Generator().manual_seed(seed + 13)
    a = torch.randn(batch, edges, 2, generator=g) * 3
    b = a + torch.randn(batch, edges, 2, generator=g) * 1.5
    mask = torch.rand(batch, edges, generator=g) > 0.3
    mask[:, 0] = True
    return torch.cat((a, b), -1), mask


def _random_scans(batch: int, scan: tuple[int, float] | None, seed: int) -> tuple[Tensor, ...]:
    """``(lidar [B, R],)``: readings uniform in ``[0, range]`` for ``scan = (R, range)``; ``()`` without a scan."""
    if scan is None:
        return ()
    g = torch.Generator().manual_seed(seed + 7)
    return (torch.rand(batch, scan[0], generator=g) * scan[1],)


def _check_planner_against_torch(payload: bytes, policy: nn.Module, humans: int, fixed_crowd: bool,
                                 scan: tuple[int, float] | None = None, inputs: tuple[str, ...] = PLANNER_INPUTS,
                                 edges: int = 0) -> tuple[float | None, int]:
    """``(the largest Q or score difference, the actions that differ on near-ties)`` between onnxruntime and
    the torch planner on random world-frame states (``(None, 0)`` without onnxruntime); ``RuntimeError`` for a
    difference above 1e-4 or an action that differs where the scores do not tie within 1e-4."""
    try:
        import onnxruntime
    except ImportError:
        return None, 0
    session = onnxruntime.InferenceSession(payload, providers=["CPUExecutionProvider"])
    worst, differing = 0.0, 0
    for batch, n, k, seed in ((64, humans, edges, 1), (3, humans if fixed_crowd else max(1, humans // 2 + 1),
                                                          edges if fixed_crowd else max(1, edges // 2) * (edges > 0), 2)):
        obs = _random_world(batch, n, seed) + _random_edges(batch, k, seed) + _random_scans(batch, scan, seed)
        with torch.no_grad():
            q, action, _, cand, scores = policy(*obs)
        got = session.run(["q_values", "action", "scores"], dict(zip(inputs, (t.numpy() for t in obs))))
        worst = max(worst, float((torch.from_numpy(got[0]) - q).abs().max()),
                    float((torch.from_numpy(got[2]) - scores).abs().max()))
        differ = torch.from_numpy(got[1]) != action
        if differ.any():
            best = scores.amax(-1)
            theirs = scores.gather(-1, (cand == torch.from_numpy(got[1])[:, None]).long().argmax(-1, keepdim=True))
            if ((best - theirs.squeeze(-1))[differ] > 1e-4).any():
                raise RuntimeError("the exported planner's actions differ from torch's where the scores do not tie")
            differing += int(differ.sum())
    if worst > 1e-4:
        raise RuntimeError(f"the exported planner's Q values or scores differ from torch's by {worst:.2e} (> 1e-4)")
    return worst, differing


def _random_observations(batch: int, humans: int, seed: int, width: int = 5) -> tuple[Tensor, Tensor, Tensor]:
    """Plausible robot-frame observations (positions within a few metres, speeds about 1 m/s); with
    ``width`` 10, entity tokens (random edge columns)."""
    g = torch.Generator().manual_seed(seed)
    robot = torch.zeros(batch, 9)
    robot[:, 2:4] = torch.randn(batch, 2, generator=g) * 0.5
    robot[:, 4] = 0.3
    robot[:, 5] = torch.rand(batch, generator=g) * 8
    robot[:, 7] = 1.0
    robot[:, 8] = (torch.rand(batch, generator=g) * 2 - 1) * torch.pi
    crowd = torch.cat((torch.randn(batch, humans, 2, generator=g) * 3, torch.randn(batch, humans, 2, generator=g) * 0.5,
                       torch.full((batch, humans, 1), 0.6)), dim=-1)
    if width > 5:
        crowd = torch.cat((crowd, torch.randn(batch, humans, width - 5, generator=g)), dim=-1)
    mask = torch.rand(batch, humans, generator=g) > 0.2
    mask[:, 0] = True
    return robot, crowd, mask


def _check_against_torch(payload: bytes, policy: GreedyQPolicy, humans: int, fixed_crowd: bool,
                         inputs: tuple[str, ...] = INPUTS, width: int = 5, scan: tuple[int, float] | None = None
                         ) -> float | None:
    """The largest Q difference between onnxruntime and torch on random inputs (None without onnxruntime)."""
    try:
        import onnxruntime
    except ImportError:
        return None
    session = onnxruntime.InferenceSession(payload, providers=["CPUExecutionProvider"])
    worst = 0.0
    for batch, n, seed in ((64, humans, 1), (3, humans if fixed_crowd else max(1, humans // 2 + 1), 2)):
        obs = _random_observations(batch, n, seed, width) + _random_scans(batch, scan, seed)
        with torch.no_grad():
            q = policy(*obs)[0]
        got = session.run(["q_values"], dict(zip(inputs, (t.numpy() for t in obs))))[0]
        worst = max(worst, float((torch.from_numpy(got) - q).abs().max()))
    if worst > 1e-4:
        raise RuntimeError(f"the exported model's Q values differ from torch's by {worst:.2e} (> 1e-4)")
    return worst


__all__ = ["DEFAULT_OPSET", "ENTITY_INPUTS", "FIXED_CROWD_ENCODERS", "FORMATS", "FORMAT_VERSION", "INPUTS",
           "LAYOUTS", "LIDAR_INPUT",
           "OUTPUTS", "PLANNER_INPUTS", "PLANNER_OUTPUTS", "ExportInfo", "ExportedModel", "GreedyQPolicy",
           "PlannerPolicy", "check_writable", "export_onnx", "read_exported"]
