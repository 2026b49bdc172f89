"""Export a trained checkpoint's greedy Q policy to ONNX, to run on a robot without torch
(``docs/export.md``; ``experiments/export.py`` is the command line).

The model takes the observation as the Q actor reads it, in the robot's goal-aligned frame
(:func:`crowdrl.envs.robot_centric.robot_centric`), with a batch axis ``B``:

* ``robot_rc`` ``[B, 9]`` float32: ``0, 0, vx, vy, radius, goal distance, 0, v_pref, heading``;
* ``humans_rc`` ``[B, N, 5]`` float32: each human's ``px, py, vx, vy, radius + robot radius``;
* ``humans_mask`` ``[B, N]`` bool: True where a row is a human present (absent rows are ignored:
  the networks are padding-invariant, so ``N`` slots may hold fewer people).

A checkpoint trained among obstacles (corridor, doorway, room) takes the entity tokens of
:func:`crowdrl.envs.robot_centric.entity_tokens` instead of the humans: ``entities_rc``
``[B, N+K, 10]`` (the humans, then the observed obstacle edges) and ``entities_mask`` ``[B, N+K]``.

It returns ``q_values`` ``[B, 81]``, the greedy ``action`` ``[B]`` (int64, the first of tied
maxima, as ``torch.argmax``) and its ``command`` ``[B, 2]``: the row of the unicycle action table
(:func:`crowdrl.sim.kinematics.action_table`), ``(speed m/s, rotation rad)``: turn by the
rotation, then move straight at the speed for one time step. ``N`` is free for every encoder
but LSTM-RL, whose recurrence is unrolled over the checkpoint's largest crowd (``N`` is then fixed;
pad with absent rows). Online planning (``planning.enabled``) needs the crowd predictor and
the simulator's reward in a search, and is not exported: such a checkpoint exports its Q policy,
and the model's metadata says so.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor, nn

from crowdrl.files import atomic_write_bytes
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table
from crowdrl.training.checkpoint import checkpoint_path, config_fingerprint, load_trained_network
from crowdrl.envs.robot_centric import ENTITY_DIM
from crowdrl.training.config import sees_obstacles, to_dict
from crowdrl.training.factories import crowd_config

INPUTS = ("robot_rc", "humans_rc", "humans_mask")
ENTITY_INPUTS = ("robot_rc", "entities_rc", "entities_mask")  # a checkpoint trained among obstacles
OUTPUTS = ("q_values", "action", "command")
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

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        q = self.net(robot_rc, humans_rc, humans_mask)
        action = q.argmax(dim=-1)
        return q, action, self.table[action]


@dataclass
class ExportInfo:
    """What :func:`export_onnx` wrote: the file, its metadata, and notes for the user (e.g. planning)."""

    path: Path
    metadata: dict[str, str]
    planning_dropped: bool = False  # the checkpoint plans online; the model is its Q policy without planning
    notes: list[str] = field(default_factory=list)
    max_q_error: float | None = None  # onnxruntime vs torch on random inputs (None: not checked)


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


def export_onnx(checkpoint: Path | str, path: Path | str, *, opset: int = DEFAULT_OPSET,
                check: bool = True) -> ExportInfo:
    """Write the greedy Q policy of ``checkpoint`` (a run folder or a ``.pt``) to ``path`` as ONNX.

    Uses torch's TorchScript-based exporter (``dynamo=False``). With ``check`` (and onnxruntime
    installed) the written model is run on random observations and compared with the torch
    policy; a difference above 1e-4 in Q raises ``RuntimeError``. Raises
    :class:`~crowdrl.training.CheckpointError` naming the file for a missing, corrupt or unsafe
    checkpoint, ``ValueError`` naming ``out`` for a path that cannot be written.
    """
    try:
        import onnx
    except ImportError:
        raise RuntimeError("exporting needs the onnx package: pip install 'crowdrl[export]'") from None
    ckpt = checkpoint_path(checkpoint)
    run, net, data = load_trained_network(ckpt)
    path = check_writable(path)
    crowd = crowd_config(run)
    low, high = crowd.min_humans or crowd.num_humans, crowd.num_humans
    policy = GreedyQPolicy(net, action_table(crowd.robot_v_pref)).eval()
    fixed_crowd = run.encoder.name in FIXED_CROWD_ENCODERS
    entities = sees_obstacles(run)
    inputs, width = (ENTITY_INPUTS, ENTITY_DIM) if entities else (INPUTS, 5)
    rows = high + crowd.num_obstacle_tokens if entities else high  # the slots an unrolled LSTM-RL takes
    example = _random_observations(2, rows, seed=0, width=width)
    axes = {inputs[0]: {0: "batch"}, inputs[1]: {0: "batch"}, inputs[2]: {0: "batch"},
            "q_values": {0: "batch"}, "action": {0: "batch"}, "command": {0: "batch"}}
    if not fixed_crowd:
        axes[inputs[1]][1] = axes[inputs[2]][1] = "entities" if entities else "humans"
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        # the shape checks of the encoders hold for every input the axes allow; the exporter's
        # deprecation notice is about torch's choice of default, not this call
        warnings.simplefilter("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.onnx")
        torch.onnx.export(policy, example, buf, input_names=list(inputs), output_names=list(OUTPUTS),
                          dynamic_axes=axes, opset_version=opset, dynamo=False)
    model = onnx.load_from_string(buf.getvalue())

    notes: list[str] = []
    planning = "off: the checkpoint acts greedily on Q"
    if run.planning.enabled:
        p = run.planning
        planning = (f"not exported: the checkpoint acts with online planning (planning.depth={p.depth}, "
                    f"planning.width={p.width}, predictor={p.predictor}); this model is its greedy Q policy "
                    f"without planning, which may act differently")
        notes.append(f"planning is not exported: {ckpt} was trained with planning.enabled=true; {path} holds "
                     f"its greedy Q policy without the online planner")
    if fixed_crowd:
        notes.append(f"{run.encoder.name}: the model takes exactly {rows} {inputs[1]} rows "
                     f"(pad with {inputs[2]}=false)")
    described = ("humans_rc [B,N,5] float32 (px, py, vx, vy, radius + robot radius), humans_mask [B,N] bool "
                 "(True: present)")
    if entities:
        described = (f"entities_rc [B,N+K,10] float32: N humans (px, py, vx, vy, radius + robot radius, 0, 0, 0, 0, 0) "
                     f"then K obstacle edges (cx, cy, 0, 0, robot radius, ax, ay, bx, by, 1: c the edge's point "
                     f"nearest to the robot, a and b its ends; trained with K={crowd.num_obstacle_tokens}, the "
                     f"nearest first), entities_mask [B,N+K] bool (True: present)")
    metadata = {
        "crowdrl.inputs": "robot_rc [B,9] float32 (0, 0, vx, vy, radius, goal distance, 0, v_pref, heading), "
                          f"{described}; all in the robot's frame: origin at the robot, x towards the goal",
        "crowdrl.outputs": "q_values [B,81] float32, action [B] int64 (greedy, first of ties), "
                           "command [B,2] float32 (speed m/s, rotation rad)",
        "crowdrl.command": f"unicycle: turn by rotation, then move straight at speed for one time step of "
                           f"{crowd.time_step} s (angular rate = rotation / time_step)",
        "crowdrl.action_table": json.dumps(policy.table.tolist()),
        "crowdrl.time_step": repr(crowd.time_step),
        "crowdrl.v_pref": repr(crowd.robot_v_pref),
        "crowdrl.humans": f"N={high} fixed" if fixed_crowd else "N free (at least 1)",
        "crowdrl.trained_humans": f"{low}..{high}" if low < high else str(high),
        "crowdrl.encoder": run.encoder.name,
        "crowdrl.exploration": run.exploration.name,
        "crowdrl.planning": planning,
        "crowdrl.frames": str(data.get("frames", "unknown")),
        "crowdrl.fingerprint": config_fingerprint(to_dict(run)),
        "crowdrl.config": json.dumps(to_dict(run), sort_keys=True),
        "crowdrl.checkpoint": ckpt.name,
    }
    onnx.helper.set_model_props(model, metadata)
    model.producer_name, model.doc_string = "crowdrl", "greedy Q policy of a crowdrl checkpoint (docs/export.md)"
    onnx.checker.check_model(model)
    payload = model.SerializeToString()
    max_err = _check_against_torch(payload, policy, rows, fixed_crowd, inputs, width) if check else None
    try:
        atomic_write_bytes(path, payload)
    except OSError as exc:
        raise ValueError(f"out: cannot write {path}: {exc.strerror or exc}") from None
    return ExportInfo(path, metadata, planning_dropped=run.planning.enabled, notes=notes, max_q_error=max_err)


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
                         inputs: tuple[str, ...] = INPUTS, width: int = 5) -> float | None:
    """The largest Q difference between onnxruntime and torch on random inputs (None without onnxruntime)."""
    try:
        import onnxruntime
    except ImportError:
        return None
    session = onnxruntime.InferenceSession(payload, providers=["CPUExecutionProvider"])
    worst = 0.0
    for batch, n, seed in ((64, humans, 1), (3, humans if fixed_crowd else max(1, humans // 2 + 1), 2)):
        obs = _random_observations(batch, n, seed, width)
        with torch.no_grad():
            q = policy(*obs)[0]
        got = session.run(["q_values"], dict(zip(inputs, (t.numpy() for t in obs))))[0]
        worst = max(worst, float((torch.from_numpy(got) - q).abs().max()))
    if worst > 1e-4:
        raise RuntimeError(f"the exported model's Q values differ from torch's by {worst:.2e} (> 1e-4)")
    return worst


__all__ = ["DEFAULT_OPSET", "ENTITY_INPUTS", "FIXED_CROWD_ENCODERS", "FORMATS", "INPUTS", "OUTPUTS", "ExportInfo",
           "GreedyQPolicy", "check_writable", "export_onnx"]
