"""The oracle as a teacher: oracle-solved cases of the training stream as demonstrations in the replay buffer.

The humans ignore the robot, so a case's crowd is known in advance and :mod:`crowdrl.sim.oracle` can solve it
(:func:`~crowdrl.sim.oracle.beam_search`). With ``train.demonstrations.cases = N > 0``, before the first
collected batch of a fresh run (docs/ceiling.md, "The oracle as a teacher"):

1. **Cases.** Episodes ``DEMO_FIRST_EPISODE + i`` (``i < N``) of the run's ``train`` stream (its seed) are
   searched, at ``widths[0]`` first, then at each wider width on the cases still unsolved. The collector takes
   the stream's ids from 0 up, and never reaches ``2**62``: the demonstrated cases are training-stream cases the
   agent never plays itself.
2. **Replay.** Each solved path is played by :class:`RecordedActions` through ``env.rollout`` of an env of the
   run's own maker (:func:`~crowdrl.training.factories.make_env`: the same simulator and transforms as
   collection), so the transitions hold the env's real rewards, dones and next observations. A path must end
   in success at the step the search found, with no event before; one that does not is dropped and counted.
3. **Storage.** The paths are written to the replay buffer as ``[cases, steps]`` batches of the keys the
   trainer stores (:meth:`~crowdrl.training.trainer.Trainer` ``stored_keys``), through the buffer's own
   transform: the same n-step returns (a window is cut by the end of the path, not by the collector's batch
   length) and the same extra keys (the crowd predictor's, counterfactual experience's).

The demonstrations are not collected frames: they add nothing to the frame count, the episode count or the
update credit. The global torch RNG is left as it was, so collection then draws what it draws without them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase

from crowdrl.sim import rng
from crowdrl.sim.config import CrowdConfig
from crowdrl.sim.crowd import SUCCESS
from crowdrl.sim.obstacles import process_obstacles, select_edges
from crowdrl.sim.oracle import beam_search
from crowdrl.sim.scenarios import initial_states

DEMO_FIRST_EPISODE = 2**62  # demonstration i is episode DEMO_FIRST_EPISODE + i of the run's train stream
SEARCH_CHUNK = 50  # cases searched at once (memory: chunk x width x 81 children a depth)
PLAY_CHUNK = 256  # paths played through one env at once


class RecordedActions(nn.Module):
    """Plays recorded action sequences: sub-env ``b`` takes ``plans[b, step_count]`` (the last action past its end)."""

    def __init__(self, plans: Tensor) -> None:
        super().__init__()
        self.register_buffer("plans", plans.long())

    def forward(self, step_count: Tensor) -> Tensor:
        t = step_count.reshape(-1).clamp(0, self.plans.shape[1] - 1)
        return self.plans[torch.arange(self.plans.shape[0], device=t.device), t]


@dataclass
class Paths:
    """The oracle's paths: ``episodes`` (ids of the train stream) and their ``actions``; ``unsolved`` counts
    the cases searched without a path found."""

    episodes: list[int] = field(default_factory=list)
    actions: list[list[int]] = field(default_factory=list)
    unsolved: int = 0


def solve_cases(cfg: CrowdConfig, seed: int, cases: int, widths: Sequence[int], *,
                first: int = DEMO_FIRST_EPISODE, chunk: int = SEARCH_CHUNK) -> Paths:
    """Search episodes ``first .. first+cases-1`` of the ``train`` stream of ``seed`` under ``cfg``, at
    ``widths[0]``, then each wider width on the cases still unsolved."""
    out = Paths()
    for a in range(0, cases, chunk):
        ids = torch.arange(first + a, first + min(cases, a + chunk))
        start = initial_states(cfg, rng.episode_keys("train", seed, ids))
        edges = process_obstacles(start.obstacles, start.obstacle_mask) if start.has_obstacles else None
        todo, found_at = torch.arange(ids.shape[0]), {}
        for w in widths:
            if todo.numel() == 0:
                break
            found = beam_search(cfg, start.index(todo), width=int(w),
                                edges=None if edges is None else select_edges(edges, todo))
            left = []
            for j, c in enumerate(todo.tolist()):
                if found.steps[j] > 0:
                    found_at[c] = found.actions[j]
                else:
                    left.append(c)
            todo = torch.tensor(left, dtype=torch.long)
        for c in sorted(found_at):
            out.episodes.append(int(ids[c]))
            out.actions.append(found_at[c])
        out.unsolved += int(todo.numel())
    return out


@torch.no_grad()
def play_paths(env: EnvBase, paths: Paths) -> tuple[list[TensorDictBase], int]:
    """The rollouts of ``paths`` through ``env`` (a fresh env of the run's maker, one sub-env per path), as
    ``[k, steps]`` batches of paths of equal length, and the number of paths dropped: those that do not end in
    success at their last step with no event before."""
    base = env.base_env
    if len(paths.episodes) != base.num_envs:
        raise ValueError(f"the env steps {base.num_envs} episodes at once, {len(paths.episodes)} paths were given")
    lengths = torch.tensor([len(a) for a in paths.actions])
    longest = int(lengths.max())
    plans = torch.zeros(len(paths.actions), longest, dtype=torch.long)
    for j, a in enumerate(paths.actions):
        plans[j, :len(a)] = torch.tensor(a)
    policy = TensorDictModule(RecordedActions(plans.to(base.device)), in_keys=["step_count"], out_keys=["action"])
    base.load_episodes(torch.tensor(paths.episodes))
    rollout = env.rollout(longest, policy=policy, break_when_any_done=False)  # [k, longest]
    done = rollout.get(("next", "done")).reshape(len(paths.actions), longest).cpu()
    event = rollout.get(("next", "event")).reshape(len(paths.actions), longest).cpu()
    steps = torch.arange(longest)
    last = lengths - 1
    early = (done & (steps[None, :] < last[:, None])).any(1)
    ok = ~early & done[torch.arange(len(lengths)), last] & (event[torch.arange(len(lengths)), last] == SUCCESS)
    batches = []
    for n in sorted(set(lengths[ok].tolist())):
        rows = (ok & (lengths == n)).nonzero(as_tuple=True)[0]
        batches.append(rollout[rows.to(rollout.device), :n])
    return batches, int((~ok).sum())


@dataclass
class DemoReport:
    """What :func:`add_demonstrations` did: cases searched, solved, replayed (stored), transitions stored, and
    the seconds spent searching and playing."""

    cases: int
    solved: int
    stored_paths: int
    transitions: int
    search_s: float
    play_s: float

    def summary(self) -> str:
        """One line for the run's log."""
        return (f"demonstrations: {self.cases} cases searched, {self.solved} solved, {self.stored_paths} paths stored "
                f"({self.transitions} transitions), {self.cases - self.solved} unsolved, "
                f"{self.solved - self.stored_paths} dropped by the replay; {self.search_s:.1f} s searching, "
                f"{self.play_s:.1f} s playing")

    def log_row(self) -> dict[str, float]:
        """The run's ``kind: demo`` row at frame 0 (``train/demo_*``, ``time/demo_*_s``)."""
        return {"kind": "demo", "frames": 0, "updates": 0, "episodes": 0,
                "train/demo_cases": self.cases, "train/demo_solved": self.solved,
                "train/demo_unsolved": self.cases - self.solved,
                "train/demo_dropped": self.solved - self.stored_paths,
                "train/demo_transitions": self.transitions,
                "time/demo_search_s": self.search_s, "time/demo_play_s": self.play_s}


def add_demonstrations(buffer: TensorDictReplayBuffer, make_play_env, cfg: CrowdConfig, seed: int, cases: int,
                       widths: Sequence[int], keys: Sequence[NestedKey], *,
                       first: int = DEMO_FIRST_EPISODE) -> DemoReport:
    """Solve ``cases`` train-stream cases of ``seed`` (from episode ``first``), play the paths through envs
    of ``make_play_env(num_envs)`` and extend ``buffer`` with their transitions' ``keys``, as collected batches
    are; the global torch RNG is left as it was."""
    with torch.random.fork_rng(devices=[]):
        began = time.perf_counter()
        paths = solve_cases(cfg, seed, cases, widths, first=first)
        searched = time.perf_counter()
        stored, transitions = 0, 0
        for a in range(0, len(paths.episodes), PLAY_CHUNK):
            part = Paths(paths.episodes[a:a + PLAY_CHUNK], paths.actions[a:a + PLAY_CHUNK])
            batches, _ = play_paths(make_play_env(len(part.episodes)), part)
            for batch in batches:
                buffer.extend(batch.select(*keys))
                stored += batch.shape[0]
                transitions += batch.numel()
    return DemoReport(cases, len(paths.episodes), stored, transitions, searched - began,
                      time.perf_counter() - searched)


__all__ = ["DEMO_FIRST_EPISODE", "DemoReport", "Paths", "RecordedActions", "add_demonstrations", "play_paths",
           "solve_cases"]
