"""The stable-bonus options of ``crowdrl.exploration``: running statistics, reward and observation
normalisation, the terminal value, ICM's feature scale, β schedules, and their config keys."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn

from crowdrl.exploration import ICM, RE3, IntrinsicRewardTransform
from crowdrl.exploration.normalize import ObservationNormalizer, RewardNormalizer, RunningMeanStd
from crowdrl.exploration.schedule import exp_schedule, linear_schedule, make_schedule
from crowdrl.training.config import ConfigError
from crowdrl.training.validation import validate

OBS_DIM, NUM_ACTIONS = 4, 3


def stream(n_batches: int = 20, batch: int = 50, shape: tuple = (), loc: float = 3.0, scale: float = 2.0,
           seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [loc + scale * torch.randn(batch, *shape, generator=g) for _ in range(n_batches)]


def transitions(n: int = 64, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": 10.0 + 5.0 * torch.randn(n, OBS_DIM, generator=g),
        "action": torch.randint(0, NUM_ACTIONS, (n,), generator=g),
        "next": {"observation": 10.0 + 5.0 * torch.randn(n, OBS_DIM, generator=g),
                 "reward": torch.randn(n, 1, generator=g),
                 "terminated": torch.zeros(n, 1, dtype=torch.bool),
                 "done": torch.zeros(n, 1, dtype=torch.bool)},
    }, batch_size=[n])


def encoder() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(OBS_DIM, 32), nn.ReLU())


# ----------------------------------------------------------------------------- running statistics
def test_running_mean_std_equals_the_moments_of_everything_seen_elementwise():
    batches = stream(shape=(3, 2))
    stats = RunningMeanStd((3, 2))
    for b in batches:
        stats.update(b)
    every = torch.cat(batches).double().numpy()
    assert int(stats.count) == every.shape[0]
    np.testing.assert_allclose(stats.mean.numpy(), every.mean(0), rtol=1e-12)
    np.testing.assert_allclose(stats.var.numpy(), every.var(0), rtol=1e-10)
    with pytest.raises(ValueError, match="shape"):
        stats.update(torch.zeros(5, 2, 3))


def test_the_std_normalised_bonus_has_the_stated_running_std():
    norm = RewardNormalizer("std")
    batches = stream()
    out = [norm(b) for b in batches]
    every = torch.cat(batches).double()
    assert float(norm.stats.std) == pytest.approx(float(every.std(correction=0)), rel=1e-10)
    # the last batch is divided by the std of everything seen up to and including it, not centred
    assert torch.allclose(out[-1].double(), batches[-1].double() / every.std(correction=0), rtol=1e-6)
    assert float(out[-1].mean()) > 1.0  # the positive mean survives without centring (3 / 2 here)


def test_mean_centring_gives_a_zero_mean_bonus():
    batches = stream()
    running = RewardNormalizer("std", center=True)
    centred = torch.cat([running(b) for b in batches])
    assert abs(float(centred[-500:].mean())) < 0.1 and float(centred[-500:].std()) == pytest.approx(1.0, abs=0.1)
    batch = RewardNormalizer("batch", center=True)
    for b in batches:
        r = batch(b).double()
        assert abs(float(r.mean())) < 1e-6 and float(r.std(correction=0)) == pytest.approx(1.0, rel=1e-5)


def test_the_clip_bounds_the_normalised_bonus_and_bad_settings_are_refused():
    norm = RewardNormalizer("batch", center=True, clip=0.5)
    r = norm(torch.arange(100.0))
    assert float(r.max()) == 0.5 and float(r.min()) == -0.5
    with pytest.raises(ValueError, match="scale"):
        RewardNormalizer("rnd")
    for clip in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="clip"):
            RewardNormalizer("std", clip=clip)


def test_observation_normalizer_whitens_float_inputs_passes_masks_and_reloads():
    norm = ObservationNormalizer(clip=5.0)
    mask = torch.ones(50, 3, dtype=torch.bool)
    for b in stream(shape=(3, 2), loc=-7.0, scale=4.0):
        x, m = norm([b, mask], batch_dims=1)
    every = torch.cat(stream(shape=(3, 2), loc=-7.0, scale=4.0)).double()
    assert torch.equal(m, mask)
    expected = ((b.double() - every.mean(0)) / every.std(0, correction=0)).clamp(-5, 5)
    assert torch.allclose(x.double(), expected, atol=1e-5)
    assert float(norm([torch.full((2, 3, 2), 1e6)], batch_dims=1, update=False)[0].max()) == 5.0
    fresh = ObservationNormalizer(clip=5.0)
    fresh.load_state_dict(norm.state_dict())  # its statistics are made from the saved state
    assert torch.equal(fresh([b], 1, update=False)[0], norm([b], 1, update=False)[0])


# ----------------------------------------------------------------------------- the transform
def test_the_transform_applies_obs_and_reward_normalisation_and_logs_diagnostics():
    re3 = RE3(encoder(), feature_dim=32, seed=1)
    t = IntrinsicRewardTransform(re3, beta=0.1, obs_norm=ObservationNormalizer(),
                                 reward_norm=RewardNormalizer("batch", center=True))
    td = t(transitions())
    r_in = td["next", "reward_int"].squeeze(-1)
    assert abs(float(r_in.mean())) < 1e-6
    assert torch.allclose(td["next", "reward"], td["next", "reward_ext"] + 0.1 * td["next", "reward_int"])
    s = t.last_stats
    for key in ("reward_int_raw_mean", "reward_int_raw_std", "reward_int_raw_max", "reward_int_std",
                "reward_int_scaled_mean", "reward_int_scaled_max", "reward_int_share"):
        assert key in s and math.isfinite(s[key]), key
    assert s["reward_int_raw_mean"] > 0.5  # log(1 + d / sigma) before centring
    assert 0.0 < s["reward_int_share"] < 1.0
    # the bonus saw whitened inputs: the same transitions shifted by 1000 give the same bonus once
    # the statistics have seen them
    shifted = transitions()
    shifted["observation"] += 1000.0
    shifted["next", "observation"] += 1000.0
    t2 = IntrinsicRewardTransform(RE3(encoder(), feature_dim=32, seed=1), beta=0.1, obs_norm=ObservationNormalizer())
    t3 = IntrinsicRewardTransform(RE3(encoder(), feature_dim=32, seed=1), beta=0.1, obs_norm=ObservationNormalizer())
    a = t2(transitions())["next", "reward_int"]
    b = t3(shifted)["next", "reward_int"]
    assert torch.allclose(a, b, rtol=1e-3, atol=1e-4)


def test_terminal_transitions_get_the_value_of_the_forgone_bonus():
    gamma, beta = 0.9, 0.5
    t = IntrinsicRewardTransform(RE3(encoder(), feature_dim=32, seed=1), beta=beta, terminal_value_gamma=gamma)
    td = transitions(32)
    ended = torch.zeros(32, 1, dtype=torch.bool)
    ended[[3, 17]] = True
    td["next", "terminated"] = ended
    td["steps_to_next_obs"] = torch.full((32, 1), 2)
    out = t(td.clone())
    mean = float(t.bonus_stats.mean)  # after this batch: its own mean
    assert mean == pytest.approx(float(out["next", "reward_int"].mean()), rel=1e-6)
    extra = out["next", "reward"] - out["next", "reward_ext"] - beta * out["next", "reward_int"]
    want = torch.where(ended, beta * mean * gamma ** 2 / (1 - gamma), 0.0)
    assert torch.allclose(extra, want, atol=1e-6)
    assert t.last_stats["reward_int_terminal_mean"] == pytest.approx(float(want.mean()), rel=1e-5)
    with pytest.raises(ValueError, match="terminal_value_gamma"):
        IntrinsicRewardTransform(RE3(encoder(), feature_dim=32, seed=1), terminal_value_gamma=1.0)


def test_the_statistics_round_trip_through_stats_state_dict():
    def make():
        return IntrinsicRewardTransform(RE3(encoder(), feature_dim=32, seed=1), beta=0.1,
                                        obs_norm=ObservationNormalizer(), reward_norm=RewardNormalizer("std", center=True))
    a = make()
    for seed in range(3):
        a(transitions(seed=seed))
    b = make()
    b.bonus.load_state_dict(a.bonus.state_dict())
    b.load_stats_state_dict(a.stats_state_dict())
    assert torch.equal(a(transitions(seed=9))["next", "reward"], b(transitions(seed=9))["next", "reward"])
    with pytest.raises(KeyError, match="obs_norm"):
        IntrinsicRewardTransform(RE3(encoder(), feature_dim=32, seed=1)).load_stats_state_dict(a.stats_state_dict())


# ----------------------------------------------------------------------------- ICM's feature scale
@pytest.mark.parametrize("feature_norm", ["none", "layernorm"])
def test_icm_feature_norm_stays_bounded_when_the_inverse_loss_alone_trains(feature_norm):
    # each action moves the state along its own axis, so the inverse model can become certain
    g = torch.Generator().manual_seed(0)
    action = torch.randint(0, NUM_ACTIONS, (64,), generator=g)
    s = torch.randn(64, OBS_DIM, generator=g)
    td = TensorDict({"observation": s, "action": action,
                     "next": {"observation": s + torch.eye(OBS_DIM)[action]}}, batch_size=[64])
    icm = ICM(encoder(), NUM_ACTIONS, feature_dim=32, seed=1, lr=1e-3, inverse_weight=1.0, feature_norm=feature_norm)
    stats = [icm.update(td) for _ in range(300)]
    first, last = stats[0]["icm_feature_norm"], stats[-1]["icm_feature_norm"]
    assert stats[-1]["icm_inverse_accuracy"] == 1.0
    if feature_norm == "layernorm":
        assert first == pytest.approx(math.sqrt(128), rel=1e-2) and last == pytest.approx(math.sqrt(128), rel=1e-2)
    else:  # the authors' features: the inverse loss inflates their scale (1.1 -> 9.8 here), which layernorm prevents
        assert last > 5 * first


def test_icm_refuses_an_unknown_feature_norm():
    with pytest.raises(ValueError, match="feature_norm"):
        ICM(encoder(), NUM_ACTIONS, feature_dim=32, feature_norm="batchnorm")


# ----------------------------------------------------------------------------- β schedules
def test_each_schedule_gives_its_formula():
    clock = {"t": 0}
    now = lambda: clock["t"]  # noqa: E731
    assert make_schedule("constant", 0.02) == 0.02
    lin = make_schedule("linear", 0.02, end=0.005, duration=1000, clock=now)
    ex = make_schedule("exp", 0.02, decay=1e-3, clock=now)
    for t in (0, 250, 1000, 5000):
        clock["t"] = t
        assert lin() == pytest.approx(0.005 + 0.015 * max(0.0, 1 - t / 1000)) == linear_schedule(0.02, 0.005, 1000, t)
        assert ex() == pytest.approx(0.02 * 0.999 ** t) == exp_schedule(0.02, 1e-3, t)
    for kwargs, match in (({"kind": "cosine"}, "unknown"), ({"kind": "linear", "end": 0.0}, "duration"),
                          ({"kind": "exp"}, "decay"), ({"kind": "exp", "decay": -0.1}, "decay"),
                          ({"kind": "exp", "decay": math.nan}, "decay"), ({"kind": "exp", "decay": 1.0}, "decay")):
        kind = kwargs.pop("kind")
        with pytest.raises(ValueError, match=match):
            make_schedule(kind, 0.01, clock=now, **kwargs)


# ----------------------------------------------------------------------------- config keys
def _run(name: str = "re3", **exploration):
    return {"exploration": {"name": name, **exploration}}


@pytest.mark.parametrize("exploration, key", [
    ({"reward_norm": "rnd"}, "exploration.reward_norm"),
    ({"beta_schedule": "cosine"}, "exploration.beta_schedule"),
    ({"beta_schedule": "exp"}, "exploration.beta_decay"),
    ({"beta_schedule": "exp", "beta_decay": -1e-5}, "exploration.beta_decay"),
    ({"beta_schedule": "exp", "beta_decay": float("nan")}, "exploration.beta_decay"),
    ({"beta_schedule": "exp", "beta_decay": float("inf")}, "exploration.beta_decay"),
    ({"beta_schedule": "linear"}, "exploration.beta_end"),
    ({"beta_decay": 1e-5}, "exploration.beta_decay"),
    ({"beta_schedule": "exp", "beta_decay": 1e-5, "beta_end": 0.0}, "exploration.beta_end"),
    ({"reward_clip": 0.0}, "exploration.reward_clip"),
    ({"obs_clip": -1.0}, "exploration.obs_clip"),
    ({"icm_feature_norm": "batchnorm"}, "exploration.icm_feature_norm"),
])
def test_bad_intrinsic_settings_are_refused_naming_the_key(exploration, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate(_run(**exploration))


def test_intrinsic_options_on_another_variant_and_terminal_value_without_discount_are_refused():
    with pytest.raises(ConfigError, match=r"exploration\.obs_norm: applies to icm, re3, rnd only; exploration\.name is"):
        validate(_run("egreedy", obs_norm=True))
    with pytest.raises(ConfigError, match=r"exploration\.terminal_value"):
        validate({**_run(terminal_value=True), "train": {"gamma": 1.0}})


def test_an_old_run_config_without_the_new_keys_builds_the_published_transform():
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import replay_context

    def transform(run, frames):
        return make_strategy(run.exploration).replay_transform(replay_context(run, ["robot_rc", "humans_rc"], 81,
                                                                              lambda: frames))

    old = validate({"exploration": {"name": "icm", "beta": 0.02, "beta_end": None}})
    t = transform(old, 0)
    assert t.obs_norm is None and t.reward_norm is None and t.terminal_value_gamma is None and t.beta == 0.02
    assert t.bonus.feature_norm == "none" and t.bonus.detach_target
    old_linear = validate({"exploration": {"name": "re3", "beta": 0.02, "beta_end": 0.0, "anneal_frames": 100}})
    t = transform(old_linear, 50)
    assert t.current_beta() == pytest.approx(0.01)  # beta_end alone still means a linear decay


def _composed_exploration(group: str):
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore

    from crowdrl.training.config import RunConfig

    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()
    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"exploration={group}", "preset=demo", "logger=csv"])
    return validate(cfg).exploration


def test_the_config_groups_hold_the_chosen_defaults_and_the_published_arms():
    from dataclasses import asdict

    from crowdrl.exploration.intrinsic_strategy import INTRINSIC_OPTIONS
    from crowdrl.training.config import ExplorationConfig

    published = ExplorationConfig()
    for name in ("icm", "re3"):
        chosen, paper = _composed_exploration(name), _composed_exploration(f"{name}_published")
        assert chosen.name == paper.name == name
        assert (chosen.beta_schedule, chosen.beta_decay, chosen.beta) == ("exp", 1e-5, 0.01)
        if name == "icm":  # ICM: every stable option; RE3: the decaying β alone (results/intrinsic/val)
            assert (chosen.reward_norm, chosen.reward_center, chosen.reward_clip, chosen.obs_norm) == ("batch", True, 5.0, True)
            assert chosen.icm_feature_norm == "layernorm"
        else:
            assert (chosen.reward_norm, chosen.reward_center, chosen.obs_norm) == ("none", False, False)
        # the published arm is the schema's default: what run folders written before the options rebuild
        assert {k: asdict(paper)[k] for k in INTRINSIC_OPTIONS} == {k: asdict(published)[k] for k in INTRINSIC_OPTIONS}
        assert paper.beta == 0.01 and paper.beta_end is None
