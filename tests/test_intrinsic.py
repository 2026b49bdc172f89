"""Intrinsic-reward transform, ICM and RE3 (``crowdrl.exploration``)."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.envs import Compose

from crowdrl.exploration import ICM, RE3, RND, IntrinsicBonus, IntrinsicRewardTransform, RunningMeanStd

OBS_DIM, NUM_ACTIONS = 4, 3


def mlp_encoder(seed: int = 0) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(OBS_DIM, 32), nn.ReLU())


def transitions(n: int = 64, seed: int = 0, action: str = "index") -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, NUM_ACTIONS, (n,), generator=g)
    act = {"index": idx, "index1": idx.unsqueeze(-1),
           "onehot": torch.nn.functional.one_hot(idx, NUM_ACTIONS).bool()}[action]
    return TensorDict({
        "observation": torch.randn(n, OBS_DIM, generator=g),
        "action": act,
        "next": {"observation": torch.randn(n, OBS_DIM, generator=g),
                 "reward": torch.randn(n, 1, generator=g),
                 "done": torch.zeros(n, 1, dtype=torch.bool)},
    }, batch_size=[n])


def make_icm(**kw) -> ICM:
    return ICM(mlp_encoder(), NUM_ACTIONS, feature_dim=32, seed=1, **kw)


def make_re3(**kw) -> RE3:
    return RE3(mlp_encoder(), feature_dim=32, seed=1, **kw)


def make_rnd() -> RND:
    return RND(mlp_encoder(0), mlp_encoder(1), feature_dim=32, seed=1)


# ----------------------------------------------------------------------------- RE3
def test_re3_ranks_an_outlier_above_clustered_states():
    n = 32
    td = transitions(n)
    nxt = 0.01 * torch.randn(n, OBS_DIM)
    nxt[7] = torch.tensor([5.0, -5.0, 5.0, -5.0])  # far from the cluster
    td["next", "observation"] = nxt
    r = make_re3().bonus(td)
    assert r.shape == (n,) and torch.isfinite(r).all() and (r > 0).all()
    assert r.argmax() == 7
    assert r[7] > 3 * r[torch.arange(n) != 7].max()


def test_re3_embeds_s_or_s_next():
    td = transitions(16)
    td["observation"] = td["next", "observation"] * 3.0  # different states
    a = make_re3(embed_next=True).knn_distance(td)
    b = make_re3(embed_next=False).knn_distance(td)
    td2 = td.clone()
    td2["observation"] = td["next", "observation"]
    assert torch.equal(make_re3(embed_next=False).knn_distance(td2), a)
    assert not torch.allclose(a, b)


def test_re3_knn_distance_is_the_kth_neighbour_distance():
    # 1-d points on a line; the random encoder is replaced by the identity to check the rank logic
    re3 = RE3(nn.Identity(), feature_dim=1, k=2, seed=0)
    re3.head = nn.Identity()
    x = torch.tensor([[0.0], [1.0], [3.0], [7.0]])
    td = TensorDict({"observation": x, "next": {"observation": x}}, batch_size=[4])
    # neighbours of 0: 1, 3, 7 -> 2nd = 3; of 1: 1, 2, 6 -> 2; of 3: 2, 3, 4 -> 3; of 7: 4, 6, 7 -> 6
    assert torch.equal(re3.knn_distance(td), torch.tensor([3.0, 2.0, 3.0, 6.0]))


def test_re3_distances_match_the_exact_pairwise_distances_and_duplicates_are_at_zero():
    # a counterfactual-sized batch (500 rows of 128-d embeddings) sampled with replacement, and a near pair
    from crowdrl.exploration.re3 import pairwise_distances

    g = torch.Generator().manual_seed(0)
    for scale in (0.01, 1.0, 100.0):
        e = scale * torch.randn(500, 128, generator=g)
        e = e[torch.randint(0, 500, (500,), generator=g)]
        e[3] = e[4] + 1e-3 * scale
        same = (e.unsqueeze(1) == e.unsqueeze(0)).all(-1)
        assert int(same.sum()) > 500  # duplicates beyond the diagonal
        exact = torch.cdist(e, e, compute_mode="donot_use_mm_for_euclid_dist")
        d = pairwise_distances(e)
        assert torch.equal(d[same], torch.zeros(int(same.sum())))
        torch.testing.assert_close(d, exact, rtol=2e-6, atol=0.0)
    # a degenerate batch, every row the same state: all at 0 (the pairs are then not recomputed one by one)
    assert torch.equal(pairwise_distances(torch.ones(300, 128)), torch.zeros(300, 300))
    # the k-th neighbour is kthvalue's on the same distances (the k smallest of each row, the last)
    re3 = make_re3(k=3)
    td = transitions(64)
    e = re3.embed(re3.obs(td, next_=True))
    ref = torch.cdist(e, e, compute_mode="donot_use_mm_for_euclid_dist").fill_diagonal_(float("inf"))
    torch.testing.assert_close(re3.knn_distance(td), ref.kthvalue(3, dim=1).values, rtol=2e-6, atol=0.0)


def test_re3_running_std_normalises_and_encoder_stays_frozen():
    re3 = make_re3()
    assert not any(p.requires_grad for p in re3.parameters())
    before = copy.deepcopy(re3.state_dict())
    td = transitions(40)
    d = re3.knn_distance(td)
    r = re3.bonus(td)
    std = d.double().std(unbiased=False)
    torch.testing.assert_close(r, torch.log1p(d / std.float()))
    assert int(re3.dist_stats.count) == 40
    re3.train()
    assert not re3.encoder.training and not re3.head.training
    assert re3.update(td) == {"re3_dist_std": pytest.approx(float(std))}
    for key, value in re3.state_dict().items():
        if not key.startswith("dist_stats"):
            assert torch.equal(value, before[key]), key


def test_running_std_matches_pooled_statistics():
    rs = RunningMeanStd()
    chunks = [torch.randn(n) * 3 + 1 for n in (5, 17, 1, 40)]
    for c in chunks:
        rs.update(c)
    allx = torch.cat(chunks).double()
    torch.testing.assert_close(rs.std, allx.std(unbiased=False))
    torch.testing.assert_close(rs.mean, allx.mean())


def test_re3_bad_k():
    with pytest.raises(ValueError, match="k"):
        make_re3(k=0)
    with pytest.raises(ValueError, match="k"):
        make_re3(k=-2)
    with pytest.raises(ValueError, match=r"k = 3, batch of 3"):
        make_re3(k=3).bonus(transitions(3))
    make_re3(k=3).bonus(transitions(4))  # k = batch - 1 is the largest allowed


# ----------------------------------------------------------------------------- ICM
def test_icm_shapes_match_the_spec():
    icm = make_icm()
    assert [m.weight.shape[::-1] for m in icm.head if isinstance(m, nn.Linear)] == [(32, 256), (256, 128)]
    assert [m.weight.shape[::-1] for m in icm.inverse_model if isinstance(m, nn.Linear)] == \
        [(256, 256), (256, 128), (128, NUM_ACTIONS)]
    assert [m.weight.shape[::-1] for m in icm.forward_model if isinstance(m, nn.Linear)] == \
        [(128 + NUM_ACTIONS, 256), (256, 128), (128, 128)]
    assert icm.optimizer.param_groups[0]["lr"] == 1e-4


def test_icm_forward_error_falls_on_a_repeated_transition():
    icm = ICM(mlp_encoder(), NUM_ACTIONS, feature_dim=32, seed=1, lr=1e-3)
    td = transitions(16)
    first = icm.bonus(td).mean()
    stats = [icm.update(td) for _ in range(150)]
    last = icm.bonus(td).mean()
    assert last < 0.2 * first
    assert stats[-1]["icm_inverse_loss"] < stats[0]["icm_inverse_loss"]
    assert set(stats[0]) == {"icm_loss", "icm_forward_loss", "icm_inverse_loss", "icm_inverse_accuracy",
                             "icm_feature_norm"}


@pytest.mark.parametrize("detach_target", [True, False])
def test_icm_fused_bonus_and_update_equals_bonus_then_update(detach_target):
    a = make_icm(detach_target=detach_target)
    b = copy.deepcopy(a)
    td = transitions(32)
    r_a, s_a = a.bonus_and_update(td)
    r_b = b.bonus(td)
    s_b = b.update(td)
    assert torch.equal(r_a, r_b)
    assert s_a == s_b
    for (name, p), q in zip(a.named_parameters(), b.parameters()):
        assert torch.equal(p, q), name


def test_icm_accepts_index_and_one_hot_actions():
    icm = make_icm()
    r = [icm.bonus(transitions(8, action=kind)) for kind in ("index", "index1", "onehot")]
    assert torch.equal(r[0], r[1]) and torch.equal(r[0], r[2])
    td = transitions(8)
    td["action"] = torch.zeros(8, 5)
    with pytest.raises(ValueError, match="one-hot"):
        icm.bonus(td)


def test_icm_target_gradient_choice():
    td = transitions(8)
    for detach, expect_grad in ((True, False), (False, True)):
        icm = make_icm(detach_target=detach)
        icm.inverse_weight = 0.0  # forward loss only
        errors, logits, idx = icm._errors(td)
        phi_next = icm.features(icm.obs(td, next_=True))
        target = phi_next.detach() if detach else phi_next
        pred = icm.forward_model(torch.cat((icm.features(icm.obs(td)),
                                            nn.functional.one_hot(idx, NUM_ACTIONS).float()), -1))
        (g,) = torch.autograd.grad((pred - target).pow(2).mean(), phi_next, allow_unused=True)
        assert (g is not None) == expect_grad


def test_seeded_construction_leaves_global_rng_alone():
    enc = mlp_encoder()
    state = torch.get_rng_state()
    a = ICM(enc, NUM_ACTIONS, feature_dim=32, seed=5)
    b = RE3(enc, feature_dim=32, seed=5)
    assert torch.equal(torch.get_rng_state(), state)
    assert torch.equal(a.head[0].weight, b.head[0].weight)  # same seed, same first draw
    with pytest.raises(ValueError, match="feature_dim"):
        ICM(nn.Linear(OBS_DIM, 8), NUM_ACTIONS)
    with pytest.raises(ValueError, match="num_actions"):
        ICM(enc, 1, feature_dim=32)


def test_crowd_encoder_with_two_observation_keys():
    from crowdrl.models import make_encoder

    keys = ("robot_rc", "humans_rc")
    B, N = 12, 10
    g = torch.Generator().manual_seed(3)

    def crowd_batch() -> TensorDict:
        return TensorDict({
            "robot_rc": torch.randn(B, 9, generator=g), "humans_rc": torch.randn(B, N, 5, generator=g),
            "action": torch.randint(0, 81, (B, 1), generator=g),
            "next": {"robot_rc": torch.randn(B, 9, generator=g), "humans_rc": torch.randn(B, N, 5, generator=g),
                     "reward": torch.randn(B, 1, generator=g)},
        }, batch_size=[B])

    icm = ICM(make_encoder("sgd3qn"), 81, in_keys=keys, seed=0)
    re3 = RE3(make_encoder("sgd3qn"), in_keys=keys, seed=0)
    td = crowd_batch()
    for bonus in (icm, re3):
        out = IntrinsicRewardTransform(bonus, beta=0.01)(td.clone())
        r_in = out["next", "reward_int"]
        assert r_in.shape == (B, 1) and torch.isfinite(r_in).all() and (r_in > 0).all()
    stats = [icm.update(td) for _ in range(20)]
    assert all(torch.isfinite(torch.tensor(list(s.values()))).all() for s in stats)
    assert stats[-1]["icm_inverse_loss"] < stats[0]["icm_inverse_loss"]


# ----------------------------------------------------------------------------- transform
@pytest.mark.parametrize("bonus_factory", [make_icm, make_re3])
def test_reward_is_r_ext_plus_beta_r_int(bonus_factory):
    td = transitions(32)
    t = IntrinsicRewardTransform(bonus_factory(), beta=0.25)
    out = t(td.clone())
    r_ext, r_in, r = out["next", "reward_ext"], out["next", "reward_int"], out["next", "reward"]
    assert r_ext.shape == r_in.shape == r.shape == (32, 1)
    assert torch.equal(r_ext, td["next", "reward"])
    assert torch.equal(r, r_ext + 0.25 * r_in)
    assert (r_in > 0).all() and torch.isfinite(r_in).all()
    assert t.last_stats["beta"] == 0.25 and "reward_int_mean" in t.last_stats


def test_rewards_are_computed_before_the_update():
    icm = make_icm()
    frozen = copy.deepcopy(icm)
    td = transitions(32)
    out = IntrinsicRewardTransform(icm, beta=1.0)(td.clone())
    assert torch.equal(out["next", "reward_int"].squeeze(-1), frozen.bonus(td))
    assert not torch.equal(icm.head[0].weight, frozen.head[0].weight)  # and the update happened
    no_update = IntrinsicRewardTransform(frozen, beta=1.0, update_bonus=False)
    w = frozen.head[0].weight.clone()
    no_update(td.clone())
    assert torch.equal(frozen.head[0].weight, w)


@pytest.mark.parametrize("bonus_factory", [make_icm, make_re3])
def test_beta_zero_is_the_extrinsic_reward_bit_for_bit_and_draws_no_rng(bonus_factory):
    td = transitions(32)
    td["next", "reward"][0] = -0.0  # -0.0 + 0 * r_in would be +0.0
    td["next", "reward"][1] = 1e-30
    t = IntrinsicRewardTransform(bonus_factory(), beta=0.0)
    state = torch.get_rng_state()
    out = t(td.clone())
    assert torch.equal(torch.get_rng_state(), state)
    r, r_ext = out["next", "reward"], td["next", "reward"]
    assert torch.equal(r.view(torch.int32), r_ext.view(torch.int32))
    assert torch.signbit(r[0]).item()


@pytest.mark.parametrize("sampler", [None, SamplerWithoutReplacement])
def test_stored_rewards_never_change(sampler):
    kw = {} if sampler is None else {"sampler": sampler()}
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(200), batch_size=24,
                                transform=IntrinsicRewardTransform(make_icm(), beta=2.0), **kw)
    data = transitions(100)
    rb.extend(data)
    before = rb.storage[:].clone()
    assert torch.equal(before["next", "reward"], data["next", "reward"])  # inv is the identity
    assert "reward_int" not in before["next"].keys()
    for _ in range(6):
        sample = rb.sample()
        assert not torch.equal(sample["next", "reward"], sample["next", "reward_ext"])
        assert torch.equal(sample["next", "reward_ext"], data["next", "reward"][sample["index"]])
    after = rb.storage[:]
    assert (after == before).all()
    assert set(after.keys(True, True)) == set(before.keys(True, True))


def test_transform_in_a_compose_after_another_transform():
    from crowdrl.training.nstep import NStepReturn

    B, T = 4, 8
    g = torch.Generator().manual_seed(0)
    batch = TensorDict({
        "observation": torch.randn(B, T, OBS_DIM, generator=g),
        "action": torch.randint(0, NUM_ACTIONS, (B, T), generator=g),
        "next": {"observation": torch.randn(B, T, OBS_DIM, generator=g),
                 "observation_1step": torch.randn(B, T, OBS_DIM, generator=g),
                 "reward": torch.randn(B, T, 1, generator=g),
                 "done": torch.zeros(B, T, 1, dtype=torch.bool),
                 "terminated": torch.zeros(B, T, 1, dtype=torch.bool)},
    }, batch_size=[B, T])
    icm = make_icm()
    t = IntrinsicRewardTransform(icm, beta=0.5, next_obs_keys=[("next", "observation_1step")], update_bonus=False)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=16,
                                transform=Compose(NStepReturn(3, 0.9, ["observation"]), t))
    rb.extend(batch)
    s = rb.sample()
    # the bonus saw the one-step successor, not the n-step ("next", "observation")
    probe = s.select("observation", "action")
    probe["next", "observation"] = s["next", "observation_1step"]
    assert torch.equal(s["next", "reward_int"].squeeze(-1), icm.bonus(probe))
    assert torch.equal(s["next", "reward"], s["next", "reward_ext"] + 0.5 * s["next", "reward_int"])


def test_two_batch_dims_keep_their_shape():
    td = transitions(24).reshape(4, 6)
    for bonus in (make_icm(), make_re3()):
        out = IntrinsicRewardTransform(bonus, beta=0.1)(td.clone())
        assert out["next", "reward_int"].shape == (4, 6, 1)
    flat = make_re3().bonus(transitions(24))
    assert torch.equal(make_re3().bonus(td), flat.reshape(4, 6))


def test_callable_beta_is_read_on_every_batch():
    calls = []

    def schedule() -> float:
        calls.append(1)
        return 0.5 / len(calls)

    t = IntrinsicRewardTransform(make_re3(), beta=schedule)
    td = transitions(16)
    for expected in (0.5, 0.25):
        out = t(td.clone())
        assert t.last_stats["beta"] == expected
        assert torch.equal(out["next", "reward"], out["next", "reward_ext"] + expected * out["next", "reward_int"])
    assert len(calls) == 2
    with pytest.raises(ValueError, match="beta"):
        IntrinsicRewardTransform(make_re3(), beta=lambda: -1.0)(td.clone())


def test_bad_input_errors():
    with pytest.raises(ValueError, match="beta"):
        IntrinsicRewardTransform(make_re3(), beta=-0.1)
    with pytest.raises(TypeError, match="IntrinsicBonus"):
        IntrinsicRewardTransform(nn.Linear(2, 2))
    with pytest.raises(ValueError, match="one to one"):
        IntrinsicRewardTransform(make_re3(), obs_keys=["a", "b"])
    td = transitions(16)
    del td["next", "observation"]
    with pytest.raises(KeyError, match=r"\('next', 'observation'\).*keys present.*'observation'"):
        IntrinsicRewardTransform(make_icm())(td)
    td = transitions(16).exclude("action")
    with pytest.raises(KeyError, match="'action'"):
        IntrinsicRewardTransform(make_icm())(td)
    t = IntrinsicRewardTransform(make_re3(), obs_keys=["pixels"])
    with pytest.raises(KeyError, match="'pixels'.*keys present"):
        t(transitions(16))


def test_custom_bonus_and_reward_keys():
    class Constant(IntrinsicBonus):
        def bonus(self, td):
            return torch.full(td.batch_size, 2.0)

    td = transitions(8)
    td["next", "r"] = td["next"].pop("reward")
    t = IntrinsicRewardTransform(Constant(["observation"]), beta=0.5, reward_key=("next", "r"),
                                 reward_ext_key="r_ext", reward_int_key="r_int")
    out = t(td.clone())
    assert torch.equal(out["next", "r"], td["next", "r"] + 1.0)
    assert torch.equal(out["r_ext"], td["next", "r"]) and (out["r_int"] == 2.0).all()


# ----------------------------------------------------------------------------- grouped batches (counterfactual)
def grouped_transitions(n: int = 12, g: int = 5, seed: int = 3) -> TensorDict:
    """``g`` transitions from each of ``n`` states: ``s`` equal along dim 1, each successor and action its own."""
    flat = transitions(n * g, seed=seed)
    td = flat.reshape(n, g)
    td["observation"] = td["observation"][:, :1].expand(n, g, OBS_DIM).clone()
    td["steps_to_next_obs"] = torch.ones(n, g, 1, dtype=torch.int64)
    td["next", "terminated"] = torch.rand(n, g, 1, generator=torch.Generator().manual_seed(seed)) < 0.2
    return td


@pytest.mark.parametrize("bonus_factory", [make_icm, make_re3, make_rnd], ids=["icm", "re3", "rnd"])
def test_a_grouped_batch_gets_the_bonus_of_its_transitions_laid_out_flat(bonus_factory):
    """``add_bonus(grouped=True)`` on ``[n, g]`` (what counterfactual experience passes) gives the rewards and the
    options' statistics of the same ``n·g`` transitions one per row, every option on."""
    from crowdrl.exploration.normalize import ObservationNormalizer, RewardNormalizer

    def transform():
        return IntrinsicRewardTransform(bonus_factory(), beta=0.3, update_bonus=False, obs_norm=ObservationNormalizer(),
                                        reward_norm=RewardNormalizer(scale="std", center=True, clip=5.0),
                                        terminal_value_gamma=0.9)

    grouped_t, flat_t = transform(), transform()
    for seed in (3, 4):  # the second batch reads statistics the first one moved
        td = grouped_transitions(seed=seed)
        a = grouped_t.add_bonus(td.clone(), learn=False, record=False, grouped=True)
        b = flat_t.add_bonus(td.reshape(-1).clone(), learn=False, record=False)
        for key in (("next", "reward"), ("next", "reward_int")):
            torch.testing.assert_close(a.get(key), b.get(key).reshape(a.get(key).shape), rtol=1e-5, atol=1e-6)
    for (ka, va), (kb, vb) in zip(grouped_t.state_dict().items(), flat_t.state_dict().items()):
        assert ka == kb
        torch.testing.assert_close(va, vb, rtol=1e-5, atol=1e-6)


