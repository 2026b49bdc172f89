"""``CrowdNavEnv``: B crowd-navigation episodes as one TorchRL ``EnvBase``."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from crowdrl.sim import rng
from crowdrl.sim.config import HUMAN_MODELS, MIXED, CrowdConfig, is_integer
from crowdrl.sim.crowd import HUMAN_OBS_DIM, ROBOT_OBS_DIM, observe, step
from crowdrl.sim.kinematics import NUM_ACTIONS, action_table, decode_action
from crowdrl.sim.lidar import observe_lidar
from crowdrl.sim.obstacles import ObstacleEdges, nearest_edges, process_obstacles, put_edges, select_edges
from crowdrl.sim.scenarios import initial_states
from crowdrl.sim.state import CrowdState

SPLITS = tuple(rng.STREAMS)
SPAWN_BLOCK = 1024  # episodes of the stream spawned in one batched call (per-episode cost: docs/benchmarks.md, "Spawning")
# Larger batches spawn larger blocks (a spawn's per-call cost is then shared by more episodes), up to this
# many episodes ahead (~1.5 MB of states at N = 10).
SPAWN_BLOCK_MAX = 8192


class CrowdNavEnv(EnvBase):
    """Robot navigation among ORCA humans, ``num_envs`` episodes stepped at once (other humans:
    ``config.human_model``, :mod:`crowdrl.sim.humans`; in a mixed crowd each human's model is in
    ``env.state.human_model``, which the robot does not observe).

    Observations (world frame): ``"robot"`` ``[B, 9]`` = (px, py, vx, vy, radius, gx, gy,
    v_pref, heading), ``"humans"`` ``[B, N, 5]`` = (px, py, vx, vy, radius) and ``"humans_mask"``
    ``[B, N]`` (bool, True = present). With ``min_humans`` (or ``config.min_humans``) below
    ``num_humans``, each episode draws its crowd size from ``min_humans..num_humans`` (a pure
    function of its id); absent humans are zero rows, masked, and take no part in anything. Per-step info:
    ``"min_separation"``, ``"discomfort_count"``, ``"event"`` (0 running, 1 success,
    2 collision, 3 timeout), ``"episode_id"`` and ``"human_goals"`` ``[B, N, 2]`` (for
    recording trajectories; no policy of crowdrl reads it). In the obstacle scenarios (corridor,
    doorway, room) the observation adds the ``K = config.num_obstacle_tokens`` obstacle edges
    nearest to the robot, ``"obstacles"`` ``[B, K, 4]`` = (ax, ay, bx, by), nearest first, with
    ``"obstacles_mask"`` ``[B, K]`` (False: padding), and the episode's whole map,
    ``"obstacle_polygons"`` ``[B, P, V, 2]`` with ``"obstacle_polygons_mask"`` ``[B, P, V]`` (the
    RVO2 polygons of :class:`~crowdrl.sim.state.CrowdState`; the ORCA baseline reads them). With
    ``config.lidar_rays = R > 0`` (every scenario) it adds ``"lidar"`` ``[B, R]``, the robot's 2-D scan
    (:func:`crowdrl.sim.lidar.observe_lidar`: ray 0 along the heading, counter-clockwise, against the
    obstacle edges and the present humans' discs, clipped at ``config.lidar_range``; a network reads it
    with ``encoder.lidar``, :mod:`crowdrl.models.scan`). Actions are indices into the 81-action
    unicycle table, or, with ``robot_kinematics="holonomic"``, velocities ``[B, 2]`` clipped to
    ``v_pref`` (:func:`crowdrl.sim.kinematics.decode_action`). Collision and goal terminate;
    the time limit truncates.

    ``orca_backend="compiled"`` steps the humans with the ``torch.compile`` ORCA of
    :mod:`crowdrl.sim.orca_compiled` (same numbers; compiles for minutes on first use per batch shape).

    Episodes come from the ``split`` stream (``train``, ``val`` or ``test``) of ``seed``:
    each (partial) reset takes the next episode ids in sub-env order, unless episodes were
    queued with :meth:`load_episodes` (or the reset tensordict of the bare env carries
    ``"load_episode"`` ``[B, 1]``), in which case those episodes are loaded (episode ``i`` is the
    same whatever ``num_envs`` or device). The stream's episodes are spawned ahead in blocks of
    :attr:`spawn_block` (one batched rejection sampling), so the partial resets of a collector
    cost a copy, not a spawn each; the states are the same as spawning each episode alone.

    :meth:`snapshot` and :meth:`restore` save and reload the in-flight episodes for an exact
    resume: after ``restore``, the next reset hands back the episodes as they were, so a new
    collector continues them step for step.

    Examples:
        Three episodes of five humans, reset and stepped with a random action:

        >>> import torch
        >>> from crowdrl.envs import CrowdNavEnv
        >>> _ = torch.manual_seed(0)
        >>> env = CrowdNavEnv("circle", num_envs=3, num_humans=5, seed=0)
        >>> td = env.reset()
        >>> td["robot"].shape, td["humans"].shape, td["humans_mask"].dtype
        (torch.Size([3, 9]), torch.Size([3, 5, 5]), torch.bool)
        >>> env.action_spec.space.n
        81
        >>> td = env.rand_step(td)
        >>> td["next", "reward"].shape, td["next", "done"].shape
        (torch.Size([3, 1]), torch.Size([3, 1]))
        >>> sorted(env.full_done_spec.keys())
        ['done', 'terminated', 'truncated']

        Episode ids come from the stream, one per sub-env; a snapshot resumes them elsewhere:

        >>> td["episode_id"].flatten().tolist()
        [0, 1, 2]
        >>> env2 = CrowdNavEnv("circle", num_envs=3, num_humans=5, seed=0)
        >>> env2.restore(env.snapshot())
        >>> torch.equal(env2.reset()["robot"], td["next", "robot"])
        True
    """

    def __init__(
        self,
        scenario: str = "circle",
        num_envs: int = 1,
        num_humans: int = 10,
        *,
        device: torch.device | str = "cpu",
        seed: int = 0,
        split: str = "train",
        config: CrowdConfig | None = None,
        dtype: torch.dtype = torch.float32,
        orca_backend: str = "eager",
        robot_kinematics: str = "unicycle",
        min_humans: int | None = None,
    ) -> None:
        if not is_integer(num_envs) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if config is None:
            config = CrowdConfig(scenario=scenario, num_humans=num_humans, orca_backend=orca_backend,
                                 robot_kinematics=robot_kinematics, min_humans=min_humans)
        elif config.scenario != scenario or config.num_humans != num_humans:
            raise ValueError("pass scenario/num_humans either directly or through config, not both differently")
        elif orca_backend != "eager" or robot_kinematics != "unicycle" or min_humans is not None:
            raise ValueError("with a config, set orca_backend, robot_kinematics and min_humans in the config")
        super().__init__(device=torch.device(device), batch_size=torch.Size([int(num_envs)]))
        self.config = config
        self.split = split
        self.dtype = dtype
        self._seed = 0
        self._next_episode = 0
        self._queued: torch.Tensor | None = None
        self._restored: dict[str, torch.Tensor] | None = None
        self._spawned: tuple[int, CrowdState] | None = None  # (first episode id, states) spawned ahead
        # obstacle scenarios: the processed obstacle edges (RVO2's processObstacles) of the spawned block
        # and of the episodes in flight, so that a step never processes them (None: not yet / open scenario)
        self._block_edges: ObstacleEdges | None = None
        self._edges: ObstacleEdges | None = None
        self._actions = action_table(config.robot_v_pref, dtype=dtype, device=self.device)
        self.state: CrowdState | None = None
        self._make_specs()
        self._set_seed(seed)

    @property
    def num_envs(self) -> int:
        return self.batch_size[0]

    @property
    def num_humans(self) -> int:
        return self.config.num_humans

    @property
    def spawn_block(self) -> int:
        """Episodes of the stream spawned ahead at once: four batches' worth, within
        ``SPAWN_BLOCK .. SPAWN_BLOCK_MAX`` (a reset needing more spawns what it needs)."""
        return min(SPAWN_BLOCK_MAX, max(SPAWN_BLOCK, 4 * self.num_envs))

    @property
    def started(self) -> bool:
        """Whether the env has been reset (it has episodes in flight)."""
        return self.state is not None

    def current(self) -> TensorDictBase:
        """The observation of the episodes in flight, as a reset that resets none of them returns it."""
        if self.state is None:
            raise RuntimeError("CrowdNavEnv.current() called before reset()")
        return self._reset_output()

    @property
    def next_episode(self) -> int:
        """The episode id the next reset without ``"load_episode"`` takes (first sub-env)."""
        return self._next_episode

    def load_episodes(self, episode_ids: torch.Tensor) -> None:
        """Make the next reset load episodes ``episode_ids [B]`` (one per sub-env) instead of the
        next ones of the stream. Works through any ``TransformedEnv``:
        ``env.base_env.load_episodes(ids); env.reset()``."""
        ids = torch.as_tensor(episode_ids, dtype=torch.int64, device=self.device).reshape(-1)
        if ids.shape != (self.num_envs,):
            raise ValueError(f"episode_ids must hold one id per sub-env ({self.num_envs}), got {tuple(ids.shape)}")
        if bool((ids < 0).any()):
            raise ValueError("episode_ids must be >= 0")
        self._queued = ids.clone()

    # 2: every CrowdState field (1, older: no human_mask or obstacles); only the current one restores. A format-2
    # snapshot written before CrowdState.human_model (each human's model) restores with every human on the
    # config's model: the only crowd there was (a mixed crowd's snapshot must hold it).
    SNAPSHOT_FORMAT = 2

    def snapshot(self) -> dict:
        """The in-flight episodes (state, ids, per-step info, returns so far) and the stream position,
        as CPU tensors: what :meth:`restore` needs for the episodes to continue exactly."""
        if self.state is None:
            raise RuntimeError("CrowdNavEnv.snapshot() called before reset()")
        min_sep, discomfort, event = self._last
        tensors = {f"state.{name}": getattr(self.state, name) for name in CrowdState.__dataclass_fields__}
        tensors.update(episode_id=self._episode_id, episode_reward=self._return, min_separation=min_sep,
                       discomfort_count=discomfort, event=event)
        return {"format": self.SNAPSHOT_FORMAT, "split": self.split, "seed": self._seed,
                "num_envs": self.num_envs, "num_humans": self.num_humans, "min_humans": self.config.min_humans,
                "next_episode": self._next_episode,
                "tensors": {k: v.detach().to("cpu", copy=True) for k, v in tensors.items()}}

    def restore(self, snapshot: dict) -> None:
        """Load a :meth:`snapshot`; the next full reset (no ``_reset`` mask, no episodes queued) returns its
        episodes as they were instead of starting new ones. Raises ``ValueError`` naming what
        does not match this env (split, seed, batch, crowd size, dtype)."""
        if not isinstance(snapshot, dict) or snapshot.get("format") != self.SNAPSHOT_FORMAT:
            found = snapshot.get("format") if isinstance(snapshot, dict) else None
            raise ValueError(f"its environments are a CrowdNavEnv snapshot of format {found!r}; this code restores format "
                             f"{self.SNAPSHOT_FORMAT} only (an older crowdrl wrote it: resume it with that version, or "
                             f"train the run again)")
        mine = {"split": self.split, "seed": self._seed, "num_envs": self.num_envs, "num_humans": self.num_humans,
                "min_humans": self.config.min_humans}
        for key, value in mine.items():
            if snapshot.get(key) != value:
                raise ValueError(f"the snapshot's {key} is {snapshot.get(key)!r}, this env's {value!r}")
        tensors = dict(snapshot.get("tensors", {}))
        if ("state.human_model" not in tensors and self.config.human_model != MIXED
                and isinstance(tensors.get("state.human_mask"), torch.Tensor)):  # written before the field
            mask = tensors["state.human_mask"]
            tensors["state.human_model"] = torch.full(mask.shape, HUMAN_MODELS.index(self.config.human_model),
                                                      dtype=torch.int8)
        missing = {f"state.{n}" for n in CrowdState.__dataclass_fields__} - set(tensors)
        if missing:
            raise ValueError(f"the snapshot lacks {sorted(missing)}")
        if tensors["state.robot_position"].dtype != self.dtype:
            raise ValueError(f"the snapshot's dtype is {tensors['state.robot_position'].dtype}, this env's {self.dtype}")
        self._restored = {k: v.to(self.device, copy=True) for k, v in tensors.items()}
        self._next_episode = int(snapshot["next_episode"])

    def _make_specs(self) -> None:
        B, N, dev = self.num_envs, self.config.num_humans, self.device
        self.observation_spec = Composite(
            robot=Unbounded((B, ROBOT_OBS_DIM), dtype=self.dtype, device=dev),
            humans=Unbounded((B, N, HUMAN_OBS_DIM), dtype=self.dtype, device=dev),
            humans_mask=Categorical(2, (B, N), dtype=torch.bool, device=dev),
            min_separation=Unbounded((B, 1), dtype=self.dtype, device=dev),
            discomfort_count=Unbounded((B, 1), dtype=torch.int64, device=dev),
            event=Categorical(4, (B, 1), dtype=torch.int64, device=dev),
            episode_id=Unbounded((B, 1), dtype=torch.int64, device=dev),
            step_count=Unbounded((B, 1), dtype=torch.int64, device=dev),
            episode_reward=Unbounded((B, 1), dtype=self.dtype, device=dev),
            human_goals=Unbounded((B, N, 2), dtype=self.dtype, device=dev),
            shape=(B,),
            device=dev,
        )
        (P, V), K = self.config.obstacles_shape, self.config.num_obstacle_tokens
        if P > 0:
            self.observation_spec.update(dict(
                obstacles=Unbounded((B, K, 4), dtype=self.dtype, device=dev),
                obstacles_mask=Categorical(2, (B, K), dtype=torch.bool, device=dev),
                obstacle_polygons=Unbounded((B, P, V, 2), dtype=self.dtype, device=dev),
                obstacle_polygons_mask=Categorical(2, (B, P, V), dtype=torch.bool, device=dev),
            ))
        if self.config.lidar_rays > 0:
            self.observation_spec["lidar"] = Bounded(0.0, self.config.lidar_range, (B, int(self.config.lidar_rays)),
                                                     dtype=self.dtype, device=dev)
        if self.config.robot_kinematics == "unicycle":
            self.action_spec = Categorical(NUM_ACTIONS, shape=(B,), dtype=torch.int64, device=dev)
        else:  # holonomic: a velocity, clipped to v_pref by the env (the box bounds each component)
            v = self.config.robot_v_pref
            self.action_spec = Bounded(-v, v, shape=(B, 2), dtype=self.dtype, device=dev)
        self.reward_spec = Unbounded((B, 1), dtype=self.dtype, device=dev)
        self.done_spec = Composite(
            done=Categorical(2, (B, 1), dtype=torch.bool, device=dev),
            terminated=Categorical(2, (B, 1), dtype=torch.bool, device=dev),
            truncated=Categorical(2, (B, 1), dtype=torch.bool, device=dev),
            shape=(B,),
            device=dev,
        )

    def _set_seed(self, seed: int | None) -> int | None:
        """Select the scenario stream ``seed`` and restart its episode counter."""
        if seed is None:
            seed = 0
        if not is_integer(seed) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self._seed = int(seed)
        self._next_episode = 0
        self._restored = None  # a new stream starts over
        self._spawned = None
        self._block_edges = None
        return seed

    def _observation(self, state: CrowdState, min_sep, discomfort, event, episode_id) -> TensorDict:
        robot, humans = observe(self.config, state)
        out = TensorDict(
            {
                "robot": robot,
                "humans": humans,
                "humans_mask": state.human_mask.clone(),
                "min_separation": min_sep.unsqueeze(-1),
                "discomfort_count": discomfort.unsqueeze(-1),
                "event": event.unsqueeze(-1),
                "episode_id": episode_id.clone(),  # never hand out views of internal state
                "step_count": state.step_count.unsqueeze(-1).clone(),
                "episode_reward": self._return.unsqueeze(-1).clone(),
                "human_goals": state.human_goal.clone(),  # not the robot's to see: for recording only
            },
            batch_size=self.batch_size,
            device=self.device,
        )
        if state.has_obstacles:
            edges, edges_mask = nearest_edges(state.robot_position, state.obstacles, state.obstacle_mask,
                                              self.config.num_obstacle_tokens)
            out.update({"obstacles": edges, "obstacles_mask": edges_mask,
                        "obstacle_polygons": state.obstacles.clone(),
                        "obstacle_polygons_mask": state.obstacle_mask.clone()})
        if self.config.lidar_rays > 0:
            out["lidar"] = observe_lidar(self.config, state)
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B = self.num_envs
        if self._restored is not None and self._queued is None and (
                tensordict is None or not {"_reset", "load_episode"} & set(tensordict.keys())):
            return self._continue_restored()
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(B).to(self.device)
        if self.state is None:
            mask = None  # nothing to keep yet
        reset_mask = torch.ones(B, dtype=torch.bool, device=self.device) if mask is None else mask
        ids = None
        if tensordict is not None and "load_episode" in tensordict.keys():
            given = tensordict.get("load_episode").reshape(B).to(self.device, torch.int64)
            if bool((given[reset_mask] < 0).any()):
                raise ValueError("load_episode must be >= 0 for the sub-envs being reset")
            ids = given
        elif self._queued is not None:
            ids, self._queued = self._queued, None
        if ids is None:  # the next episodes of the stream
            k = int(reset_mask.sum())
            ids = torch.zeros(B, dtype=torch.int64, device=self.device)
            ids[reset_mask] = torch.arange(self._next_episode, self._next_episode + k, device=self.device)
            fresh, fresh_edges = self._stream_states(self._next_episode, k)
            self._next_episode += k
        else:
            fresh = initial_states(self.config, rng.episode_keys(self.split, self._seed, ids[reset_mask]),
                                   dtype=self.dtype)
            fresh_edges = process_obstacles(fresh.obstacles, fresh.obstacle_mask) if fresh.has_obstacles else None
        if mask is None:
            self.state = fresh
            self._edges = fresh_edges
            self._episode_id = ids.clone()
            self._return = torch.zeros(B, dtype=self.dtype, device=self.device)
            self._last = (
                torch.full((B,), float("inf"), dtype=self.dtype, device=self.device),
                torch.zeros(B, dtype=torch.int64, device=self.device),
                torch.zeros(B, dtype=torch.int64, device=self.device),
            )
        else:
            idx = reset_mask.nonzero(as_tuple=True)[0]
            for name in CrowdState.__dataclass_fields__:
                getattr(self.state, name)[idx] = getattr(fresh, name)
            if fresh_edges is not None:  # only the reset episodes' obstacles change
                self._edges = None if self._edges is None else put_edges(self._edges, idx, fresh_edges)
            self._episode_id = torch.where(reset_mask, ids, self._episode_id)
            self._return = torch.where(reset_mask, 0.0, self._return)
            min_sep, discomfort, event = self._last
            self._last = (
                torch.where(reset_mask, float("inf"), min_sep),
                torch.where(reset_mask, 0, discomfort),
                torch.where(reset_mask, 0, event),
            )
        return self._reset_output()

    def _stream_states(self, first: int, k: int) -> tuple[CrowdState, ObstacleEdges | None]:
        """Initial states of episodes ``first .. first+k-1`` of the stream, from the block spawned ahead,
        and their processed obstacle edges (``None`` without obstacles), processed with the block."""
        start, block = self._spawned if self._spawned is not None else (-1, None)
        if block is None or first < start or first + k > start + block.batch_size:
            ids = torch.arange(first, first + max(k, self.spawn_block), device=self.device)
            block = initial_states(self.config, rng.episode_keys(self.split, self._seed, ids), dtype=self.dtype)
            start, self._spawned = first, (first, block)
            self._block_edges = (process_obstacles(block.obstacles, block.obstacle_mask) if block.has_obstacles
                                 else None)
        rows = slice(first - start, first - start + k)
        part = block.index(rows)
        edges = None if self._block_edges is None else select_edges(self._block_edges, rows)
        return CrowdState(**{name: getattr(part, name).clone() for name in CrowdState.__dataclass_fields__}), edges

    def _reset_output(self) -> TensorDictBase:
        out = self._observation(self.state, *self._last, self._episode_id.unsqueeze(-1))
        false = torch.zeros(self.num_envs, 1, dtype=torch.bool, device=self.device)
        out.update({"done": false, "terminated": false.clone(), "truncated": false.clone()})
        return out

    def _continue_restored(self) -> TensorDictBase:
        """The reset after :meth:`restore`: the snapshot's episodes, as they were."""
        t, self._restored = self._restored, None
        self.state = CrowdState(**{name: t[f"state.{name}"] for name in CrowdState.__dataclass_fields__})
        self._edges = None  # processed again on the first step
        self._episode_id, self._return = t["episode_id"], t["episode_reward"]
        self._last = (t["min_separation"], t["discomfort_count"], t["event"])
        return self._reset_output()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.state is None:
            raise RuntimeError("CrowdNavEnv.step() called before reset()")
        action = tensordict.get("action")
        if action.device != self.device:
            raise ValueError(f"action is on {action.device}, the env on {self.device}")
        kinematics = self.config.robot_kinematics
        if kinematics == "unicycle":
            if action.shape == (self.num_envs, NUM_ACTIONS) and action.dtype == torch.bool:
                action = action.long().argmax(-1)  # one-hot
            elif action.shape == (self.num_envs, 1):
                action = action.squeeze(-1)
        velocity, heading = decode_action(kinematics, action, self.state.robot_heading, self._actions,
                                          self.config.robot_v_pref)
        if self.state.has_obstacles and self._edges is None:
            self._edges = process_obstacles(self.state.obstacles, self.state.obstacle_mask)
        self.state, res = step(self.config, self.state, velocity, heading, obstacle_edges=self._edges)
        self._return = self._return + res.reward
        self._last = (res.min_separation, res.discomfort_count, res.event)
        out = self._observation(self.state, *self._last, self._episode_id.unsqueeze(-1))
        out.update(
            {
                "reward": res.reward.unsqueeze(-1),
                "done": (res.terminated | res.truncated).unsqueeze(-1),
                "terminated": res.terminated.unsqueeze(-1),
                "truncated": res.truncated.unsqueeze(-1),
            }
        )
        return out
