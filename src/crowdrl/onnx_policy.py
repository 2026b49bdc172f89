"""A policy exported to ONNX (:mod:`crowdrl.export`) acting in a crowdrl env through onnxruntime: the
module ``evaluate.py checkpoint=<file>.onnx`` rolls out with ``env.rollout``, as it rolls out a checkpoint's
torch actor. Needs onnx and onnxruntime (``pip install 'crowdrl[export]'``); not imported by
:mod:`crowdrl.policies`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from crowdrl.evaluation.rollout import crowd_env_of
from crowdrl.export import ExportedModel, read_exported


class OnnxPolicy(TensorDictModuleBase):
    """An exported model's policy on a crowdrl env's tensordicts: feeds the model the keys of its observation
    layout (the world-frame ``robot``, ``humans`` of the planner; the robot-centric ``robot_rc``, ``humans_rc``
    of a greedy model), with the env's ``humans_mask`` (all present when the env has none) and ``lidar`` when the
    network reads the scan, and writes
    ``"action"`` ``[*]``, ``"action_value"`` ``[*, 81]`` and ``"chosen_action_value"`` ``[*, 1]`` as the torch
    actors do. Deterministic: the model is the evaluation policy (no exploration).

    Args:
        model: the model, read by :func:`~crowdrl.export.read_exported` (or a path to read).
        threads: onnxruntime's intra-op threads.
    """

    def __init__(self, model: ExportedModel | Path | str, threads: int = 1) -> None:
        super().__init__()
        self.model = model if isinstance(model, ExportedModel) else read_exported(model)
        self.session = self.model.session(threads)
        self.in_keys = list(self.model.inputs)
        self.out_keys = ["action", "action_value", "chosen_action_value"]

    def check_env(self, env: EnvBase, num_humans_key: str = "eval.num_humans", scenario_key: str = "env") -> None:
        """``ValueError`` naming the key when ``env`` gives the model other observations than it was exported
        for: another crowd size than a fixed-N model's (LSTM-RL), obstacles the exported planner would not see,
        or a network trained among obstacles in an open scenario."""
        cfg = crowd_env_of(env).config
        path = self.model.path
        rows = cfg.num_humans + (cfg.num_obstacle_tokens if self.model.layout.startswith("entities") else 0)
        if self.model.fixed_humans is not None and rows != self.model.fixed_humans:
            raise ValueError(f"{num_humans_key}: {path} takes exactly {self.model.fixed_humans} rows of humans "
                             f"(and obstacle edges; {self.model.run.encoder.name}), the env gives {rows}")
        if self.model.plans and cfg.num_obstacle_tokens > 0 and "obstacles" not in self.in_keys:
            raise ValueError(f"{scenario_key}: {path} holds an online planner that reads no obstacle edges; "
                             f"{cfg.scenario} has obstacles, which the checkpoint's planner would see: evaluate "
                             "the checkpoint instead")
        rays = int(self.model.metadata.get("crowdrl.lidar_rays", 0))
        if rays and cfg.lidar_rays != rays:
            raise ValueError(f"{scenario_key}.lidar_rays: {path} reads a lidar scan of {rays} rays, the env gives "
                             f"{cfg.lidar_rays}")
        if cfg.robot_kinematics != "unicycle":
            raise ValueError(f"{scenario_key}: {path} acts with the unicycle's 81 actions, the env's robot is "
                             f"{cfg.robot_kinematics}")

    def feeds(self, tensordict: TensorDictBase) -> dict[str, np.ndarray]:
        """The model's inputs from ``tensordict`` (flattened to one batch axis): a missing humans' mask is all
        present; missing obstacle edges (an open scenario, for a planner trained among obstacles) are one masked
        edge."""
        names = self.in_keys
        first = tensordict.get(names[0])
        lead = first.shape[:-1]
        given: dict[str, torch.Tensor] = {}
        for name in names:
            value = tensordict.get(name, None)
            if value is None and name == "obstacles":
                value = torch.zeros(*lead, 1, 4)
            if value is None and name.endswith("_mask"):  # a fixed crowd, or no edges: every row present / absent
                rows = given[name[:-len("_mask")]]
                value = torch.full(rows.shape[:-1], name != "obstacles_mask", dtype=torch.bool)
            given[name] = value.to("cpu", torch.bool if name.endswith("_mask") else torch.float32)
        return {name: value.reshape(-1, *value.shape[len(lead):]).numpy() for name, value in given.items()}

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        lead = tensordict.get(self.in_keys[0]).shape[:-1]
        q, action = self.session.run(["q_values", "action"], self.feeds(tensordict))
        device = tensordict.device
        q = torch.from_numpy(q).reshape(*lead, -1).to(device)
        action = torch.from_numpy(action).reshape(lead).to(device)
        tensordict.set("action", action)
        tensordict.set("action_value", q)
        tensordict.set("chosen_action_value", q.gather(-1, action.unsqueeze(-1)))
        return tensordict


class ComparedPolicy(TensorDictModuleBase):
    """Acts with ``reference`` (the checkpoint's torch actor) and, on every step's observation, asks ``exported``
    too: counts the steps of running episodes, those where the two actions are identical, and those where
    they differ by float rounding only (the exported model's own scores, or Q for a greedy model, of the two
    actions within ``tie`` of each other)."""

    def __init__(self, reference: TensorDictModuleBase, exported: OnnxPolicy, tie: float = 1e-4) -> None:
        super().__init__()
        self.reference, self.exported, self.tie = reference, exported, float(tie)
        self.in_keys = list(dict.fromkeys([*reference.in_keys, *exported.in_keys]))
        self.out_keys = list(reference.out_keys)
        self.steps = self.identical = self.rounding = 0

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.reference(tensordict)
        want = tensordict.get("action").reshape(-1).cpu().numpy()
        names = ["q_values", "action"] + (["candidates", "scores"] if self.exported.model.plans else [])
        out = dict(zip(names, self.exported.session.run(names, self.exported.feeds(tensordict))))
        done = tensordict.get("done", None)
        live = np.ones(len(want), bool) if done is None else ~done.reshape(-1).cpu().numpy()
        got = out["action"]
        if self.exported.model.plans:  # the torch action's score in the exported model (-inf: not a candidate)
            hit = out["candidates"] == want[:, None]
            theirs = np.where(hit.any(-1), np.where(hit, out["scores"], -np.inf).max(-1), -np.inf)
            gap = out["scores"].max(-1) - theirs
        else:
            rows = np.arange(len(want))
            gap = out["q_values"][rows, got] - out["q_values"][rows, want]
        same = got == want
        self.steps += int(live.sum())
        self.identical += int((same & live).sum())
        self.rounding += int((~same & live & (gap <= self.tie)).sum())
        return tensordict


__all__ = ["ComparedPolicy", "OnnxPolicy"]