def test_icm_reads_each_state_of_a_grouped_batch_once():
    icm = make_icm()
    rows = []
    features = icm.features
    icm.features = lambda obs: rows.append(obs[0].shape[0]) or features(obs)
    td = grouped_transitions(n=12, g=5)
    grouped = icm.grouped_bonus(td)
    assert rows == [12 + 60] and grouped.shape == (12, 5)
    torch.testing.assert_close(grouped, icm.bonus(td.reshape(-1)).reshape(12, 5), rtol=1e-5, atol=1e-7)


def test_a_grouped_bonus_is_refused_with_learning_or_a_flat_batch():
    t = IntrinsicRewardTransform(make_icm(), beta=0.1)
    with pytest.raises(ValueError, match=r"grouped=True.*\[n, g\].*learn=False"):
        t.add_bonus(grouped_transitions(), grouped=True)
    with pytest.raises(ValueError, match=r"grouped=True.*\[n, g\]"):
        t.add_bonus(transitions(8), learn=False, grouped=True)


def test_grouped_bonus_and_pairwise_distances_refuse_other_shapes():
    from crowdrl.exploration.re3 import pairwise_distances

    for bonus in (make_icm(), make_re3()):
        with pytest.raises(ValueError, match=r"grouped_bonus takes a batch shaped \[n, g\].*got batch \(8,\)"):
            bonus.grouped_bonus(transitions(8))
    with pytest.raises(ValueError, match=r"pairwise_distances takes a float tensor shaped \[n, D\]"):
        pairwise_distances(torch.ones(5))
    with pytest.raises(ValueError, match=r"pairwise_distances takes a float tensor shaped \[n, D\]"):
        pairwise_distances(torch.ones(5, 3, dtype=torch.int64))
