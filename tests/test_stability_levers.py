"""The learner's stability levers (``train.target_tau``, ``huber_delta``, ``grad_clip_norm``, ``lr_end``,
``q_layer_norm``):
each off by default with the old fingerprint, each doing what it says, bad values refused naming the key."""

import math

import pytest
import torch

from crowdrl.training import ConfigError, Trainer, validate
from crowdrl.training.checkpoint import config_fingerprint
from crowdrl.training.config import to_dict
from crowdrl.training.loss import D3QNLoss

LEVERS = {"target_tau": 0.01, "huber_delta": 1.0, "grad_clip_norm": 5.0, "lr_end": 1e-4, "q_layer_norm": True}


def test_levers_at_their_defaults_keep_the_fingerprint_and_each_one_set_changes_it():
    # every lever off: the learner the keys were recorded with
    base = validate({"train": {"counterfactual": {"mode": "off"}, "target_tau": 1.0}}, resources=False)
    stored = to_dict(base)
    for key in LEVERS:  # a config recorded before the keys
        stored["train"].pop(key)
    assert config_fingerprint(stored) == config_fingerprint(to_dict(base))
    for key, value in LEVERS.items():
        run = validate({"train": {**to_dict(base)["train"], key: value}}, resources=False)
        assert config_fingerprint(to_dict(run)) != config_fingerprint(to_dict(base)), key


@pytest.mark.parametrize("key,value", [("target_tau", 0.0), ("target_tau", 1.5), ("huber_delta", 0.0),
                                       ("grad_clip_norm", -1.0), ("lr_end", 0.1), ("lr_end", -1e-4)])
def test_bad_lever_values_are_refused_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=f"train.{key}"):
        validate({"train": {key: value}}, resources=False)


@pytest.mark.parametrize("value", [2, 0, "yes", "true"])
def test_a_bool_key_given_anything_but_true_or_false_is_refused_naming_it(value):
    """Issue 52 (D10): OmegaConf makes any integer a bool (``q_layer_norm: 2`` was stored as ``true``); a
    config (the Python API, a resumed run's config.yaml) must give ``true`` or ``false``."""
    with pytest.raises(ConfigError, match=f"train.q_layer_norm: must be true or false, got {value!r}"):
        validate({"train": {"q_layer_norm": value}}, resources=False)
    with pytest.raises(ConfigError, match="logger.render: must be true or false"):
        validate({"logger": {"render": 1}}, resources=False)
    assert validate({"train": {"q_layer_norm": True}}, resources=False).train.q_layer_norm is True


def test_huber_loss_is_squared_error_inside_delta_and_linear_beyond():
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 4)
    loss = D3QNLoss(net, ["x"], gamma=0.9, huber_delta=1.0)
    obs = torch.randn(8, 3)
    q = net(obs).detach()
    action = torch.arange(8).remainder(4).reshape(8, 1)
    q_a = q.gather(-1, action).squeeze(-1)
    y = q_a + torch.tensor([0.1, -0.5, 2.0, -3.0, 0.0, 0.9, -1.1, 4.0])
    from crowdrl.training.loss import D3QNBatch

    b = D3QNBatch((obs,), (obs,), action, torch.zeros(8, 1), torch.zeros(8, 1, dtype=torch.bool),
                  torch.ones(8, 1, dtype=torch.int64))
    value, _ = loss.objective(None, b, y.reshape(8, 1))
    d = (q_a - y).abs()
    expected = torch.where(d <= 1, 0.5 * d ** 2, d - 0.5).mean()
    torch.testing.assert_close(value, expected)


def test_polyak_update_moves_the_target_by_tau():
    net = torch.nn.Linear(2, 2)
    loss = D3QNLoss(net, ["x"], gamma=0.9)
    before = loss.target_net.weight.detach().clone()
    with torch.no_grad():
        net.weight.add_(1.0)
    loss.update_target_polyak(0.25)
    torch.testing.assert_close(loss.target_net.weight, before + 0.25 * (net.weight - before))
    with pytest.raises(ValueError, match="tau"):
        loss.update_target_polyak(0.0)


