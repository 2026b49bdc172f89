"""The training loop of one run folder: collect, store, update, validate, checkpoint; resume.

One ``Trainer`` is one run folder. Per collected batch of ``num_envs x steps_per_batch`` frames
(a TorchRL collector acting with the exploration strategy's policy):

1. the batch goes into the replay buffer (n-step returns are written then);
2. ``updates_per_frame`` updates per collected frame, each :meth:`D3QNLearner.step
   <crowdrl.training.learner.D3QNLearner.step>` on a sampled batch of ``batch_size`` (the learner owns
   the loss, optimiser, gradient clip, target rule, learning-rate schedule and non-finite checks);
3. the strategy's schedules move on (ε, dropout p, β);
4. every ``val_every_frames`` a greedy validation on held-out episodes (the best policy is kept in
   ``checkpoints/best.pt``), every 20 finished episodes a ``train`` log row, every
   ``checkpoint_every_frames`` an atomic ``checkpoints/last.pt`` from which a killed run resumes exactly.

What the exploration variant adds comes through its :class:`~crowdrl.exploration.strategy.ExplorationStrategy`,
what else learns on the sampled batches through :class:`~crowdrl.auxiliary.AuxiliaryLearner` instances,
what the update does through its :class:`~crowdrl.training.parts.UpdatePart`: the loop names none of them.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import torch

from crowdrl.envs.episodes import FinishedEpisode, episode_statistics, finished_episodes
from crowdrl.evaluation import EpisodeMetrics, evaluate
from crowdrl.exploration import make_strategy
from crowdrl.files import atomic_write_json
from crowdrl.training.checkpoint import (CheckpointError, config_fingerprint, load_checkpoint, merge_payload,
                                        restore_rng, rng_state, save_checkpoint, val_checkpoint_name)
from crowdrl.training.acting import make_acting
from crowdrl.training.config import RunConfig, to_dict
from crowdrl.training.counters import Counters
from crowdrl.training.demonstrations import add_demonstrations
from crowdrl.training.facts import RunFacts
from crowdrl.training.factories import (buffer_state_dict, make_buffer, make_collector, make_env, make_exploration,
                                        make_learner)
from crowdrl.training.learner import NonFiniteError
from crowdrl.training.scalars import ScalarLog, WandbMirror, progress_bar
from crowdrl.training.variants import make_network, replay_context, successor_key


_log = logging.getLogger(__name__)


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
        self.facts = facts = RunFacts.of(run)  # the crowd, the observation keys, obstacles seen, the action count
        self.env = make_env(run, split="train")
        self.val_env = make_env(run, split="val", num_envs=t.val_episodes)  # same maker, held-out stream
        self.crowd_cfg = facts.crowd
        # the exploration strategy: its network surgery, acting policy, replay transform, learners
        self.strategy = make_strategy(run.exploration)
        self.net = make_network(run, facts.num_actions, strategy=self.strategy).to(run.device)
        # how it acts: greedy on Q, or the online planner with its crowd predictor (seeded apart from the global RNG)
        self.acting = make_acting(run.planning, facts, train=t, encoder=run.encoder.name, learn=True)
        self.predictor = self.acting.predictor
        self.actor = self.acting.actor(self.net, self.env)
        self.policy = make_exploration(self.env, self.actor, self.strategy)
        self.counters = Counters()
        # the strategy's replay transform (ICM / RE3: their own seeds, the global RNG is untouched)
        successor = successor_key(run, self.strategy)
        self.buffer = make_buffer(t, facts, self.strategy,
                                  replay_context(run, list(facts.obs_keys), facts.num_actions,
                                                 lambda: self.counters.frames, successor), successor)
        # the Q network's update: loss, optimiser, the update part (counterfactual experience), the auxiliary
        # learners (the strategy's, the crowd predictor), the target rule and the learning-rate schedule
        self.learner = make_learner(t, self.net, facts, self.strategy, self.acting, successor)
        # what the replay buffer keeps: the transitions, and what the predictor and the update part read
        self.stored_keys = facts.replay_keys(self.acting, self.learner.part)
        self.log = None
        self.wandb = None
        self._restored: dict[str, Any] | None = None
        self._stop_requested = False
        self._pending_episodes: list[FinishedEpisode] = []  # finished episodes not yet logged (logged by 20)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        payload = {
            **self.learner.state_dict(),  # loss, optimizer, part_losses, update_part
            "counters": self.counters.__dict__.copy(),
            **rng_state(),  # torch_rng, cuda_rng
            "config": self.config_dict,
            "wandb_id": self.wandb.id if self.wandb else None,
            # for an exact resume: the in-flight episodes, the finished ones not yet logged (plain tuples)
            "env": self.env.base_env.snapshot() if self.env.base_env.started else None,
            "pending_episodes": [tuple(e) for e in self._pending_episodes],
        }
        # the strategy's and the learners' own top-level keys
        for part in (self.strategy, *self.learner.learners):
            merge_payload(payload, part.state_dict(), type(part).__name__)
        if self.run.train.save_buffer:
            payload["buffer"] = buffer_state_dict(self.buffer)  # unwritten slots zeroed: identical runs, same bytes
        return payload

    def load_state_dict(self, data: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` of this code version; an older ``last.pt`` (its environments'
        snapshot of an older format) raises ``ValueError`` saying so, before anything is restored."""
        self.env.base_env.restore(data.get("env"))  # first: it names an older file's format
        self.learner.load_state_dict(data)
        self.counters = Counters.from_dict(data["counters"])
        restore_rng(data)
        self._pending_episodes = [FinishedEpisode(*e) for e in data["pending_episodes"]]
        for part in (self.strategy, *self.learner.learners):
            part.load_state_dict(data)
        if "buffer" in data:
            self.buffer.load_state_dict(data["buffer"])

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
        self.learner.set_frames(c.frames)
        if c.frames >= t.total_frames:  # killed after training, e.g. during the test: nothing left to train
            summary = self._summary()
            self.write_status("trained", **summary)
            return summary
        if resume_data is None and t.demonstrations.cases > 0:  # a fresh run: once, before the first batch
            self._add_demonstrations()
        collector = make_collector(t, self.env, self.policy, run.device)  # its first reset continues restored episodes
        if resume_data:  # the collector's set-up may draw random numbers: the stream continues from here
            restore_rng(resume_data)
        bar = progress_bar(t.total_frames, c.frames) if run.logger.progress_bar else None
        recent = self._pending_episodes
        try:
            tick = time.perf_counter()
            for batch in collector:
                c.collect_s += time.perf_counter() - tick
                frames = batch.numel()
                c.frames += frames
                c.next_train_episode = self.env.base_env.next_episode
                finished = finished_episodes(batch)
                c.episodes += len(finished)
                recent.extend(finished)
                self.buffer.extend(batch.select(*self.stored_keys))
                tick = time.perf_counter()
                loss_value = self.update(frames)
                c.update_s += time.perf_counter() - tick
                self.strategy.before_collection(c.frames)
                self.learner.set_frames(c.frames)
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
        c.demo_transitions, c.demo_s = report.transitions, report.search_s + report.play_s
        _log.info(report.summary())
        if not any(r.get("kind") == "demo" for r in self.log.rows()):  # a restart from scratch logged it already
            self.emit(report.log_row())

    def _summary(self) -> dict[str, Any]:
        c = self.counters
        return {"frames": c.frames, "updates": c.updates, "episodes": c.episodes,
                "best_val_score": c.best_val,  # validation success + 1e-3 * return
                "best_frames": c.best_frames, "timers_s": c.timers()}

    def update(self, frames: int) -> float:
        """The updates ``frames`` new frames earn (``updates_per_frame`` each, the fraction carried over);
        returns their mean loss (NaN: none)."""
        t, c = self.run.train, self.counters
        c.update_credit += frames * t.updates_per_frame
        n = int(c.update_credit)
        c.update_credit -= n
        self.learner.reset_scalars()
        if c.frames < t.warmup_frames:  # warm-up of a fresh run: no updates owed
            return math.nan
        if len(self.buffer) < max(t.batch_size, min(t.warmup_frames, t.buffer_size)):
            # a run resumed without its buffer refills it first; the updates stay owed
            c.update_credit += n
            return math.nan
        total = 0.0
        try:
            for _ in range(n):
                c.updates += 1
                total += self.learner.step(self.buffer.sample(), c.updates)
            if n:
                self.learner.check_finite_weights(c.updates)
        except NonFiniteError as exc:
            raise NonFiniteError(f"{exc} (frame {c.frames}); lower train.lr or check the rewards") from None
        return total / max(n, 1)

    def _validate(self) -> EpisodeMetrics:
        c, t = self.counters, self.run.train
        c.last_val = c.frames
        per_scenario: dict[str, EpisodeMetrics] = {}  # a scenario mix's: each scenario's own (logged, not selected on)
        with self.strategy.evaluating():  # the strategy's greedy setting (e.g. its mean weights)
            metrics, _ = evaluate(self.val_env, self.policy, num_episodes=t.val_episodes, per_scenario=per_scenario)
        score = metrics.success_rate + 1e-3 * metrics.average_return  # ties broken by return
        row = {"kind": "val", "frames": c.frames, "updates": c.updates, "episodes": c.episodes,
               **{f"val/{k}": v for k, v in metrics.as_dict().items()},
               **{f"val/{name}/{k}": v for name, m in per_scenario.items()
                  for k, v in m.as_dict().items() if k in ("success_rate", "collision_rate", "timeout_rate")},
               # how far below the running best score this validation fell (0 at a new best): a collapse shows here
               "val/drop_from_best": max(0.0, c.best_val - score) if math.isfinite(c.best_val) else 0.0}
        if score > c.best_val or t.keep_val_checkpoints:
            policy = {"net": self.net.state_dict(), "config": self.config_dict, "frames": c.frames,
                      "val": metrics.as_dict()}
            for learner in self.learner.learners:  # what the planner acts with (the crowd predictor)
                policy.update(learner.policy_state())
            if t.keep_val_checkpoints:  # the seconds trained before this validation: minutes to a quality
                save_checkpoint(self.ckpt_dir / val_checkpoint_name(c.frames), {**policy, "timers_s": c.timers()},
                                self.fingerprint)
            if score > c.best_val:
                c.best_val, c.best_frames = score, c.frames
                save_checkpoint(self.ckpt_dir / "best.pt", policy, self.fingerprint)
                row["val/best"] = 1
        self.emit(row)
        return metrics

    def _log_train(self, episodes: list[FinishedEpisode], loss_value: float) -> None:
        c = self.counters
        self.emit({
            "kind": "train", "frames": c.frames, "updates": c.updates, "episodes": c.episodes,
            **{f"train/{k}": v for k, v in episode_statistics(episodes, self.crowd_cfg.time_step).items()},
            **{f"train/{k}": v for k, v in self.strategy.scalars().items()},
            "train/loss": loss_value,
            **{f"train/{k}": v for k, v in self.learner.scalars().items()},
            **{f"train/{k}": v for k, v in self.learner.pop_part_losses().items()},
            **{f"train/{k}": v for k, v in self.learner.part.scalars().items()},
            **{f"time/{k}_s": v for k, v in self.counters.timers().items()},
        })

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


__all__ = ["Trainer", "NonFiniteError", "CheckpointError"]
