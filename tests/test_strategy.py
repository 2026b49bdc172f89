"""The exploration-strategy registry and the auxiliary-learner interface, through the trainer."""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass as dataclasses_dataclass
from dataclasses import make_dataclass as dataclasses_make

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from crowdrl.auxiliary import AuxiliaryLearner
from crowdrl.exploration import ICM, ExplorationStrategy, IntrinsicRewardTransform, make_strategy, register_strategy
from crowdrl.training import ConfigError, Trainer, validate
from crowdrl.training.checkpoint import load_checkpoint
from crowdrl.training.config import ExplorationConfig


class CountingLearner(AuxiliaryLearner):
    def __init__(self) -> None:
        self.steps = 0

    def step(self, sample):
        self.steps += 1
        return {"counting_steps": float(self.steps)}

    def scalar_names(self):
        return ("counting_steps",)

    def state_dict(self):
        return {"counting": self.steps}

    def load_state_dict(self, payload):
        self.steps = payload["counting"]


class CountingStrategy(ExplorationStrategy):
    """ε-greedy that counts the trainer's calls of its hooks."""

    def __init__(self, config) -> None:
        super().__init__(config)
        self.calls = {"schedule": 0, "before_collection": 0, "before_update": 0}
        self.learner = CountingLearner()

    def schedule(self, frames):
        self.calls["schedule"] += 1
        super().schedule(frames)

    def before_collection(self, frames):
        self.calls["before_collection"] += 1
        super().before_collection(frames)

    def before_update(self, loss):
        self.calls["before_update"] += 1

    def learners(self):
        return [self.learner]


register_strategy("counting", CountingStrategy)


def test_a_strategy_registered_outside_the_trainer_trains_logs_and_checkpoints(tmp_path):
    run = validate({"preset": "smoke", "encoder": {"name": "sarl"}, "env": {"num_humans": 4, "orca_backend": "eager"},
                    "logger": {"name": "csv", "progress_bar": False, "render": False},
                    "planning": {"enabled": False}, "exploration": {"name": "counting"},
                    "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 64, "warmup_frames": 32,
                              "batch_size": 16, "buffer_size": 1000, "updates_per_frame": 0.25,
                              "target_update_frames": 32, "val_every_frames": 64, "val_episodes": 2,
                              "checkpoint_every_frames": 64, "test_episodes": 2,
                              "compile_acting": False, "compile_loss": False}})
    trainer = Trainer(run, tmp_path)
    try:
        summary = trainer.train()
    finally:
        trainer.close()
    strategy = trainer.strategy
    assert isinstance(strategy, CountingStrategy)
    assert strategy.calls == {"schedule": 3, "before_collection": 2, "before_update": summary["updates"]}
    assert strategy.learner.steps == summary["updates"] > 0
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["counting"] == summary["updates"]
    assert 1 <= trainer.learner.scalars()["counting_steps"] <= summary["updates"]  # the last batch's mean
    rows = [json.loads(line) for line in (tmp_path / "scalars.jsonl").read_text().splitlines()]
    assert all("train/counting_steps" in r and "train/epsilon" in r for r in rows if r["kind"] == "train")


def test_an_unknown_strategy_is_refused_naming_the_registered_ones():
    with pytest.raises(ValueError, match="registered: egreedy"):
        make_strategy(ExplorationConfig(name="curiosity"))
    with pytest.raises(ConfigError, match=r"exploration\.name.*counting"):
        validate({"exploration": {"name": "curiosity"}})


