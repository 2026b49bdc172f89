"""Mixed crowds (``human_model="mixed"``: ``social_force_share`` and ``linear_share`` of the humans, ORCA the
rest): the single models recovered at the extreme shares, each human moved by its own model over the whole
crowd, the per-episode counts and draws, the keys' validation, and what a run and an env keep of them."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from crowdrl.sim import crowd
from crowdrl.sim.config import HUMAN_MODELS, CrowdConfig
from crowdrl.sim.humans import human_velocities, linear_humans, orca_humans, social_force_humans
from crowdrl.sim.rng import episode_keys
from crowdrl.sim.scenarios import assign_human_models, initial_states
from crowdrl.sim.state import CrowdState

ORCA, SOCIAL_FORCE, LINEAR = (HUMAN_MODELS.index(m) for m in ("orca", "social_force", "linear"))


def _mixed(**kwargs) -> CrowdConfig:
    return CrowdConfig(human_model="mixed", **kwargs)


def _run(cfg: CrowdConfig, ids: torch.Tensor, steps: int) -> tuple[CrowdState, list]:
    """``steps`` steps of episodes ``ids`` of the test stream with a fixed robot motion (crossing the crowd)."""
    state = initial_states(cfg, episode_keys("test", 7, ids))
    results = []
    action = torch.tensor([[0.2, 0.9]]).repeat(len(ids), 1)
    for _ in range(steps):
        state, result = crowd.step(cfg, state, action)
        results.append(result)
    return state, results


def _same_episodes(a: tuple[CrowdState, list], b: tuple[CrowdState, list]) -> None:
    """Every state field but the model codes and every step result equal bit for bit."""
    (sa, ra), (sb, rb) = a, b
    for f in dataclasses.fields(CrowdState):
        if f.name != "human_model":
            assert torch.equal(getattr(sa, f.name), getattr(sb, f.name)), f.name
    for t, (x, y) in enumerate(zip(ra, rb)):
        for name, u, v in zip(x._fields, x, y):
            assert (u is None and v is None) or torch.equal(u, v), (t, name)


@pytest.mark.parametrize("shares, single", [((0.0, 0.0), "orca"), ((1.0, 0.0), "social_force"),
                                            ((0.0, 1.0), "linear")])
@pytest.mark.parametrize("visible, min_humans", [(False, None), (True, 2)])
def test_the_extreme_shares_step_exactly_as_the_single_models(shares, single, visible, min_humans):
    common = dict(num_humans=6, min_humans=min_humans, robot_visible=visible, sf_substeps=3)
    ids = torch.arange(8)
    mixed = _run(_mixed(social_force_share=shares[0], linear_share=shares[1], **common), ids, 12)
    alone = _run(CrowdConfig(human_model=single, **common), ids, 12)
    _same_episodes(mixed, alone)
    present = mixed[0].human_mask
    assert bool((mixed[0].human_model[present] == HUMAN_MODELS.index(single)).all())
    assert torch.equal(alone[0].human_model, torch.full_like(present, HUMAN_MODELS.index(single), dtype=torch.int8))


@pytest.mark.parametrize("visible", [False, True])
def test_in_a_mixed_crowd_each_human_moves_by_its_own_model_over_the_whole_crowd(visible):
    cfg = _mixed(num_humans=8, min_humans=3, social_force_share=0.4, linear_share=0.3, robot_visible=visible)
    state = initial_states(cfg, episode_keys("train", 2, torch.arange(32)))
    gen = torch.Generator().manual_seed(5)
    state = state.replace(human_velocity=torch.rand(32, 8, 2, generator=gen) - 0.5,
                          robot_position=state.human_position[:, 0] + torch.tensor([0.7, 0.0]),  # among the crowd
                          robot_velocity=torch.tensor([[0.2, 0.7]]).repeat(32, 1))
    velocities, infeasible = human_velocities(cfg, state)
    single = {m: CrowdConfig(**{**dataclasses.asdict(cfg), "human_model": m, "social_force_share": 0.0,
                                "linear_share": 0.0}) for m in HUMAN_MODELS}
    orca_v, orca_inf = orca_humans(single["orca"], state)
    answers = {ORCA: orca_v, SOCIAL_FORCE: social_force_humans(single["social_force"], state),
               LINEAR: linear_humans(single["linear"], state)}
    present, model = state.human_mask, state.human_model
    for code, answer in answers.items():
        mine = present & (model == code)
        assert int(mine.sum()) >= 10, HUMAN_MODELS[code]  # every model has humans here
        assert torch.equal(velocities[mine], answer[mine]), HUMAN_MODELS[code]
        # ... and the models differ on these humans: the selection matters
        others = [a for c, a in answers.items() if c != code]
        assert all(not torch.allclose(answer[mine], o[mine]) for o in others), HUMAN_MODELS[code]
    assert torch.equal(velocities[~present], state.human_velocity[~present])
    assert torch.equal(infeasible, orca_inf & (model == ORCA))
    # the robot is seen by the ORCA and social-force humans only when visible: as the single models see it
    blind, _ = human_velocities(dataclasses.replace(cfg, robot_visible=not visible), state)
    lin = present & (model == LINEAR)
    assert torch.equal(blind[lin], velocities[lin]) and not torch.equal(blind[present & ~lin], velocities[present & ~lin])


def _round(x: float) -> int:
    return math.floor(x + 0.5)


@pytest.mark.parametrize("shares, n, counts", [
    ((0.5, 0.5), 3, (2, 1, 0)),  # sf round(1.5) = 2, sf + linear round(3.0) = 3
    ((0.25, 0.25), 2, (1, 0, 1)),  # round(0.5) = 1, round(1.0) = 1: no linear human
    ((0.3, 0.3), 10, (3, 3, 4)),
    ((0.3, 0.3), 5, (2, 1, 2)),  # round(1.5) = 2, round(3.0) = 3
    ((0.0, 0.35), 1, (0, 0, 1)),
    ((1 / 3, 1 / 3), 7, (2, 3, 2)),  # round(2.33) = 2, round(4.67) = 5
    ((0.7, 0.3), 4, (3, 1, 0)),
])
def test_the_counts_follow_the_rounding_rule(shares, n, counts):
    cfg = _mixed(num_humans=max(n, 1), social_force_share=shares[0], linear_share=shares[1])
    sf, lin = cfg.model_counts(torch.tensor([n]))
    assert (int(sf), int(lin), n - int(sf) - int(lin)) == counts


@pytest.mark.parametrize("scenario", ["circle", "square", "corridor"])
def test_each_episode_has_its_counts_among_its_present_humans(scenario):
    sf_share = 0.0 if scenario == "corridor" else 0.35
    cfg = _mixed(scenario=scenario, num_humans=9, min_humans=1, social_force_share=sf_share, linear_share=0.4)
    state = initial_states(cfg, episode_keys("val", 1, torch.arange(200)))
    sizes = state.human_mask.sum(-1)
    assert len(set(sizes.tolist())) == 9  # every crowd size 1..9 drawn
    for b in range(200):
        n, row, present = int(sizes[b]), state.human_model[b], state.human_mask[b]
        want_sf = _round(sf_share * n)
        want_lin = _round((sf_share + 0.4) * n) - want_sf
        got = [int((row[present] == c).sum()) for c in (SOCIAL_FORCE, LINEAR, ORCA)]
        assert got == [want_sf, want_lin, n - want_sf - want_lin], (b, n)
        assert bool((row[~present] == ORCA).all())  # absent humans: marked ORCA, take no part
    assert state.human_model.dtype == torch.int8


def test_the_assignment_is_a_pure_function_of_the_episode():
    cfg = _mixed(num_humans=10, min_humans=4, social_force_share=0.3, linear_share=0.3)
    ids = torch.arange(64)
    whole = initial_states(cfg, episode_keys("train", 3, ids)).human_model
    again = initial_states(cfg, episode_keys("train", 3, ids)).human_model
    assert torch.equal(whole, again)
    # whatever the batch it is drawn in, or its order
    perm = torch.randperm(64, generator=torch.Generator().manual_seed(0))
    assert torch.equal(initial_states(cfg, episode_keys("train", 3, ids[perm])).human_model, whole[perm])
    assert torch.equal(initial_states(cfg, episode_keys("train", 3, ids[17:18])).human_model, whole[17:18])
    # episodes differ, and so do the streams and the seeds for the same episode ids
    assert len({tuple(r.tolist()) for r in whole}) > 40
    for split, seed in (("test", 3), ("val", 3), ("train", 4)):
        other = initial_states(cfg, episode_keys(split, seed, ids)).human_model
        assert not torch.equal(other, whole), (split, seed)
    # a crowd of variable size: the same humans' models as in a fixed crowd of the size the episode drew
    state = initial_states(cfg, episode_keys("train", 3, ids))
    sizes = state.human_mask.sum(-1)
    for n in (4, 7, 10):
        fixed = _mixed(num_humans=n, social_force_share=0.3, linear_share=0.3)
        rows = (sizes == n).nonzero().squeeze(-1)
        assert rows.numel()
        assert torch.equal(initial_states(fixed, state.episode_key[rows]).human_model, whole[rows, :n])


def test_a_mixed_crowd_changes_no_other_draw_of_the_episode():
    """The positions, goals, crowd sizes and later goals of a mixed crowd are those of the same episodes with
    any single model (the models' draws live under their own tag); a single-model config draws nothing."""
    common = dict(scenario="square", num_humans=7, min_humans=3)
    keys = episode_keys("test", 0, torch.arange(16))
    mixed = initial_states(_mixed(social_force_share=0.5, linear_share=0.25, **common), keys)
    plain = initial_states(CrowdConfig(**common), keys)
    for f in dataclasses.fields(CrowdState):
        if f.name != "human_model":
            assert torch.equal(getattr(mixed, f.name), getattr(plain, f.name)), f.name
    codes = torch.zeros(16, 7, dtype=torch.int8)
    assert torch.equal(plain.human_model, codes)
    assert torch.equal(assign_human_models(CrowdConfig(human_model="linear", **common), keys, plain.human_mask),
                       codes + LINEAR)


def test_a_mixed_crowd_steps_reproducibly_and_keeps_its_models():
    cfg = _mixed(num_humans=6, social_force_share=0.34, linear_share=0.33, robot_visible=True, sf_substeps=2)
    (a, ra), (b, rb) = _run(cfg, torch.arange(6), 30), _run(cfg, torch.arange(6), 30)
    assert torch.equal(a.human_position, b.human_position) and torch.isfinite(a.human_position).all()
    assert all(torch.equal(x.reward, y.reward) and torch.equal(x.event, y.event) for x, y in zip(ra, rb))
    assert torch.equal(a.human_model, initial_states(cfg, episode_keys("test", 7, torch.arange(6))).human_model)
    orca, _ = _run(CrowdConfig(num_humans=6, robot_visible=True), torch.arange(6), 30)
    assert not torch.allclose(orca.human_position, a.human_position)


def test_a_hand_built_state_without_models_is_refused_by_a_mixed_step():
    cfg = _mixed(num_humans=4, linear_share=0.5)
    state = initial_states(cfg, episode_keys("test", 0, torch.arange(2))).replace(human_model=None)
    with pytest.raises(ValueError, match="human_model"):
        human_velocities(cfg, state)
    human_velocities(CrowdConfig(num_humans=4), state)  # a single model does not read it


@pytest.mark.parametrize("kwargs, key", [
    ({"human_model": "mix"}, "human_model"),
    ({"human_model": "mixed", "social_force_share": -0.1}, "social_force_share"),
    ({"human_model": "mixed", "linear_share": 1.5}, "linear_share"),
    ({"human_model": "mixed", "linear_share": math.nan}, "linear_share"),
    ({"human_model": "mixed", "social_force_share": math.inf}, "social_force_share"),
    ({"human_model": "mixed", "social_force_share": True}, "social_force_share"),
    ({"human_model": "mixed", "linear_share": "0.3"}, "linear_share"),
    ({"human_model": "mixed", "social_force_share": 0.7, "linear_share": 0.4}, "social_force_share \\+ linear_share"),
    ({"social_force_share": 0.2}, "social_force_share"),  # shares with a single model
    ({"human_model": "linear", "linear_share": 1.0}, "linear_share"),
    ({"human_model": "mixed", "social_force_share": 0.2, "scenario": "doorway"}, "social_force_share"),
])
def test_bad_shares_are_refused_naming_the_key(kwargs, key):
    with pytest.raises(ValueError, match=rf"^{key}"):
        CrowdConfig(**kwargs)


def test_good_shares_are_taken():
    CrowdConfig(human_model="mixed", social_force_share=0.7, linear_share=0.3)  # sum exactly 1: no ORCA human
    CrowdConfig(human_model="mixed", social_force_share=0.1, linear_share=0.9)  # 0.1 + 0.9 in floats
    CrowdConfig(human_model="mixed", scenario="room", linear_share=0.5)  # linear and ORCA among obstacles
    CrowdConfig(human_model="mixed", social_force_share=np.float64(0.5), linear_share=0)


def test_humans_react_to_the_robot_when_some_episode_has_orca_or_social_force_humans():
    assert _mixed(robot_visible=True, social_force_share=0.2).humans_react_to_robot
    assert _mixed(robot_visible=True, linear_share=0.5).humans_react_to_robot
    assert _mixed(robot_visible=True, social_force_share=0.5, linear_share=0.5).humans_react_to_robot
    assert not _mixed(linear_share=0.5).humans_react_to_robot  # blind
    assert not _mixed(robot_visible=True, linear_share=1.0).humans_react_to_robot
    # 0.9 of 1..3 humans rounds to all of them: no episode has a human that sees the robot
    assert not _mixed(robot_visible=True, num_humans=3, min_humans=1, linear_share=0.9).humans_react_to_robot
    # ... but 0.9 of 10 leaves one ORCA human
    assert _mixed(robot_visible=True, num_humans=10, min_humans=1, linear_share=0.9).humans_react_to_robot
    assert _mixed(num_humans=10, min_humans=1, linear_share=0.9).human_models_present == ("orca", "linear")


def test_the_run_config_takes_the_shares_and_the_default_fingerprint_is_unchanged():
    from crowdrl.training import validate
    from crowdrl.training.checkpoint import config_fingerprint
    from crowdrl.training.config import ConfigError, to_dict
    from crowdrl.training.config import crowd_config

    # the learner the keys were recorded with (visible robots need it: no counterfactual)
    plain = {"train": {"counterfactual": {"mode": "off"}, "target_tau": 1.0}}
    now = to_dict(validate(plain, resources=False))
    before = {**now, "env": {k: v for k, v in now["env"].items() if k not in ("social_force_share", "linear_share")}}
    assert config_fingerprint(now) == config_fingerprint(before)
    mixed = {"human_model": "mixed", "social_force_share": 0.3, "linear_share": 0.2}
    runs = [to_dict(validate({"env": e, **plain}, resources=False)) for e in (
        mixed, {**mixed, "linear_share": 0.25}, {**mixed, "robot_visible": True}, {**mixed, "sf_tau": 0.3},
        {"human_model": "mixed"}, {"human_model": "mixed", "linear_share": 0.2})]
    prints = [config_fingerprint(r) for r in runs]
    assert len(set(prints) | {config_fingerprint(now)}) == 7
    # the social-force parameters count only where social-force humans may be present
    no_sf = {"human_model": "mixed", "linear_share": 0.2}
    assert config_fingerprint(to_dict(validate({"env": {**no_sf, "sf_tau": 0.3}, **plain}, resources=False))) == prints[5]
    cfg = crowd_config(validate({"env": {**mixed, "min_humans": 4}}, resources=False))
    assert (cfg.human_model, cfg.social_force_share, cfg.linear_share, cfg.min_humans) == ("mixed", 0.3, 0.2, 4)
    for env, key in (({"human_model": "mixed", "linear_share": 1.2}, "env.linear_share"),
                     ({"social_force_share": 0.2}, "env.social_force_share"),
                     ({**mixed, "linear_share": 0.8}, "env.social_force_share \\+ linear_share"),
                     ({"scenario": "corridor", **mixed}, "env.social_force_share")):
        with pytest.raises(ConfigError, match=rf"^{key}"):
            validate({"env": env}, resources=False)


def test_counterfactual_experience_is_refused_when_mixed_humans_see_the_robot():
    from crowdrl.training import validate
    from crowdrl.training.config import ConfigError

    cf = {"train": {"counterfactual": {"mode": "merged"}}}
    with pytest.raises(ConfigError, match="^train.counterfactual.mode.*orca and social_force humans"):
        validate({"env": {"human_model": "mixed", "social_force_share": 0.5, "robot_visible": True}, **cf},
                 resources=False)
    validate({"env": {"human_model": "mixed", "linear_share": 1.0, "robot_visible": True}, **cf}, resources=False)
    validate({"env": {"human_model": "mixed", "social_force_share": 0.5}, **cf}, resources=False)


def test_an_env_snapshot_keeps_each_humans_model():
    from crowdrl.envs import CrowdNavEnv

    cfg = _mixed(scenario="square", num_humans=5, min_humans=2, social_force_share=0.4, linear_share=0.4)
    gen = torch.Generator().manual_seed(3)
    actions = torch.randint(0, 81, (40, 4), generator=gen)
    env = CrowdNavEnv("square", num_envs=4, num_humans=5, seed=1, config=cfg)
    td = env.reset()
    for t in range(15):
        _, td = env.step_and_maybe_reset(td.set("action", actions[t]))
    saved = env.snapshot()
    assert torch.equal(saved["tensors"]["state.human_model"], env.state.human_model)
    twin = CrowdNavEnv("square", num_envs=4, num_humans=5, seed=1, config=cfg)
    twin.restore(saved)
    td2 = twin.reset()
    assert torch.equal(twin.state.human_model, env.state.human_model)
    for t in range(15, 40):  # auto-resets included: a reset sub-env takes its new episode's models
        out, td = env.step_and_maybe_reset(td.set("action", actions[t]))
        out2, td2 = twin.step_and_maybe_reset(td2.set("action", actions[t]))
        assert (out == out2).all(), t
        assert torch.equal(twin.state.human_model, env.state.human_model)
    ids = td["episode_id"].flatten()
    assert int(ids.max()) > 3  # some sub-env was reset
    assert torch.equal(env.state.human_model, initial_states(cfg, episode_keys("train", 1, ids)).human_model)
    # a snapshot written before the field: refused for a mixed crowd, every human the model of a single one
    old = {**saved, "tensors": {k: v for k, v in saved["tensors"].items() if k != "state.human_model"}}
    with pytest.raises(ValueError, match="state.human_model"):
        CrowdNavEnv("square", num_envs=4, num_humans=5, seed=1, config=cfg).restore(old)
    linear = CrowdConfig(scenario="square", num_humans=5, min_humans=2, human_model="linear")
    plain = CrowdNavEnv("square", num_envs=4, num_humans=5, seed=1, config=linear)
    plain.restore(old)
    plain.reset()
    assert torch.equal(plain.state.human_model, torch.full((4, 5), LINEAR, dtype=torch.int8))


def test_the_gymnasium_ids_take_the_shares():
    import gymnasium as gym

    import crowdrl  # noqa: F401  (registers the ids)

    env = gym.make("crowdrl/CircleCrossing-v0", human_model="mixed", social_force_share=0.3, linear_share=0.3).unwrapped
    assert (env.config.human_model, env.config.social_force_share, env.config.linear_share) == ("mixed", 0.3, 0.3)
    env.reset(seed=0)
    assert sorted(env._state.human_model[0].tolist()) == [0] * 4 + [1] * 3 + [2] * 3
    for _ in range(3):
        obs, _, terminated, truncated, _ = env.step(40)
        if terminated or truncated:
            break
    assert np.isfinite(obs["humans"]).all()
    with pytest.raises(ValueError, match="^social_force_share"):
        gym.make("crowdrl/Doorway-v0", human_model="mixed", social_force_share=0.3)


def test_evaluate_spec_takes_a_mixed_crowd_and_refuses_shares_without_it():
    from crowdrl.agents import evaluate_spec

    record, _ = evaluate_spec(policy="orca", episodes=2, batch=2, human_model="mixed", social_force_share=0.3,
                              linear_share=0.3)
    assert {k: record[k] for k in ("human_model", "social_force_share", "linear_share", "robot_visible")} == {
        "human_model": "mixed", "social_force_share": 0.3, "linear_share": 0.3, "robot_visible": False}
    plain, _ = evaluate_spec(policy="orca", episodes=2, batch=2, human_model="linear")
    assert plain["human_model"] == "linear" and "linear_share" not in plain
    with pytest.raises(ValueError, match="^eval.linear_share"):
        evaluate_spec(policy="orca", episodes=2, batch=2, linear_share=0.5)  # the baseline's humans: orca
    agent = Path(__file__).resolve().parents[1] / "pretrained" / "sgd3qn-planning-re3-demo-s0"
    with pytest.raises(ValueError, match="^eval.social_force_share"):  # the checkpoint's humans: orca
        evaluate_spec(checkpoint=agent, episodes=2, batch=2, social_force_share=0.5)
    with pytest.raises(ValueError, match="^eval.social_force_share"):
        evaluate_spec(checkpoint=agent, episodes=2, batch=2, scenario="room", human_model="mixed",
                      social_force_share=0.5)
