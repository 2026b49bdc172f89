"""``ScenarioMixEnv``: several scenarios stepped as one batch, for one agent that works in all of them.

Each scenario's rows are a :class:`~crowdrl.envs.CrowdNavEnv` of their own, with the scenario's own episode
stream: case *i* of a scenario is the case a single-scenario env of the same split and seed plays, whatever
the mix. The rows are stacked, in the order of ``rows``, into one ``[B]`` batch of a single observation layout:

* the obstacle keys are present whenever one scenario has obstacles. ``"obstacles"`` ``[B, K, 4]`` holds the
  ``K`` (the largest of the mix) nearest edges, and ``"obstacle_polygons"`` ``[B, P, V, 2]`` the largest map.
  Rows with fewer obstacles, open space included, are padded with zeros and masked (``False``).
* ``"scenario"`` ``[B, 1]`` int64 is each row's index in :data:`crowdrl.sim.config.SCENARIOS`, for statistics
  per scenario (no policy of crowdrl reads it).

Networks that read entity tokens (:class:`~crowdrl.envs.RobotCentric` with ``entities=True``) see the padded
edges as masked tokens, which take no part in attention.

>>> from crowdrl.sim.config import CrowdConfig
>>> env = ScenarioMixEnv({s: CrowdConfig(scenario=s, num_humans=4) for s in ("circle", "doorway")},
...                      {"circle": 2, "doorway": 1}, seed=0)
>>> td = env.reset()
>>> td["obstacles"].shape, td["obstacles_mask"].any(-1).tolist(), td["scenario"].flatten().tolist()
(torch.Size([3, 2, 4]), [False, False, True], [0, 0, 3])
>>> td["episode_id"].flatten().tolist()   # each scenario's own stream
[0, 1, 0]
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from crowdrl.envs.crowd_nav import CrowdNavEnv
from crowdrl.sim.config import SCENARIOS, CrowdConfig

OBSTACLE_OBS = ("obstacles", "obstacles_mask", "obstacle_polygons", "obstacle_polygons_mask")


def _batched(leaf, batch: int):
    """A copy of a scenario env's spec ``leaf`` ``[rows, ...]`` for ``batch`` rows."""
    out = leaf.clone()
    out.shape = torch.Size([batch, *leaf.shape[1:]])
    return out


def mix_rows(mix: Mapping[str, float], num_envs: int, key: str = "env.mix") -> dict[str, int]:
    """The rows of each scenario of ``mix`` (scenario -> proportion) among ``num_envs``, by largest remainder; a
    scenario of proportion 0 gets none. ``ValueError`` naming ``key`` for an unknown scenario, a negative or
    non-finite proportion, all zero, or a scenario left without a row.

    >>> mix_rows({"circle": 1, "square": 1, "doorway": 2}, 8)
    {'circle': 2, 'square': 2, 'doorway': 4}
    """
    for name, share in mix.items():
        if name not in SCENARIOS:
            raise ValueError(f"{key}: unknown scenario {name!r}; known: {', '.join(SCENARIOS)}")
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not math.isfinite(share) or share < 0:
            raise ValueError(f"{key}.{name}: a proportion must be a finite number >= 0, got {share!r}")
    total = float(sum(mix.values()))
    if total <= 0:
        raise ValueError(f"{key}: every proportion is 0; give at least one scenario a proportion > 0")
    exact = {name: num_envs * share / total for name, share in mix.items() if share > 0}
    rows = {name: math.floor(x) for name, x in exact.items()}
    by_remainder = sorted(exact, key=lambda name: (-(exact[name] - rows[name]), list(exact).index(name)))
    for name in by_remainder[:num_envs - sum(rows.values())]:
        rows[name] += 1
    empty = [name for name, n in rows.items() if n == 0]
    if empty:
        raise ValueError(f"{key}: scenario {empty[0]!r} gets no row of the {num_envs} envs at its proportion; raise "
                         f"train.num_envs or its proportion")
    return rows