def test_a_deferred_icm_step_equals_the_step_at_sample_time():
    """update_bonus=False + learn_from_last: the same bonus, the same weights after, as update_bonus=True."""
    torch.manual_seed(0)
    batch = TensorDict({"observation": torch.randn(16, 4), "action": torch.randint(0, 3, (16,)),
                        ("next", "observation"): torch.randn(16, 4), ("next", "reward"): torch.zeros(16, 1)},
                       batch_size=[16])
    icm = ICM(nn.Linear(4, 16), num_actions=3, feature_dim=16, seed=0)
    at_once = IntrinsicRewardTransform(icm, beta=0.1)
    deferred = IntrinsicRewardTransform(copy.deepcopy(icm), beta=0.1, update_bonus=False)
    for _ in range(3):
        a, b = at_once.add_bonus(batch.clone()), deferred.add_bonus(batch.clone())
        deferred.learn_from_last()
        assert torch.equal(a["next", "reward"], b["next", "reward"])
        assert at_once.last_stats == deferred.last_stats
    for p, q in zip(at_once.bonus.parameters(), deferred.bonus.parameters()):
        assert torch.equal(p, q)
    with pytest.raises(RuntimeError, match="learn_from_last"):
        deferred.learn_from_last()


def test_a_strategy_owns_its_keys_their_checks_and_an_exclusive_key_is_refused_elsewhere():
    from crowdrl.exploration.strategy import owned_keys

    assert owned_keys("noisy") == {"sigma0": 0.5} and owned_keys("egreedy") == {}
    assert set(owned_keys("re3")) - set(owned_keys("icm")) == {"re3_k"}  # the shared intrinsic keys, then its own
    with pytest.raises(ConfigError, match=r"exploration\.sigma0: must be > 0"):  # noisy's own check
        validate({"exploration": {"name": "noisy", "sigma0": 0.0}})
    with pytest.raises(ConfigError, match=r"exploration\.re3_k: must lie in 1\.\.train\.batch_size-1 \(31\)"):
        validate({"exploration": {"name": "re3", "re3_k": 32}, "train": {"batch_size": 32}})
    validate({"exploration": {"name": "icm", "re3_k": 32}, "train": {"batch_size": 32}})  # re3_k's bound: re3 only
    with pytest.raises(ConfigError, match=r"exploration\.icm_feature_norm: applies to icm only; .* 're3'"):
        validate({"exploration": {"name": "re3", "icm_feature_norm": "layernorm"}})


def test_a_key_added_to_a_strategy_at_its_default_changes_no_stored_fingerprint(monkeypatch):
    """The fingerprint hashes the keys there were, and a later key only under its strategy and off its default:
    every shipped pretrained agent keeps its fingerprint whichever strategy gains a key."""
    import dataclasses
    from pathlib import Path

    from crowdrl.exploration import strategy as registry
    from crowdrl.training.checkpoint import config_fingerprint, load_checkpoint

    stored = sorted((Path(__file__).resolve().parents[1] / "pretrained").glob("*/best.pt"))
    assert stored
    for path in stored:
        data = load_checkpoint(path)
        config, fingerprint = data["config"], data["fingerprint"]
        assert config_fingerprint(config) == fingerprint
        for name in registry.strategy_names():
            base = registry._SCHEMAS[name] or object
            grown = dataclasses.make_dataclass(f"Grown{name}", [("probe_gain", float, dataclasses.field(default=0.25))],
                                               bases=(base,) if base is not object else ())
            monkeypatch.setitem(registry._SCHEMAS, name, grown)
            with_key = {**config, "exploration": {**config["exploration"], "probe_gain": 0.25}}
            assert config_fingerprint(with_key) == fingerprint, (path, name)  # at its default: unchanged
            off = {**config, "exploration": {**config["exploration"], "probe_gain": 0.5}}
            # off its default it counts, but only under the strategy that owns it
            assert (config_fingerprint(off) != fingerprint) == (config["exploration"]["name"] == name), (path, name)
            monkeypatch.undo()


def test_a_strategy_registered_after_the_run_schema_is_built_with_new_keys_is_refused():
    @dataclasses_dataclass
    class LateConfig:
        late_rate: float = 1.0

    with pytest.raises(RuntimeError, match="import the module that registers 'late' before crowdrl.training"):
        register_strategy("late", ExplorationStrategy, LateConfig)
    with pytest.raises(ValueError, match="'sigma0' is declared otherwise"):
        register_strategy("late", ExplorationStrategy, dataclasses_make("Clash", [("sigma0", float, 0.9)]))