def _run(tmp_path, **train):
    run = validate({"preset": "smoke", "encoder": {"name": "sarl"}, "env": {"num_humans": 3, "orca_backend": "eager"},
                    "logger": {"name": "csv", "progress_bar": False, "render": False}, "planning": {"enabled": False},
                    "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 128, "warmup_frames": 32,
                              "batch_size": 16, "buffer_size": 1000, "updates_per_frame": 0.25,
                              "target_update_frames": 1000, "val_every_frames": 128, "val_episodes": 2,
                              "checkpoint_every_frames": 128, "test_episodes": 2, "compile_acting": False,
                              "compile_loss": False, **train}}, resources=False)
    return Trainer(run, tmp_path)


def test_polyak_targets_follow_the_online_network_every_update_and_hard_copies_stop(tmp_path):
    trainer = _run(tmp_path / "polyak", target_tau=0.5)
    try:
        trainer.train()
        online = torch.cat([p.detach().flatten() for p in trainer.net.parameters()])
        target = torch.cat([p.detach().flatten() for p in trainer.learner.loss.target_net.parameters()])
        initial = _run(tmp_path / "fresh")  # same seed: the parameters the run started from
        start = torch.cat([p.detach().flatten() for p in initial.net.parameters()])
        initial.close()
        # never hard-copied (target_update_frames is beyond the run), yet the target moved off its start
        assert not torch.equal(target, start) and not torch.equal(target, online)
        assert (target - online).norm() < (start - online).norm()
    finally:
        trainer.close()


def test_clipped_gradients_and_the_decayed_learning_rate(tmp_path):
    trainer = _run(tmp_path / "levers", grad_clip_norm=1e-3, lr_end=1e-4)
    norms = []
    step = trainer.learner.optimizer.step

    def spy(*a, **k):
        norms.append(math.sqrt(sum(float(p.grad.pow(2).sum()) for p in trainer.net.parameters() if p.grad is not None)))
        return step(*a, **k)

    trainer.learner.optimizer.step = spy
    try:
        trainer.train()
    finally:
        trainer.close()
    assert norms and max(norms) <= 1e-3 * (1 + 1e-4)
    lr = trainer.learner.optimizer.param_groups[0]["lr"]
    assert lr == pytest.approx(1e-4 + (1e-3 - 1e-4) * max(0.0, 1 - 128 / 128))  # at total_frames: lr_end


def test_layer_norm_head_normalises_each_hidden_layer_and_off_keeps_the_papers_parameters():
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import make_network

    plain_run, normed_run = validate({}, resources=False), validate({"train": {"q_layer_norm": True}}, resources=False)
    plain = make_network(plain_run, strategy=make_strategy(plain_run.exploration))
    normed = make_network(normed_run, strategy=make_strategy(normed_run.exploration))
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain.modules())
    assert sum(isinstance(m, torch.nn.LayerNorm) for m in normed.head.modules()) == 4  # trunk 2, value 1, advantage 1
    assert list(plain.head.state_dict()) == ["trunk.0.weight", "trunk.0.bias", "trunk.2.weight", "trunk.2.bias",
                                             "value.0.weight", "value.0.bias", "value.2.weight", "value.2.bias",
                                             "advantage.0.weight", "advantage.0.bias", "advantage.2.weight",
                                             "advantage.2.bias"]  # what stored checkpoints hold
    # each hidden activation of the normed trunk has zero mean and unit variance per sample before its ReLU
    z = torch.randn(5, normed.head.embedding_dim)
    pre = normed.head.trunk[:2](z)
    torch.testing.assert_close(pre.mean(-1), torch.zeros(5), atol=1e-5, rtol=0)
    torch.testing.assert_close(pre.var(-1, unbiased=False), torch.ones(5), atol=1e-3, rtol=0)


def test_layer_norm_head_composes_with_noisy_and_dropout_heads():
    from crowdrl.exploration import make_strategy
    from crowdrl.training.variants import make_network

    for exploration in ("noisy", "dropout"):
        run = validate({"train": {"q_layer_norm": True}, "exploration": {"name": exploration}}, resources=False)
        net = make_network(run, strategy=make_strategy(run.exploration))
        assert sum(isinstance(m, torch.nn.LayerNorm) for m in net.head.modules()) == 4, exploration