class ScenarioMixEnv(EnvBase):
    """Scenarios ``configs`` (name -> :class:`CrowdConfig`), ``rows[name]`` envs each, stepped as one batch.

    The configs must differ in their scenario only (one crowd size, time step, reward, lidar for all). The
    env has :class:`CrowdNavEnv`'s observations, actions, rewards and done keys, the obstacle keys padded to the
    mix (module docstring) and ``"scenario"``; :meth:`load_episodes`, :meth:`snapshot` and :meth:`restore` act
    per scenario. ``config`` is the first scenario's (the constants all share).
    """

    SNAPSHOT_FORMAT = 1

    def __init__(self, configs: Mapping[str, CrowdConfig], rows: Mapping[str, int], *, seed: int = 0,
                 split: str = "train", device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> None:
        if set(configs) != set(rows) or not rows:
            raise ValueError(f"rows ({sorted(rows)}) must name the scenarios of configs ({sorted(configs)})")
        names = list(rows)
        for name in names:
            if configs[name].scenario != name:
                raise ValueError(f"configs[{name!r}] is a config of scenario {configs[name].scenario!r}")
            if isinstance(rows[name], bool) or not isinstance(rows[name], int) or rows[name] < 1:
                raise ValueError(f"rows[{name!r}] must be an integer >= 1, got {rows[name]!r}")
        first = configs[names[0]]
        shared = {f.name for f in dataclasses.fields(CrowdConfig)} - {"scenario"}
        for name in names[1:]:
            differ = sorted(k for k in shared if getattr(configs[name], k) != getattr(first, k))
            if differ:
                raise ValueError(f"configs: scenario {name!r} differs from {names[0]!r} in {', '.join(differ)}; a mix's "
                                 "scenarios share every other key")
        super().__init__(device=torch.device(device), batch_size=torch.Size([sum(rows.values())]))
        self.config = first
        self.rows = {name: int(rows[name]) for name in names}
        self.parts = {name: CrowdNavEnv(name, num_envs=self.rows[name], num_humans=first.num_humans,
                                        config=configs[name], seed=seed, split=split, device=self.device, dtype=dtype)
                      for name in names}
        bounds = torch.tensor([0, *self.rows.values()]).cumsum(0).tolist()
        self.slices = {name: slice(bounds[i], bounds[i + 1]) for i, name in enumerate(names)}
        shapes = [configs[name].obstacles_shape for name in names]
        self.obstacle_tokens = max(configs[name].num_obstacle_tokens for name in names)
        self.polygons_shape = (max(p for p, _ in shapes), max(v for _, v in shapes))
        self.split = split
        self._make_specs()

    @property
    def num_envs(self) -> int:
        return self.batch_size[0]

    @property
    def num_humans(self) -> int:
        return self.config.num_humans

    @property
    def started(self) -> bool:
        """Whether the env has been reset (it has episodes in flight)."""
        return all(part.started for part in self.parts.values())

    def current(self) -> TensorDictBase:
        """The observation of the episodes in flight, as a reset that resets none of them returns it."""
        return self._gather({name: self._kept(part, part.current()) for name, part in self.parts.items()})

    @property
    def next_episode(self) -> int:
        """Episodes started so far, over every scenario (each keeps its own stream's counter)."""
        return sum(part.next_episode for part in self.parts.values())

    def load_episodes(self, episode_ids: torch.Tensor) -> None:
        """Make the next reset load ``episode_ids [B]``: each row the case of its own scenario's stream."""
        ids = torch.as_tensor(episode_ids, dtype=torch.int64).reshape(-1)
        if ids.shape != (self.num_envs,):
            raise ValueError(f"episode_ids must hold one id per sub-env ({self.num_envs}), got {tuple(ids.shape)}")
        for name, part in self.parts.items():
            part.load_episodes(ids[self.slices[name]])

    def snapshot(self) -> dict:
        """Every scenario's in-flight episodes and stream position (:meth:`CrowdNavEnv.snapshot`)."""
        return {"format": self.SNAPSHOT_FORMAT, "rows": dict(self.rows),
                "parts": {name: part.snapshot() for name, part in self.parts.items()}}

    def restore(self, snapshot: dict) -> None:
        """Load a :meth:`snapshot` of the same mix; ``ValueError`` naming what differs."""
        if not isinstance(snapshot, dict) or snapshot.get("format") != self.SNAPSHOT_FORMAT:
            raise ValueError(f"its environments are not a scenario-mix snapshot of format {self.SNAPSHOT_FORMAT} "
                             "(a single-scenario run's, or an older crowdrl's)")
        if snapshot.get("rows") != self.rows:
            raise ValueError(f"the snapshot's scenario rows are {snapshot.get('rows')!r}, this env's {self.rows!r}")
        for name, part in self.parts.items():
            part.restore(snapshot["parts"][name])

    def _make_specs(self) -> None:
        B, dev = self.num_envs, self.device
        any_part = next(iter(self.parts.values()))
        leaves = dict(any_part.observation_spec.items())
        dtype = leaves["robot"].dtype
        K, (P, V) = self.obstacle_tokens, self.polygons_shape
        spec = Composite({key: _batched(leaf, B) for key, leaf in leaves.items() if key not in OBSTACLE_OBS},
                         shape=(B,), device=dev)
        if P > 0:
            spec["obstacles"] = Unbounded((B, K, 4), dtype=dtype, device=dev)
            spec["obstacles_mask"] = Categorical(2, (B, K), dtype=torch.bool, device=dev)
            spec["obstacle_polygons"] = Unbounded((B, P, V, 2), dtype=dtype, device=dev)
            spec["obstacle_polygons_mask"] = Categorical(2, (B, P, V), dtype=torch.bool, device=dev)
        spec["scenario"] = Categorical(len(SCENARIOS), (B, 1), dtype=torch.int64, device=dev)
        self.observation_spec = spec
        self.action_spec = _batched(any_part.action_spec, B)
        self.reward_spec = _batched(any_part.reward_spec, B)
        self.done_spec = Composite({key: _batched(leaf, B) for key, leaf in any_part.done_spec.items()}, shape=(B,),
                                   device=dev)

    def _padded(self, name: str, out: TensorDictBase) -> TensorDictBase:
        """``out`` (one scenario's rows) with the obstacle keys padded to the mix, and ``"scenario"``."""
        n = out.batch_size[0]
        K, (P, V) = self.obstacle_tokens, self.polygons_shape
        if P > 0:
            dtype = out.get("robot").dtype
            full = {"obstacles": (K, 4, dtype), "obstacles_mask": (K, torch.bool),
                    "obstacle_polygons": (P, V, 2, dtype), "obstacle_polygons_mask": (P, V, torch.bool)}
            for key, (*shape, kind) in full.items():
                padded = torch.zeros(n, *shape, dtype=kind, device=self.device)
                if key in out.keys():
                    value = out.get(key)
                    padded[(slice(None), *(slice(0, s) for s in value.shape[1:]))] = value
                out.set(key, padded)
        out.set("scenario", torch.full((n, 1), SCENARIOS.index(name), dtype=torch.int64, device=self.device))
        return out

    def _gather(self, outs: dict[str, TensorDictBase]) -> TensorDictBase:
        return torch.cat([self._padded(name, outs[name]) for name in self.parts], 0)

    def _set_seed(self, seed: int | None) -> int | None:
        for part in getattr(self, "parts", {}).values():
            part.set_seed(seed, static_seed=True)
        return seed

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        outs = {}
        for name, part in self.parts.items():
            rows = self.slices[name]
            given = TensorDict({}, batch_size=[self.rows[name]], device=self.device)
            if tensordict is not None:
                for key in ("_reset", "load_episode"):
                    if key in tensordict.keys():
                        given.set(key, tensordict.get(key)[rows])
            if "_reset" in given.keys() and part.started and not bool(given.get("_reset").any()):
                out = part.current()  # nothing of this scenario to reset
            else:
                out = part.reset(given if given.keys() else None)
            outs[name] = self._kept(part, out)
        return self._gather(outs)

    @staticmethod
    def _kept(part: CrowdNavEnv, out: TensorDictBase) -> TensorDictBase:
        return out.select(*part.observation_spec.keys(), *part.done_spec.keys())

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        outs = {}
        for name, part in self.parts.items():
            given = TensorDict({"action": action[self.slices[name]]}, batch_size=[self.rows[name]], device=self.device)
            outs[name] = part.step(given).get("next")
        return self._gather(outs)


__all__ = ["ScenarioMixEnv", "mix_rows"]
