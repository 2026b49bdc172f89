"""The crowd encoders SARL, LSTM-RL and MP-RGL: shapes, symmetries, masks, gradients, training;
SG-D3QN's mask too."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from crowdrl_testing import robot_centric_states, fresh_network
from crowdrl.models import (
    ENCODERS,
    LSTMRLEncoder,
    MPRGLEncoder,
    SARLEncoder,
    make_encoder,
    make_q_network,
)
from crowdrl.models.lstm_rl import sort_far_to_near
from crowdrl.training import ConfigError, validate
from crowdrl.training.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
NAMES = ["sarl", "lstm_rl", "mp_rgl"]
MASKED = [*NAMES, "sgd3qn"]  # every registered encoder honours humans_mask
# (class, embedding_dim, parameter count): SPEC §2 dimensions
EXPECTED = {"sarl": (SARLEncoder, 59, 62801), "lstm_rl": (LSTMRLEncoder, 59, 13000), "mp_rgl": (MPRGLEncoder, 32, 9280)}


def _states(*batch: int, n: int = 6, dtype=torch.float64):
    return robot_centric_states(*batch, n=n, dtype=dtype)


def _encoder(name: str, dtype=torch.float64) -> nn.Module:
    return make_encoder(name).to(dtype)


@pytest.mark.parametrize("name", NAMES)
def test_registered_with_spec_sizes_and_a_hydra_yaml(name):
    cls, dim, count = EXPECTED[name]
    enc = make_encoder(name)
    assert ENCODERS[name] is cls and isinstance(enc, cls)
    assert enc.embedding_dim == dim
    assert sum(p.numel() for p in enc.parameters()) == count
    assert (ROOT / "conf" / "encoder" / f"{name}.yaml").read_text().splitlines()[-1] == f"name: {name}"


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
@pytest.mark.parametrize("n", [1, 4])
def test_shapes_for_any_batch_dims_and_crowd_size(name, batch, n):
    robot, humans = _states(*batch, n=n, dtype=torch.float32)
    net = make_q_network(name)
    emb = net.encoder(robot, humans)
    assert emb.shape == (*batch, net.encoder.embedding_dim) and emb.dtype == torch.float32
    q = net(robot, humans)
    assert q.shape == (*batch, 81) and torch.isfinite(q).all()
    mask = torch.ones(*batch, n, dtype=torch.bool)
    torch.testing.assert_close(net.encoder(robot, humans, mask), emb)  # all present == no mask


@pytest.mark.parametrize("name", NAMES)
def test_rows_are_independent_and_batch_dims_flatten(name):
    enc = _encoder(name)
    robot, humans = _states(2, 3)
    out = enc(robot, humans)
    torch.testing.assert_close(out[1, 2], enc(robot[1, 2], humans[1, 2]), rtol=0, atol=1e-12)
    flat = enc(robot.reshape(6, 9), humans.reshape(6, 6, 5))
    torch.testing.assert_close(out.reshape(6, -1), flat, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", NAMES)  # LSTM-RL too: it sorts the humans by distance first
def test_invariant_to_the_order_of_the_humans(name):
    enc = _encoder(name)
    robot, humans = _states(4, n=7)
    mask = torch.rand(4, 7) < 0.7
    mask[:, 0] = True
    perm = torch.randperm(7)
    torch.testing.assert_close(enc(robot, humans[:, perm]), enc(robot, humans), rtol=0, atol=1e-12)
    torch.testing.assert_close(enc(robot, humans[:, perm], mask[:, perm]), enc(robot, humans, mask), rtol=0, atol=1e-12)
    # and it does depend on the humans (not a constant)
    assert not torch.allclose(enc(robot, humans), enc(robot, humans.flip(0)))


def _reference_lstm(enc: LSTMRLEncoder) -> nn.LSTM:
    """``nn.LSTM`` with the encoder's weights (one bias in ``bias_ih``, ``bias_hh`` zero)."""
    lstm = nn.LSTM(14, enc.hidden_dim, batch_first=True).double()
    with torch.no_grad():
        lstm.weight_ih_l0.copy_(enc.input.weight)
        lstm.bias_ih_l0.copy_(enc.input.bias)
        lstm.weight_hh_l0.copy_(enc.hidden.weight)
        lstm.bias_hh_l0.zero_()
    return lstm


