"""Counterfactual experience: from each sampled state, the transitions of actions the robot did not take.

For a sampled transition ``(s, a, r, s')`` and ``k`` alternative actions ``a'`` it builds
``(s, a', r', s'_a', terminated')`` exactly as the environment would have returned them:

* the robot's next state by the simulator's one-step model (:func:`crowdrl.sim.lookahead.look_ahead`:
  the unicycle kinematics, the reward, collision and goal of :func:`crowdrl.sim.crowd.step_reward`
  against the humans' motion over that step, and the episode's walls in obstacle scenarios);
* the humans' next state is the **real** one stored with the transition: exact because the humans
  ignore the robot (ORCA with an invisible robot), so their step is the same whatever it does;
* the next observation through the env's own transform (:class:`crowdrl.envs.RobotCentric`, and
  the observed obstacle edges re-selected from the new position, as the env does; a network that reads
  the lidar scan gets the env's own scan from the new pose, :func:`crowdrl.sim.lidar.robot_scan` against
  the episode's walls and the humans' real next discs);
* ``terminated' = collided or reached``; a timeout stays a truncation (the target bootstraps), and
  the bootstrap discount is ``γ`` (one step).

Alternatives: ``topk`` by the online Q (SG-D3QN's ``expand_width = 5``), ``all`` 81 actions, or
``random``: ``k`` distinct actions per state from the part's own generator (seeded; saved for resume).

Two arrangements (:class:`~crowdrl.training.parts.UpdatePart`): ``second_update`` (SG-D3QN's
trainer: after the real double-DQN step, a second one on the ``B·k`` counterfactual transitions,
the top-k chosen by the network the real step updated) and ``merged`` (one step on
``(1 - weight) · mean_real + weight · mean_counterfactual``). An intrinsic bonus (ICM, RE3) is added
to the counterfactual rewards too, as upstream does, without training the bonus on them.
Where upstream differs: its ``done`` is always false and its reward estimator is its own copy of the
reward; here both are the simulator's (exact).
"""

from __future__ import annotations

from typing import Any, Callable, Iterator, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn

from crowdrl.compile import CompiledModule
from crowdrl.envs.robot_centric import RobotCentric
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, wrap_angle
from crowdrl.sim.lidar import robot_scan
from crowdrl.sim.lookahead import look_ahead
from crowdrl.sim.obstacles import nearest_edges, obstacle_segments
from crowdrl.training.facts import LIDAR_KEY
from crowdrl.training.loss import WEIGHT_KEY
from crowdrl.training.parts import UpdatePart

MODES = ("second_update", "merged")
ACTIONS = ("topk", "all", "random")
WORLD_KEYS: list[NestedKey] = ["robot", "humans", ("next", "humans")]  # the world-frame state and the humans' next
MAP_KEYS: list[NestedKey] = ["obstacle_polygons", "obstacle_polygons_mask"]  # the episode's walls (obstacle scenarios)


