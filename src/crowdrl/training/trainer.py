"""D3QN training on CrowdNavEnv: TorchRL collector, n-step replay, double DQN, validation,
atomic checkpoints and resume.

One ``Trainer`` is one run folder. The loop: collect ``num_envs x steps_per_batch`` frames with
the exploration strategy's policy, write them to the replay buffer as n-step transitions, do
``updates_per_frame`` updates of batch ``batch_size`` per collected frame (each: the auxiliary
learners' steps on the sampled batch, then the Q update's gradient steps), update the target
network (``train.target_tau`` < 1: Polyak averaging after every update, ``D3QNLoss.update_target_polyak``; 1: a hard
copy every ``target_update_frames`` frames), validate greedily on held-out validation
episodes every ``val_every_frames`` frames (the best policy is kept), checkpoint every
``checkpoint_every_frames`` frames. What the exploration variant adds comes through its
:class:`~crowdrl.exploration.strategy.ExplorationStrategy`, what else learns on the sampled batches
through :class:`~crowdrl.auxiliary.AuxiliaryLearner` instances, what the update does through its
:class:`~crowdrl.training.parts.UpdatePart`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from crowdrl.evaluation import EpisodeMetrics, evaluate
from crowdrl.exploration import make_strategy
from crowdrl.exploration.schedule import linear_schedule
from crowdrl.sim.crowd import COLLISION, SUCCESS, TIMEOUT
from crowdrl.files import atomic_write_json
from crowdrl.training.checkpoint import CheckpointError, config_fingerprint, load_checkpoint, save_checkpoint
from crowdrl.training.config import RunConfig, sees_obstacles, to_dict
from crowdrl.training.demonstrations import add_demonstrations
from crowdrl.training.factories import (buffer_state_dict, make_actor, make_buffer, make_collector, make_env,
                                        make_exploration, make_learners, make_loss, make_optimizer, make_predictor_of,
                                        make_update_part, obs_keys, stored_keys)
from crowdrl.training.scalars import ScalarLog, WandbMirror
from crowdrl.training.variants import make_network, replay_context


TIMER_COUNTERS = ("collect_s", "update_s", "validate_s")
_log = logging.getLogger(__name__)


class NonFiniteError(FloatingPointError):
    """Training produced a non-finite loss or non-finite weights: the run fails, it is never tested."""


@dataclass
class Counters:
    frames: int = 0
    updates: int = 0
    episodes: int = 0
    update_credit: float = 0.0
    next_train_episode: int = 0
    best_val: float = -math.inf
    best_frames: int = -1
    last_val: int = 0
    last_checkpoint: int = 0
    # seconds spent collecting, updating and validating up to the checkpoint, so that a resumed run's
    # timers (scalars' time/*_s, status.json's timers_s) count the whole run
    collect_s: float = 0.0
    update_s: float = 0.0
    validate_s: float = 0.0
    # the oracle's demonstrations (train.demonstrations): transitions stored before the first collected batch,
    # and the seconds spent solving and playing them (not frames)
    demo_transitions: int = 0
    demo_s: float = 0.0

    def timers(self) -> dict[str, float]:
        """The seconds spent so far as ``{"collect": ..., "update": ..., "validate": ...}``, and ``"demo"``
        (the oracle's demonstrations) in a run that has them."""
        out = {name.removesuffix("_s"): getattr(self, name) for name in TIMER_COUNTERS}
        if self.demo_s > 0:
            out["demo"] = self.demo_s
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Counters":
        """The counters of a checkpoint; ``ValueError`` naming a missing or unknown counter (the timers
        and the demonstrations' counters, added later, are 0 in a checkpoint without them)."""
        names = {f.name for f in fields(cls)}
        data = {**dict.fromkeys(TIMER_COUNTERS, 0.0), "demo_transitions": 0, "demo_s": 0.0, **data}
        if set(data) != names:
            raise ValueError(f"its counters differ from this code's: missing {sorted(names - set(data))}, "
                             f"unknown {sorted(set(data) - names)}")
        return cls(**data)


class Trainer:
    """One D3QN run of ``run`` in the folder ``run_dir`` (see the module docstring for the loop).

    :meth:`train` trains to ``train.total_frames`` (resuming from ``run_dir/checkpoints/last.pt``
    when it is there) and returns a summary; :meth:`save` and :meth:`restore` write and read
    checkpoints; :meth:`request_stop` makes the loop checkpoint and stop after the current batch;
    :meth:`close` closes the logs. The final test is :func:`crowdrl.training.run_training`'s.

    Examples:
        A 64-frame run on four environments (SARL encoder, nothing compiled, no planning):

        >>> import os, tempfile
        >>> from crowdrl.training import Trainer, validate
        >>> run = validate({
        ...     "preset": "smoke", "encoder": {"name": "sarl"}, "env": {"num_humans": 4, "orca_backend": "eager"},
        ...     "logger": {"name": "csv", "progress_bar": False, "render": False},
        ...     "planning": {"enabled": False}, "exploration": {"name": "egreedy"},
        ...     "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 64, "warmup_frames": 32,
        ...               "batch_size": 16, "buffer_size": 1000, "updates_per_frame": 0.25,
        ...               "target_update_frames": 32, "val_every_frames": 64, "val_episodes": 2,
        ...               "checkpoint_every_frames": 64, "test_episodes": 2,
        ...               "compile_acting": False, "compile_loss": False}})
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     trainer = Trainer(run, folder)
        ...     try:
        ...         summary = trainer.train()
        ...     finally:
        ...         trainer.close()
        ...     checkpoints = sorted(os.listdir(os.path.join(folder, "checkpoints")))
        >>> summary["frames"], summary["updates"] > 0, checkpoints
        (64, True, ['best.pt', 'last.pt'])
    """

    def __init__(self, run: RunConfig, run_dir: Path | str) -> None:
        self.run = run
        self.dir = Path(run_dir)
        self.ckpt_dir = self.dir / "checkpoints"
        self.config_dict = to_dict(run)
        self.fingerprint = config_fingerprint(self.config_dict)
        torch.set_num_threads(run.threads)
        torch.manual_seed(run.seed)
        t = run.train
        self.env = make_env(run, split="train")
        self.val_env = make_env(run, split="val", num_envs=t.val_episodes)  # same maker, held-out stream
        self.crowd_cfg = self.env.base_env.config
        # + the humans' mask when the crowd size varies; entity tokens among obstacles
        self.obs_keys = obs_keys(self.crowd_cfg, sees_obstacles(run))
        self.stored_keys = stored_keys(run, self.obs_keys)
        num_actions = int(self.env.action_spec.n)
        # the exploration strategy: its network surgery, acting policy, replay transform, learners
        self.strategy = make_strategy(run.exploration)
        self.net = make_network(run, num_actions, self.strategy).to(run.device)
        # online planning: the crowd predictor (seeded apart from the global RNG)
        self.predictor = make_predictor_of(run, self.crowd_cfg.time_step)
        self.actor = make_actor(run, self.env, self.net, self.predictor)
        self.policy, _ = make_exploration(run, self.env, self.actor, self.strategy)
        self.loss = make_loss(run, self.net, self.obs_keys)
        # the target network is copied every `updates_per_copy` updates (target_update_frames of data)
        self.updates_per_copy = max(1, round(t.target_update_frames * max(t.updates_per_frame, 1e-9)))
        self.optimizer = make_optimizer(run, self.net)
        self.counters = Counters()
        # the strategy's replay transform (ICM / RE3: their own seeds, the global RNG is untouched)
        self.buffer = make_buffer(run, self.obs_keys, self.strategy,
                                  replay_context(run, list(self.obs_keys), num_actions, lambda: self.counters.frames))
        # what else learns on each sampled batch, with its own optimiser (the strategy's, the crowd predictor)
        self.learners = make_learners(run, self.predictor, self.obs_keys, self.strategy)
        # the gradient steps of one update (the sampled batch; with counterfactual experience, simulated ones too)
        self.update_part = make_update_part(run, self.net, self.obs_keys, self.crowd_cfg, self.strategy.reward_bonus())
        self.stored_keys += [k for k in self.update_part.stored_keys() if k not in self.stored_keys]
        self.log = None
        self.wandb = None
        self._restored: dict[str, Any] | None = None
        self._stop_requested = False
        # the learners' scalars: means over the last batch's updates (NaN: none)
        self.learner_scalars = dict.fromkeys(self._learner_scalar_names(), math.nan)
        self._learner_sums: dict[str, float] = {}
        self._part_losses: dict[str, list[float]] = {}  # losses of the update's later batches since the last log
        # (event, return, steps, goal distance) of finished episodes not yet logged (logged by 20)
        self._pending_episodes: list[tuple[int, float, int, float]] = []

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        payload = {
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "counters": self.counters.__dict__.copy(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None,
            "config": self.config_dict,
            "wandb_id": self.wandb.id if self.wandb else None,
            # for an exact resume: the in-flight episodes, the finished ones not yet logged
            "env": self.env.base_env.snapshot() if self.env.base_env.state is not None else None,
            "pending_episodes": list(self._pending_episodes),
            # the later batches' losses since the last logged row (train/loss_<part>): its mean spans the resume
            "part_losses": {name: list(values) for name, values in self._part_losses.items()},
            "update_part": self.update_part.state_dict(),
        }
        # the strategy's and the learners' own top-level keys
        for part in (self.strategy, *self.learners):
            _merge(payload, part.state_dict(), type(part).__name__)
        if self.run.train.save_buffer:
            payload["buffer"] = buffer_state_dict(self.buffer)  # unwritten slots zeroed: identical runs, same bytes
        return payload

    def load_state_dict(self, data: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` of this code version; an older ``last.pt`` (its environments'
        snapshot of an older format) raises ``ValueError`` saying so, before anything is restored."""
        self.env.base_env.restore(data.get("env"))  # first: it names an older file's format
        self.loss.load_state_dict(data["loss"])
        self.optimizer.load_state_dict(data["optimizer"])
        self.counters = Counters.from_dict(data["counters"])
        self._set_rng(data)
        self._pending_episodes = [tuple(e) for e in data["pending_episodes"]]  # (event, return, steps, goal distance)
        # a checkpoint written before the key kept none: read as empty
        self._part_losses = {str(name): [float(v) for v in values] for name, values in data.get("part_losses", {}).items()}
        self.update_part.load_state_dict(data.get("update_part", {}))  # a checkpoint before parts: none had state
        for part in (self.strategy, *self.learners):
            part.load_state_dict(data)
        if "buffer" in data:
            self.buffer.load_state_dict(data["buffer"])

    @staticmethod
    def _set_rng(data: dict[str, Any]) -> None:
        torch.set_rng_state(data["torch_rng"])
        if data.get("cuda_rng") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(data["cuda_rng"])

    def save(self, name: str = "last.pt") -> Path:
        path = self.ckpt_dir / name
        save_checkpoint(path, self.state_dict(), self.fingerprint)
        return path

    # ------------------------------------------------------------------ loop
    def restore(self) -> dict[str, Any] | None:
        """Load ``checkpoints/last.pt`` when the folder has one (a resume) and return it.

        Raises :class:`CheckpointError` for a truncated, foreign or unloadable checkpoint before
        anything is written: a refused resume leaves the folder as it was.
        """
        if self._restored is not None:
            return self._restored or None
        last = self.ckpt_dir / "last.pt"
        data: dict[str, Any] = {}
        if last.exists():
            data = load_checkpoint(last, self.fingerprint, config=self.config_dict)
            try:
                self.load_state_dict(data)
            except (KeyError, RuntimeError, ValueError, TypeError) as exc:
                raise CheckpointError(f"{last} cannot be restored into this run: {str(exc).splitlines()[0]}") from None
        self._restored = data
        return data or None

    @property
    def stop_requested(self) -> bool:
        return self._stop_requested

    def request_stop(self) -> None:
        """Stop at the end of the current batch, after a checkpoint (what SIGTERM and SIGINT do)."""
        self._stop_requested = True

    def train(self) -> dict[str, Any]:
        resume_data = self.restore()
        self.dir.mkdir(parents=True, exist_ok=True)
        run, t, c = self.run, self.run.train, self.counters
        self.log = ScalarLog(self.dir)
        dropped = self.log.truncate_after(self.counters.frames)
        if run.logger.name == "wandb":
            self.wandb = WandbMirror(self.dir, self.config_dict, run.logger.project, run.logger.mode,
                                     resume_data.get("wandb_id") if resume_data else None)
        self.write_status("running", resumed_from=c.frames if resume_data else None, dropped_rows=dropped)
        self.strategy.schedule(c.frames)  # a resumed run acts with the schedules of its frame count, not their start
        self.set_learning_rate()
        if c.frames >= t.total_frames:  # killed after training, e.g. during the test: nothing left to train
            summary = self._summary()
            self.write_status("trained", **summary)
            return summary
        if resume_data is None and t.demonstrations.cases > 0:  # a fresh run: once, before the first batch
            self._add_demonstrations()
        collector = make_collector(run, self.env, self.policy)  # its first reset continues restored episodes
        if resume_data:  # the collector's set-up may draw random numbers: the stream continues from here
            self._set_rng(resume_data)
        bar = _progress(run.logger.progress_bar, t.total_frames, c.frames)
        recent = self._pending_episodes  # (event, return, steps, goal distance) of finished episodes not yet logged
        try:
            tick = time.perf_counter()
            for batch in collector:
                c.collect_s += time.perf_counter() - tick
                frames = batch.numel()
                c.frames += frames
                c.next_train_episode = self.env.base_env.next_episode
                finished = _finished_episodes(batch)
                c.episodes += len(finished)
                recent.extend(finished)
                self.buffer.extend(batch.select(*self.stored_keys))
                tick = time.perf_counter()
                loss_value = self._update(frames)
                c.update_s += time.perf_counter() - tick
                self.strategy.before_collection(c.frames)
                self.set_learning_rate()
                if c.frames - c.last_val >= t.val_every_frames or c.frames >= t.total_frames:
                    tick = time.perf_counter()
                    self._validate()
                    c.validate_s += time.perf_counter() - tick
                if recent and (len(recent) >= 20 or c.frames >= t.total_frames):
                    self._log_train(recent, loss_value)
                    recent.clear()
                if bar is not None:
                    bar.update(frames)
                    bar.set_postfix(**self.strategy.progress(), episodes=c.episodes, best_val_score=f"{c.best_val:.3f}")
                if c.frames - c.last_checkpoint >= t.checkpoint_every_frames or c.frames >= t.total_frames:
                    c.last_checkpoint = c.frames
                    self.save("last.pt")
                if c.frames >= t.total_frames:
                    break
                if self._stop_requested:
                    c.last_checkpoint = c.frames
                    self.save("last.pt")
                    raise KeyboardInterrupt(f"stopped by a signal at frame {c.frames}; checkpoint saved")
                tick = time.perf_counter()
        finally:
            collector.shutdown()
            if bar is not None:
                bar.close()
        summary = self._summary()
        self.write_status("trained", **summary)
        return summary

    def _add_demonstrations(self) -> None:
        """The oracle's demonstrations into the replay buffer (:mod:`crowdrl.training.demonstrations`), logged
        as a ``kind: demo`` row at frame 0; the global RNG is left as it was."""
        run, d, c = self.run, self.run.train.demonstrations, self.counters
        report = add_demonstrations(self.buffer, lambda n: make_env(run, split="train", num_envs=n), self.crowd_cfg,
                                    run.seed, d.cases, d.widths, self.stored_keys)
        c.demo_transitions = report.transitions
        c.demo_s = report.search_s + report.play_s
        _log.info("demonstrations: %d cases searched, %d solved, %d paths stored (%d transitions), %d unsolved, "
                  "%d dropped by the replay; %.1f s searching, %.1f s playing", report.cases, report.solved,
                  report.stored_paths, report.transitions, report.cases - report.solved,
                  report.solved - report.stored_paths, report.search_s, report.play_s)
        if not any(r.get("kind") == "demo" for r in self.log.rows()):  # a restart from scratch logged it already
            self.emit({"kind": "demo", "frames": 0, "updates": 0, "episodes": 0,
                       "train/demo_cases": report.cases, "train/demo_solved": report.solved,
                       "train/demo_unsolved": report.cases - report.solved,
                       "train/demo_dropped": report.solved - report.stored_paths,
                       "train/demo_transitions": report.transitions,
                       "time/demo_search_s": report.search_s, "time/demo_play_s": report.play_s})

    def _summary(self) -> dict[str, Any]:
        c = self.counters
        return {"frames": c.frames, "updates": c.updates, "episodes": c.episodes,
                "best_val_score": c.best_val,  # validation success + 1e-3 * return
                "best_frames": c.best_frames, "timers_s": c.timers()}

    def _update(self, frames: int) -> float:
        t, c = self.run.train, self.counters
        c.update_credit += frames * t.updates_per_frame
        n = int(c.update_credit)
        c.update_credit -= n
        self.learner_scalars = dict.fromkeys(self.learner_scalars, math.nan)
        self._learner_sums = dict.fromkeys(self.learner_scalars, 0.0)
        if c.frames < t.warmup_frames:  # warm-up of a fresh run: no updates owed
            return math.nan
        if len(self.buffer) < max(t.batch_size, min(t.warmup_frames, t.buffer_size)):
            # a run resumed without its buffer refills it first; the updates stay owed
            c.update_credit += n
            return math.nan
        total = 0.0
        for _ in range(n):
            total += self.update_once(self.buffer.sample())
        if n:
            self.learner_scalars = {k: total_k / n for k, total_k in self._learner_sums.items()}
        params = [*self.net.parameters(), *(p for learner in self.learners for p in learner.parameters())]
        if n and not bool(torch.stack([torch.isfinite(p).all() for p in params]).all()):  # one sync
            raise NonFiniteError(f"the weights of the Q network or of an auxiliary learner became non-finite by update "
                                 f"{c.updates} (frame {c.frames}); lower train.lr or check the rewards")
        return total / max(n, 1)

    def _learner_scalar_names(self) -> list[str]:
        return [name for learner in self.learners for name in learner.scalar_names()]

    def set_learning_rate(self) -> None:
        """The Q optimiser's learning rate at the frame count reached: ``train.lr``, decayed linearly to
        ``train.lr_end`` over ``train.total_frames`` when that is set."""
        t = self.run.train
        if t.lr_end is None:
            return
        lr = linear_schedule(t.lr, t.lr_end, t.total_frames, self.counters.frames)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def update_once(self, sample: TensorDictBase) -> float:
        """One update on a sampled batch: each auxiliary learner's step on it, then a gradient step on
        each batch of the update part (the sample, then any simulated one), the target copy when it
        is due; returns the loss of the first batch."""
        for learner in self.learners:  # before the Q steps, which may read what they learn (a simulated batch's reward)
            for name, value in learner.step(sample).items():
                self._learner_sums[name] = self._learner_sums.get(name, 0.0) + value
        self.strategy.before_update(self.loss)
        loss = None
        for name, batch in self.update_part.batches(sample):
            value = self.loss.loss_and_grad(batch)["loss"]  # gradients into the Q network's .grad
            if self.run.train.grad_clip_norm is not None:
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.run.train.grad_clip_norm)
            self.optimizer.step()
            if loss is None:
                loss = value
            else:
                self._part_losses.setdefault(name, []).append(float(value))
        self.counters.updates += 1
        if self.run.train.target_tau < 1:
            self.loss.update_target_polyak(self.run.train.target_tau)
        elif self.counters.updates % self.updates_per_copy == 0:
            self.loss.update_target()
        value = float(loss.detach())
        if not math.isfinite(value):
            raise NonFiniteError(f"the loss became non-finite ({value}) at update {self.counters.updates} "
                                 f"(frame {self.counters.frames}); lower train.lr or check the rewards")
        return value

    def _validate(self) -> EpisodeMetrics:
        c, t = self.counters, self.run.train
        c.last_val = c.frames
        with self.strategy.evaluating():  # the strategy's greedy setting (e.g. its mean weights)
            metrics, _ = evaluate(self.val_env, self.policy, num_episodes=t.val_episodes)
        score = metrics.success_rate + 1e-3 * metrics.average_return  # ties broken by return
        row = {"kind": "val", "frames": c.frames, "updates": c.updates, "episodes": c.episodes,
               **{f"val/{k}": v for k, v in metrics.as_dict().items()},
               # how far below the running best score this validation fell (0 at a new best): a collapse shows here
               "val/drop_from_best": max(0.0, c.best_val - score) if math.isfinite(c.best_val) else 0.0}
        if score > c.best_val:
            c.best_val, c.best_frames = score, c.frames
            best = {"net": self.net.state_dict(), "config": self.config_dict, "frames": c.frames, "val": metrics.as_dict()}
            for learner in self.learners:  # what the planner acts with (the crowd predictor)
                best.update(learner.policy_state())
            save_checkpoint(self.ckpt_dir / "best.pt", best, self.fingerprint)
            row["val/best"] = 1
        self.emit(row)
        return metrics

    def _log_train(self, episodes: list[tuple[int, float, int, float]], loss_value: float) -> None:
        c = self.counters
        n = len(episodes)
        events = [e for e, *_ in episodes]
        succ_steps = [s for e, _, s, _ in episodes if e == SUCCESS]
        timeout_dist = [d for e, _, _, d in episodes if e == TIMEOUT]
        self.emit({
            "kind": "train", "frames": c.frames, "updates": c.updates, "episodes": c.episodes,
            "train/success_rate": events.count(SUCCESS) / n,
            "train/collision_rate": events.count(COLLISION) / n,
            "train/timeout_rate": events.count(TIMEOUT) / n,
            "train/return": sum(r for _, r, _, _ in episodes) / n,
            "train/episode_length": sum(s for _, _, s, _ in episodes) / n,
            # how far from its goal a timed-out robot stopped: hovering near it, or gone far away
            "train/timeout_goal_distance": sum(timeout_dist) / len(timeout_dist) if timeout_dist else math.nan,
            "train/navigation_time": (sum(succ_steps) / len(succ_steps) * self.crowd_cfg.time_step) if succ_steps else math.nan,
            **{f"train/{k}": v for k, v in self.strategy.scalars().items()},
            "train/loss": loss_value,
            **{f"train/{k}": v for k, v in self.learner_scalars.items()},
            **{f"train/loss_{name}": sum(v) / len(v) for name, v in self._part_losses.items() if v},
            **{f"train/{k}": v for k, v in self.update_part.scalars().items()},
            **{f"time/{k}_s": v for k, v in self.counters.timers().items()},
        })
        self._part_losses.clear()

    def emit(self, row: dict[str, Any]) -> None:
        """Append a row of scalars to the run's log (and wandb when on)."""
        self.log.log(row)
        if self.wandb is not None:
            self.wandb.log(row)

    def write_status(self, state: str, **info: Any) -> None:
        """Atomically rewrite ``status.json``: ``{"state": state, **info}``."""
        atomic_write_json(self.dir / "status.json", {"state": state, **info}, default=str)

    def close(self) -> None:
        if self.log is not None:
            self.log.close()
        if self.wandb is not None:
            self.wandb.close()
            self.wandb = None


def _merge(payload: dict[str, Any], part: dict[str, Any], owner: str) -> None:
    """Add ``part``'s top-level checkpoint keys to ``payload``; ``KeyError`` for a key already there."""
    clash = sorted(set(part) & set(payload))
    if clash:
        raise KeyError(f"{owner} writes checkpoint keys already taken: {clash}")
    payload.update(part)


def _finished_episodes(batch: TensorDictBase) -> list[tuple[int, float, int, float]]:
    """``(event, return, steps, distance to the goal at the end)`` of the episodes that ended in ``batch``."""
    nxt = batch.get("next")
    done = nxt.get("done").reshape(-1)
    if not bool(done.any()):
        return []
    events = nxt.get("event").reshape(-1)[done].tolist()
    returns = nxt.get("episode_reward").reshape(-1)[done].tolist()
    steps = nxt.get("step_count").reshape(-1)[done].tolist()
    robot = nxt.get("robot")  # world frame: px, py, vx, vy, radius, gx, gy, ...
    robot = robot.reshape(-1, robot.shape[-1])[done]
    dist = (robot[:, 5:7] - robot[:, 0:2]).norm(dim=-1).tolist()
    return list(zip(events, returns, steps, dist))


def _progress(enabled: bool, total: int, initial: int):
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError as exc:
        from crowdrl._extras import missing

        raise missing("tqdm", "train", "the progress bar (logger.progress_bar=false does without)") from exc

    return tqdm(total=total, initial=initial, unit="frame", dynamic_ncols=True, smoothing=0.05)


__all__ = ["Trainer", "NonFiniteError", "CheckpointError"]