def test_lstm_rl_feeds_the_closest_human_last():
    enc = _encoder("lstm_rl")
    robot = torch.tensor([0, 0, 0.5, 0.1, 0.3, 4.0, 0, 1.0, 0.2], dtype=torch.float64)
    # distances 1, 5, 3 (human 0 the closest): the LSTM must see 1 (5 m), 2 (3 m), 0 (1 m)
    humans = torch.tensor([[0.6, 0.8, 0.1, 0.0, 0.6],
                           [3.0, -4.0, -0.5, 0.2, 0.6],
                           [0.0, 3.0, 0.3, -0.9, 0.6]], dtype=torch.float64)
    sorted_humans, _ = sort_far_to_near(humans.unsqueeze(0), None)
    assert torch.equal(sorted_humans[0], humans[[1, 2, 0]])

    lstm = _reference_lstm(enc)

    def run(order):
        seq = torch.cat((robot.expand(3, 9), humans[order]), dim=-1).unsqueeze(0)
        return torch.cat((robot, lstm(seq)[1][0][0, 0]))

    out = enc(robot, humans)
    torch.testing.assert_close(out, run([1, 2, 0]), rtol=0, atol=1e-12)  # far -> near, closest last
    assert not torch.allclose(out, run([0, 2, 1]))  # near -> far is another function
    # masked: an absent human is skipped wherever it sorts (it sorts first, as if infinitely far)
    mask = torch.tensor([True, True, False])
    seq = torch.cat((robot.expand(2, 9), humans[[1, 0]]), dim=-1).unsqueeze(0)
    torch.testing.assert_close(enc(robot, humans, mask), torch.cat((robot, lstm(seq)[1][0][0, 0])), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_gradients_reach_every_parameter(name):
    enc = _encoder(name)
    robot, humans = _states(8, n=5)
    mask = torch.ones(8, 5, dtype=torch.bool)
    mask[::2, 3:] = False
    (enc(robot, humans, mask) ** 2).sum().backward()
    for pname, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), pname
        assert p.grad.abs().sum() > 0, f"{name}: no gradient reaches {pname}"


@pytest.mark.parametrize("name", MASKED)
def test_padded_masked_batch_equals_the_unpadded_one(name):
    """Rows with 1..5 humans, padded to 8 with garbage (NaN included) at random places, masked."""
    enc = _encoder(name)
    counts = [1, 3, 5, 2, 4, 5]
    rows = [_states(n=k) for k in counts]
    expected = torch.stack([enc(r, h) for r, h in rows])

    n_max = 8
    robot = torch.stack([r for r, _ in rows])
    humans = 100 * torch.randn(len(counts), n_max, 5, dtype=torch.float64)
    humans[0, 1:] = float("nan")
    mask = torch.zeros(len(counts), n_max, dtype=torch.bool)
    for i, (k, (_, h)) in enumerate(zip(counts, rows)):
        slots = torch.randperm(n_max)[:k].sort().values  # present humans keep their order, padding in between
        humans[i, slots] = h
        mask[i, slots] = True
    humans.requires_grad_(True)
    out = enc(robot, humans, mask)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-6)
    out.sum().backward()
    assert torch.all(humans.grad[~mask] == 0) and torch.isfinite(humans.grad).all()  # absent humans take no part

    # the same with two leading batch dims
    out2 = enc(robot.reshape(2, 3, 9), humans.detach().reshape(2, 3, n_max, 5), mask.reshape(2, 3, n_max))
    torch.testing.assert_close(out2.reshape(len(counts), -1), expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", MASKED)
def test_the_q_network_passes_the_mask_to_its_encoder(name):
    net = make_q_network(name).double()
    robot, humans = _states(3, n=4)
    padded = torch.cat((humans, torch.full((3, 2, 5), float("nan"), dtype=torch.float64)), dim=1)
    mask = torch.arange(6).expand(3, 6) < 4
    torch.testing.assert_close(net(robot, padded, mask), net(robot, humans), rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", MASKED)
def test_a_row_without_humans_stays_finite(name):
    enc = _encoder(name)
    robot, humans = _states(2, n=3)
    mask = torch.tensor([[True, False, True], [False, False, False]])
    assert torch.isfinite(enc(robot, humans, mask)).all()


@pytest.mark.parametrize("name", MASKED)
def test_bad_inputs_raise(name):
    enc = _encoder(name)
    robot, humans = _states(4, n=3)
    with pytest.raises(ValueError, match="robot_rc"):
        enc(robot[..., :8], humans)
    with pytest.raises(ValueError, match="humans_rc"):
        enc(robot, humans[..., :4])
    with pytest.raises(ValueError, match="humans_rc"):
        enc(robot, humans[:3])
    with pytest.raises(ValueError, match="at least one human"):
        enc(robot, humans[:, :0])
    with pytest.raises(ValueError, match="humans_mask"):
        enc(robot, humans, torch.ones(4, 3))  # not bool
    with pytest.raises(ValueError, match="humans_mask"):
        enc(robot, humans, torch.ones(4, 2, dtype=torch.bool))


def test_unknown_encoder_names_the_allowed_ones():
    with pytest.raises(ValueError, match="allowed") as err:
        make_encoder("nope")
    assert all(name in str(err.value) for name in [*NAMES, "sgd3qn"])
    with pytest.raises(ConfigError, match=r"encoder\.name") as err:
        validate({"encoder": {"name": "nope"}})
    assert all(name in str(err.value) for name in [*NAMES, "sgd3qn"])


# ---------------------------------------------------------------- one smoke run per encoder x variant
TINY = {"logger": {"progress_bar": False, "render": False},
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 96, "buffer_size": 1000, "batch_size": 16,
                  "warmup_frames": 32, "updates_per_frame": 0.25, "target_update_frames": 32,
                  "val_every_frames": 96, "val_episodes": 2, "checkpoint_every_frames": 96, "test_episodes": 2,
                  "compile_loss": False},
        "env": {"min_humans": 1, "max_humans": 4}}  # a crowd of 1..4 humans: the networks read the mask


def _compose(name: str, exploration: str) -> dict:
    """The run config as ``train.py encoder=<name> exploration=<exploration> preset=smoke logger=csv`` composes it."""
    from hydra import compose, initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    from crowdrl.training.config import RunConfig

    from crowdrl.training.resolvers import register_resolvers

    register_resolvers()
    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[f"encoder={name}", f"exploration={exploration}",
                                                       "preset=smoke", "logger=csv"])
    return OmegaConf.merge(cfg, TINY)