class CounterfactualExperience(UpdatePart):
    """Counterfactual transitions of a sampled batch and the update arrangement that learns from them.

    Args:
        config: the simulator's constants of the training env (unicycle robot, humans ignoring it).
        net: the online Q network (``net(*obs) -> [B, 81]``), read by ``actions="topk"``.
        obs_keys: the keys the network reads (the loss's).
        mode: ``"second_update"`` or ``"merged"``; actions: ``"topk"``, ``"all"`` or ``"random"``;
        k: alternatives per state (``all``: 81); weight: ``merged``'s weight of the counterfactual terms.
        entities: the network reads entity tokens (humans and obstacle edges), as among obstacles.
        seed: seeds the generator of ``actions="random"``.
        reward_bonus: adds an intrinsic bonus to a batch's ``("next", "reward")`` (the run's
            :meth:`~crowdrl.exploration.IntrinsicRewardTransform.add_bonus`, not training the bonus).
        one_step_key: where the run's buffer keeps the one-step successor ``s_{t+1}`` (n-step returns
            with an intrinsic bonus: :data:`crowdrl.training.variants.ONE_STEP_KEY`); the
            counterfactual transitions hold their next observation there too, for the bonus to read.
        obstacle_tokens: the edges the robot observes from a new pose (``None``: ``config``'s; a scenario mix's
            largest, :func:`~crowdrl.training.config.map_extent`).
        compile: ``topk``'s forward pass through ``torch.compile`` (:class:`~crowdrl.compile.CompiledModule`, the
            network's own parameters; ``train.compile_acting``, as the other forward passes without gradient):
            Q equal to eager's to float rounding.

    Example::

        part = CounterfactualExperience(env_config, net, ["robot_rc", "humans_rc"], k=5)
        for name, batch in part.batches(buffer.sample()):   # "real", then "counterfactual" ([100, 5])
            loss.loss_and_grad(batch); optimizer.step()
    """

    def __init__(self, config: CrowdConfig, net: nn.Module, obs_keys: Sequence[str], *, mode: str = "second_update",
                 actions: str = "topk", k: int = 5, weight: float = 0.5, entities: bool = False, seed: int = 0,
                 reward_bonus: Callable[[TensorDictBase], TensorDictBase] | None = None,
                 one_step_key: str | None = None, obstacle_tokens: int | None = None, compile: bool = False) -> None:
        if mode not in MODES:
            raise ValueError(f"mode: got {mode!r}; allowed: {', '.join(MODES)}")
        if actions not in ACTIONS:
            raise ValueError(f"actions: got {actions!r}; allowed: {', '.join(ACTIONS)}")
        if isinstance(k, bool) or int(k) != k or not 1 <= k <= NUM_ACTIONS:
            raise ValueError(f"k: must be an integer in 1..{NUM_ACTIONS}, got {k!r}")
        if not 0.0 <= weight <= 1.0:
            raise ValueError(f"weight: must lie in [0, 1], got {weight}")
        if config.robot_kinematics != "unicycle":
            raise ValueError(f"counterfactual experience needs the unicycle's discrete actions, got "
                             f"{config.robot_kinematics!r}")
        if config.humans_react_to_robot:
            raise ValueError("counterfactual experience replays the humans' real next state, exact only while they "
                             "ignore the robot; with this config's visible robot they react to it")
        self.config, self.net, self.obs_keys = config, net, list(obs_keys)
        # the Q values that rank the alternatives: ~3x faster compiled than eager at a batch of 100 (1 thread)
        self.q = CompiledModule(net, what="the counterfactual top-k") if compile else net
        self.mode, self.actions, self.weight = mode, actions, float(weight)
        self.k = NUM_ACTIONS if actions == "all" else int(k)
        self.reward_bonus, self.one_step_key = reward_bonus, one_step_key
        self.observe = RobotCentric(entities=entities)
        self.table = action_table(config.robot_v_pref)
        # the edges observed from a new pose: config's K, or a scenario mix's (the most of its scenarios; padded)
        self.obstacle_tokens = config.num_obstacle_tokens if obstacle_tokens is None else int(obstacle_tokens)
        self.has_map = self.obstacle_tokens > 0
        self.generator = torch.Generator().manual_seed(int(seed))
        self._scalars: dict[str, float] = {}

    # ------------------------------------------------------------------ UpdatePart
    def stored_keys(self) -> list[NestedKey]:
        return [*WORLD_KEYS, *(["humans_mask"] if self.config.variable_crowd else []),
                *(MAP_KEYS if self.has_map else [])]

    def batches(self, sample: TensorDictBase) -> Iterator[tuple[str, TensorDictBase]]:
        if self.mode == "second_update":
            yield "real", sample
            yield "counterfactual", self.counterfactual_batch(sample)  # top-k by the network just updated
            return
        fake = self.counterfactual_batch(sample)  # [B, k]
        real = sample.select(*fake.keys(include_nested=True, leaves_only=True)).unsqueeze(1)  # [B, 1]: same states
        B, k = fake.batch_size
        real.set(WEIGHT_KEY, torch.full((B, 1), (1.0 - self.weight) / B, device=real.device))
        fake.set(WEIGHT_KEY, torch.full((B, k), self.weight / (B * k), device=fake.device))
        yield "merged", torch.cat([real, fake], dim=1)  # [B, 1 + k]: column 0 the real transition

    def scalars(self) -> dict[str, float]:
        return dict(self._scalars)

    def state_dict(self) -> dict[str, Any]:
        # the last update's scalars reach the next logged row, even one logged before any update of a resumed run
        return {"generator": self.generator.get_state(), "scalars": dict(self._scalars)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])
        self._scalars = {str(k): float(v) for k, v in state.get("scalars", {}).items()}  # older checkpoints: none

    # ------------------------------------------------------------------ the transitions
    @torch.no_grad()
    def alternatives(self, sample: TensorDictBase) -> Tensor:
        """The ``k`` alternative actions ``[B, k]`` of each sampled state."""
        B = sample.batch_size[0]
        device = sample.device if sample.device is not None else sample.get("robot").device
        if self.actions == "all":
            return torch.arange(NUM_ACTIONS, device=device).expand(B, NUM_ACTIONS)
        if self.actions == "random":  # k distinct actions: the first k of a random permutation
            return torch.rand(B, NUM_ACTIONS, generator=self.generator).argsort(-1)[:, :self.k].to(device)
        q = self.q(*(sample.get(key) for key in self.obs_keys))
        return q.topk(self.k, dim=-1).indices

    @torch.no_grad()
    def transitions(self, sample: TensorDictBase, actions: Tensor) -> TensorDictBase:
        """The ``B·k`` transitions ``(s, a', r', s'_a', terminated')`` of ``actions [B, k]`` from the
        sampled states, as a tensordict shaped ``[B, k]`` (``[i, j]``: state ``i``, action
        ``actions[i, j]``; the state's observation is a view shared along ``k``, which the loss
        encodes once)."""
        cfg = self.config
        B, k = actions.shape
        robot, humans, humans_next = (sample.get(key) for key in WORLD_KEYS)
        mask = sample.get("humans_mask") if cfg.variable_crowd else None
        walls = walls_mask = None
        if self.has_map:
            walls, walls_mask = sample.get(MAP_KEYS[0]), sample.get(MAP_KEYS[1])
        step = look_ahead(cfg, self.table.to(robot.device), robot, humans, humans_next, actions, mask, walls, walls_mask)
        robot_next = step.robot_next.reshape(B * k, -1)
        robot_next = torch.cat((robot_next[:, :8], wrap_angle(robot_next[:, 8:9])), -1)  # as the simulator stores it

        def repeat(x: Tensor) -> Tensor:  # [B, ...] -> [B*k, ...], each row k times
            return x.repeat_interleave(k, dim=0)

        nxt = TensorDict({"robot": robot_next, "humans": repeat(humans_next)}, [B * k])
        if mask is not None:
            nxt.set("humans_mask", repeat(mask))
        if self.has_map:  # the edges the robot observes from its new position
            edges, edges_mask = nearest_edges(robot_next[:, 0:2], repeat(walls), repeat(walls_mask),
                                              self.obstacle_tokens)
            nxt.set("obstacles", edges)
            nxt.set("obstacles_mask", edges_mask)
        nxt = self.observe(nxt)
        if LIDAR_KEY in self.obs_keys:  # the scan from the new pose, as the env computes it
            segments = obstacle_segments(repeat(walls), repeat(walls_mask)) if self.has_map else None
            nxt.set(LIDAR_KEY, robot_scan(cfg, robot_next[:, 0:2], robot_next[:, 8], repeat(humans_next)[..., 0:2],
                                          None if mask is None else repeat(mask), segments))

        def grouped(x: Tensor) -> Tensor:  # [B*k, ...] -> [B, k, ...]
            return x.reshape(B, k, *x.shape[1:])

        def shared(x: Tensor) -> Tensor:  # [B, ...] -> [B, k, ...]: the state, read once by the loss
            return x.unsqueeze(1).expand(B, k, *x.shape[1:])

        judged = step.judged
        terminated = grouped((judged.collided | judged.reached).reshape(B * k, 1))
        reward = sample.get(("next", "reward"))
        action = sample.get("action")
        out = TensorDict({
            **{key: shared(sample.get(key)) for key in self.obs_keys},
            "action": actions.reshape(B, k, *action.shape[1:]).to(action.dtype),
            "steps_to_next_obs": torch.ones(B, k, 1, dtype=torch.int64, device=robot.device),
            "next": {**{key: grouped(nxt.get(key)) for key in self.obs_keys},
                     "reward": judged.reward.reshape(B, k, *reward.shape[1:]).to(reward.dtype),
                     "terminated": terminated, "done": terminated.clone()},
        }, [B, k], device=sample.device)
        if self.one_step_key is not None:  # one step: the successor the bonus reads is the next observation
            for key in self.obs_keys:
                out.set((self.one_step_key, key), out.get(("next", key)))
        self._scalars = {"counterfactual_collision_rate": float(judged.collided.float().mean()),
                         "counterfactual_goal_rate": float(judged.reached.float().mean()),
                         "counterfactual_reward": float(judged.reward.mean())}
        return out

    def counterfactual_batch(self, sample: TensorDictBase) -> TensorDictBase:
        """:meth:`transitions` of :meth:`alternatives`, with the intrinsic bonus when the run has one."""
        out = self.transitions(sample, self.alternatives(sample))
        if self.reward_bonus is None:
            return out
        # [B, k]: k transitions from each sampled state (a bonus may read each state once, as ICM does); on a
        # shallow copy (no tensor copied), which the bonus fills with its own entries: the batch keeps the loss's keys
        out.set(("next", "reward"), self.reward_bonus(out.clone(recurse=False)).get(("next", "reward")))
        return out


__all__ = ["ACTIONS", "MAP_KEYS", "MODES", "WORLD_KEYS", "CounterfactualExperience"]
