"""D3QN training on CrowdNavEnv: TorchRL collector, n-step replay, double DQN, validation,
atomic checkpoints and resume.

One ``Trainer`` is one run folder. The loop: collect ``num_envs x steps_per_batch`` frames with
the ε-greedy policy, write them to the replay buffer as n-step transitions, do
``updates_per_frame`` updates of batch ``batch_size`` per collected frame, copy the target
network every ``target_update_frames`` frames, validate greedily on held-out validation
episodes every ``val_every_frames`` frames (the best policy is kept), checkpoint every
``checkpoint_every_frames`` frames.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from crowdrl.evaluation import EpisodeMetrics, evaluate
from crowdrl.exploration.dropout import set_dropout_p
from crowdrl.exploration.noisy import noise_disabled, reset_noise
from crowdrl.exploration.schedule import linear_schedule
from crowdrl.sim.crowd import COLLISION, SUCCESS, TIMEOUT
from crowdrl.files import atomic_write_json
from crowdrl.training.checkpoint import CheckpointError, config_fingerprint, load_checkpoint, save_checkpoint
from crowdrl.training.config import RunConfig, sees_obstacles, to_dict
from crowdrl.training.factories import (MASK_KEY, buffer_state_dict, make_actor, make_buffer, make_collector, make_env,
                                        make_exploration, make_loss, make_optimizer, make_predictor_of, make_update_part,
                                        obs_keys, stored_keys)
from crowdrl.training.predictor_loss import PredictorLoss
from crowdrl.training.scalars import ScalarLog, WandbMirror
from crowdrl.training.variants import make_bonus, make_network


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

    @classmethod
    def from_dict(cls, data: dict) -> "Counters":
        """The counters of a checkpoint; ``ValueError`` naming a missing or unknown counter."""
        names = {f.name for f in fields(cls)}
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
        self.net = make_network(run, int(self.env.action_spec.n)).to(run.device)
        # online planning: the crowd predictor (seeded apart from the global RNG) and its own Adam
        self.predictor = make_predictor_of(run, self.crowd_cfg.time_step)
        self.predictor_optimizer = None
        if self.predictor is not None and any(True for _ in self.predictor.parameters()):
            self.predictor_optimizer = make_optimizer(run, self.predictor, lr=run.planning.lr)
            # its loss and gradients: one compiled graph under train.compile_loss, as the Q update
            self.predictor_loss_fn = PredictorLoss(self.predictor, compile=run.train.compile_loss)
        self.actor = make_actor(run, self.env, self.net, self.predictor)
        self.policy, self.egreedy = make_exploration(run, self.env, self.actor)
        self.loss = make_loss(run, self.net, self.obs_keys)
        # the target network is copied every `updates_per_copy` updates (target_update_frames of data)
        self.updates_per_copy = max(1, round(t.target_update_frames * max(t.updates_per_frame, 1e-9)))
        self.optimizer = make_optimizer(run, self.net)
        self.counters = Counters()
        # ICM / RE3: built after the Q network, from their own seeds (the global RNG is untouched)
        self.bonus = make_bonus(run, list(self.obs_keys), int(self.env.action_spec.n))
        if self.bonus is not None:
            self.bonus.to(run.device)
        self.buffer, self.intrinsic = make_buffer(run, self.bonus, lambda: self.counters.frames, self.obs_keys)
        # the gradient steps of one update (the sampled batch; with counterfactual experience, simulated ones too)
        self.update_part = make_update_part(run, self.net, self.obs_keys, self.crowd_cfg, self.intrinsic)
        self.stored_keys += [k for k in self.update_part.stored_keys() if k not in self.stored_keys]
        self.log = None
        self.wandb = None
        self._restored: dict[str, Any] | None = None
        self._stop_requested = False
        self.predictor_loss = math.nan  # mean predictor loss of the last batch's updates (NaN: none)
        self._predictor_loss_sum = 0.0
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
            # for an exact resume: the in-flight episodes, the finished ones not yet logged, the last bonus stats
            "env": self.env.base_env.snapshot() if self.env.base_env.state is not None else None,
            "pending_episodes": list(self._pending_episodes),
            "intrinsic_stats": dict(self.intrinsic.last_stats) if self.intrinsic is not None else None,
            # the running statistics of the bonus's normalisers (obs, reward, terminal value)
            "intrinsic_norm": self.intrinsic.stats_state_dict() if self.intrinsic is not None else None,
            "update_part": self.update_part.state_dict(),
        }
        if self.bonus is not None:
            payload["bonus"] = self.bonus.state_dict()
            if getattr(self.bonus, "optimizer", None) is not None:
                payload["bonus_optimizer"] = self.bonus.optimizer.state_dict()
        if self.predictor_optimizer is not None:
            payload["predictor"] = self.predictor.state_dict()
            payload["predictor_optimizer"] = self.predictor_optimizer.state_dict()
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
        self.update_part.load_state_dict(data.get("update_part", {}))  # a checkpoint before parts: none had state
        if self.intrinsic is not None:
            if data.get("intrinsic_stats") is not None:
                self.intrinsic.last_stats = dict(data["intrinsic_stats"])
            self.intrinsic.load_stats_state_dict(data["intrinsic_norm"])
        if self.bonus is not None:
            self.bonus.load_state_dict(data["bonus"])
            if "bonus_optimizer" in data:
                self.bonus.optimizer.load_state_dict(data["bonus_optimizer"])
        if self.predictor_optimizer is not None:
            self.predictor.load_state_dict(data["predictor"])
            self.predictor_optimizer.load_state_dict(data["predictor_optimizer"])
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
        self._set_schedules()  # a resumed run acts with the schedules of its frame count, not their start
        if c.frames >= t.total_frames:  # killed after training, e.g. during the test: nothing left to train
            summary = self._summary({"collect": 0.0, "update": 0.0, "validate": 0.0})
            self.write_status("trained", **summary)
            return summary
        collector = make_collector(run, self.env, self.policy)  # its first reset continues restored episodes
        if resume_data:  # the collector's set-up may draw random numbers: the stream continues from here
            self._set_rng(resume_data)
        bar = _progress(run.logger.progress_bar, t.total_frames, c.frames)
        timers = {"collect": 0.0, "update": 0.0, "validate": 0.0}
        recent = self._pending_episodes  # (event, return, steps, goal distance) of finished episodes not yet logged
        try:
            tick = time.perf_counter()
            for batch in collector:
                timers["collect"] += time.perf_counter() - tick
                frames = batch.numel()
                c.frames += frames
                c.next_train_episode = self.env.base_env.next_episode
                finished = _finished_episodes(batch)
                c.episodes += len(finished)
                recent.extend(finished)
                self.buffer.extend(batch.select(*self.stored_keys))
                tick = time.perf_counter()
                loss_value = self._update(frames)
                timers["update"] += time.perf_counter() - tick
                self._set_schedules()
                if run.exploration.name == "noisy":
                    reset_noise(self.net)  # a fresh noise sample for the next batch's actions
                if c.frames - c.last_val >= t.val_every_frames or c.frames >= t.total_frames:
                    tick = time.perf_counter()
                    self._validate()
                    timers["validate"] += time.perf_counter() - tick
                if recent and (len(recent) >= 20 or c.frames >= t.total_frames):
                    self._log_train(recent, loss_value, timers)
                    recent.clear()
                if bar is not None:
                    bar.update(frames)
                    bar.set_postfix(eps=f"{float(self.egreedy.eps):.3f}", episodes=c.episodes,
                                    best_val_score=f"{c.best_val:.3f}")
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
        summary = self._summary(timers)
        self.write_status("trained", **summary)
        return summary

    def _summary(self, timers: dict) -> dict[str, Any]:
        c = self.counters
        return {"frames": c.frames, "updates": c.updates, "episodes": c.episodes,
                "best_val_score": c.best_val,  # validation success + 1e-3 * return
                "best_frames": c.best_frames, "timers_s": timers}

    def _set_schedules(self) -> None:
        """ε and the dropout p for the frame count reached (before each collected batch)."""
        x, frames = self.run.exploration, self.counters.frames
        self.egreedy.eps.fill_(linear_schedule(x.eps_start, x.eps_end, x.anneal_frames, frames))
        if x.name == "dropout":
            set_dropout_p(self.net, linear_schedule(x.dropout_start, x.dropout_end, x.anneal_frames, frames))

    def _update(self, frames: int) -> float:
        t, c = self.run.train, self.counters
        c.update_credit += frames * t.updates_per_frame
        n = int(c.update_credit)
        c.update_credit -= n
        self.predictor_loss, self._predictor_loss_sum = math.nan, 0.0
        if c.frames < t.warmup_frames:  # warm-up of a fresh run: no updates owed
            return math.nan
        if len(self.buffer) < max(t.batch_size, min(t.warmup_frames, t.buffer_size)):
            # a run resumed without its buffer refills it first; the updates stay owed
            c.update_credit += n
            return math.nan
        total = 0.0
        for _ in range(n):
            total += self.update_once(self.buffer.sample())
        if n and self.predictor_optimizer is not None:
            self.predictor_loss = self._predictor_loss_sum / n
        params = [*self.net.parameters(), *(self.predictor.parameters() if self.predictor is not None else ())]
        if n and not bool(torch.stack([torch.isfinite(p).all() for p in params]).all()):  # one sync
            raise NonFiniteError(f"the Q network's weights became non-finite by update {c.updates} "
                                 f"(frame {c.frames}); lower train.lr or check the rewards")
        return total / max(n, 1)

    def update_once(self, sample: TensorDictBase) -> float:
        """One update on a sampled batch: a gradient step on each batch of the update part (the sample,
        then any simulated one), the predictor's step, the target copy when it is due; returns the
        loss of the first batch."""
        if self.run.exploration.name == "noisy":
            reset_noise(self.loss)  # independent noise for the online and the target network
        loss = None
        for name, batch in self.update_part.batches(sample):
            value = self.loss.loss_and_grad(batch)["loss"]  # gradients into the Q network's .grad
            self.optimizer.step()
            if loss is None:
                loss = value
            else:
                self._part_losses.setdefault(name, []).append(float(value))
        if self.predictor_optimizer is not None:
            self._predictor_loss_sum += self.predictor_step(sample)
        self.counters.updates += 1
        if self.counters.updates % self.updates_per_copy == 0:
            self.loss.update_target()
        value = float(loss.detach())
        if not math.isfinite(value):
            raise NonFiniteError(f"the loss became non-finite ({value}) at update {self.counters.updates} "
                                 f"(frame {self.counters.frames}); lower train.lr or check the rewards")
        return value

    def predictor_step(self, sample: TensorDictBase) -> float:
        """One Adam step of the crowd predictor: MSE to the sampled transitions' real next human states."""
        loss = self.predictor_loss_fn.loss_and_grad(sample.get("robot"), sample.get("humans"),
                                                    sample.get(("next", "humans")),
                                                    sample.get(MASK_KEY) if MASK_KEY in self.obs_keys else None)
        self.predictor_optimizer.step()
        return float(loss)

    def _validate(self) -> EpisodeMetrics:
        c, t = self.counters, self.run.train
        c.last_val = c.frames
        with noise_disabled(self.net):  # greedy on the mean weights (no-op without noisy layers)
            metrics, _ = evaluate(self.val_env, self.policy, num_episodes=t.val_episodes)
        score = metrics.success_rate + 1e-3 * metrics.average_return  # ties broken by return
        row = {"kind": "val", "frames": c.frames, "updates": c.updates, "episodes": c.episodes,
               **{f"val/{k}": v for k, v in metrics.as_dict().items()},
               # how far below the running best score this validation fell (0 at a new best): a collapse shows here
               "val/drop_from_best": max(0.0, c.best_val - score) if math.isfinite(c.best_val) else 0.0}
        if score > c.best_val:
            c.best_val, c.best_frames = score, c.frames
            best = {"net": self.net.state_dict(), "config": self.config_dict, "frames": c.frames, "val": metrics.as_dict()}
            if self.predictor_optimizer is not None:
                best["predictor"] = self.predictor.state_dict()
            save_checkpoint(self.ckpt_dir / "best.pt", best, self.fingerprint)
            row["val/best"] = 1
        self.emit(row)
        return metrics

    def _log_train(self, episodes: list[tuple[int, float, int, float]], loss_value: float, timers: dict) -> None:
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
            "train/epsilon": float(self.egreedy.eps),
            "train/loss": loss_value,
            **({"train/predictor_loss": self.predictor_loss} if self.predictor_optimizer is not None else {}),
            **({f"train/intrinsic_{k}": v for k, v in self.intrinsic.last_stats.items()} if self.intrinsic else {}),
            **{f"train/loss_{name}": sum(v) / len(v) for name, v in self._part_losses.items() if v},
            **{f"train/{k}": v for k, v in self.update_part.scalars().items()},
            **{f"time/{k}_s": v for k, v in timers.items()},
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