@pytest.mark.parametrize("exploration", ["egreedy", "icm", "re3"])  # ~2 s each on a 2-core CPU
@pytest.mark.parametrize("name", NAMES)
def test_each_encoder_trains_through_hydra(tmp_path, name, exploration):
    run = validate(_compose(name, exploration))
    assert run.encoder.name == name and run.exploration.name == exploration
    trainer = Trainer(run, tmp_path)
    try:
        summary = trainer.train()
        assert isinstance(trainer.net.encoder, EXPECTED[name][0])
        if exploration != "egreedy":
            assert isinstance(trainer.strategy.bonus.encoder, EXPECTED[name][0])
            assert list(trainer.strategy.bonus.in_keys) == ["robot_rc", "humans_rc", "humans_mask"]  # its encoder reads the mask
    finally:
        trainer.close()
    assert summary["updates"] > 0 and summary["frames"] == 96
    assert all(torch.isfinite(p).all() for p in trainer.net.parameters())
    assert trainer.learner.loss.obs_keys == ["robot_rc", "humans_rc", "humans_mask"]
    sample = trainer.buffer.sample()
    assert sample.get("humans_mask").shape == (16, 4) and not bool(sample.get("humans_mask").all())
    if exploration != "egreedy":
        assert trainer.strategy.transform.last_stats["reward_int_raw_mean"] > 0  # the bonus was computed from this encoder


def test_a_checkpoint_of_one_encoder_is_refused_by_another(tmp_path):
    """SG-D3QN weights saved under a SARL config (a valid fingerprint for that config): loading
    builds the SARL network from the config and refuses the weights, naming the file."""
    from crowdrl.training.checkpoint import CheckpointError, config_fingerprint, save_checkpoint
    from crowdrl.training.config import to_dict
    from crowdrl.training.pipeline import load_trained_network

    sgd3qn = validate({"encoder": {"name": "sgd3qn"}})
    sarl = to_dict(validate({"encoder": {"name": "sarl"}}))
    path = tmp_path / "best.pt"
    save_checkpoint(path, {"net": fresh_network(sgd3qn).state_dict(), "config": sarl}, config_fingerprint(sarl))
    with pytest.raises(CheckpointError, match=r"best\.pt: the network shape does not match its config"):
        load_trained_network(path)
