"""Noisy-net and dropout exploration of a Q-network head (``crowdrl.exploration.noisy`` / ``.dropout``)."""

import copy
import json
import math
import subprocess
import sys
import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Categorical
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss, HardUpdate

from crowdrl.envs import CrowdNavEnv, RobotCentric
from crowdrl.exploration.dropout import (
    ScheduledDropout,
    acting,
    add_action_dropout,
    dropout_layers,
    set_acting,
    set_dropout_p,
)
from crowdrl.exploration.schedule import linear_schedule
from crowdrl.exploration.noisy import (
    FactorisedNoisyLinear,
    noise_disabled,
    noisify_head,
    noisy_layers,
    reset_noise,
    set_noise,
)
from crowdrl.models import DuelingHead, make_q_network

IN_KEYS = ["robot_rc", "humans_rc"]


def _obs(batch: int = 6, n: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.randn(batch, 9), torch.randn(batch, n, 5)


def _noisy_net(sigma0: float = 0.5) -> nn.Module:
    """The SG-D3QN Q-network with a noisy dueling head."""
    net = make_q_network("sgd3qn")
    noisify_head(net.head, sigma0)
    return net


def _dropout_net(p: float = 0.5) -> nn.Module:
    """The SG-D3QN Q-network with action dropout in its dueling head."""
    net = make_q_network("sgd3qn")
    add_action_dropout(net.head, p)
    return net


def _plain_head_from_noisy(head: DuelingHead) -> DuelingHead:
    """A plain DuelingHead whose Linear weights are the noisy head's mean weights."""
    plain = DuelingHead(head.embedding_dim, head.num_actions)
    sd = {k.replace("weight_mu", "weight").replace("bias_mu", "bias"): v
          for k, v in head.state_dict().items() if k.endswith(("weight_mu", "bias_mu"))}
    plain.load_state_dict(sd)
    return plain


def _actor(net: nn.Module) -> QValueActor:
    return QValueActor(TensorDictModule(net, IN_KEYS, ["action_value"]), in_keys=IN_KEYS, spec=Categorical(81))


def _transitions(batch: int = 8) -> TensorDict:
    robot, humans = _obs(batch)
    nrobot, nhumans = _obs(batch)
    return TensorDict({
        "robot_rc": robot, "humans_rc": humans, "action": torch.randint(0, 81, (batch,)),
        "next": {"robot_rc": nrobot, "humans_rc": nhumans, "reward": torch.randn(batch, 1),
                 "done": torch.zeros(batch, 1, dtype=torch.bool),
                 "terminated": torch.zeros(batch, 1, dtype=torch.bool)},
    }, [batch])


def _dqn_loss(net: nn.Module) -> tuple[DQNLoss, HardUpdate]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loss = DQNLoss(_actor(net), delay_value=True, double_dqn=True, loss_function="l2",
                       action_space=Categorical(81))
    loss.make_value_estimator(gamma=0.97)
    return loss, HardUpdate(loss, value_network_update_interval=0)


# ----------------------------------------------------------------------------------- noisy nets
def test_noisify_replaces_every_head_linear_only():
    net = _noisy_net()
    plain = DuelingHead()
    layers = [m for m in net.head.modules() if isinstance(m, nn.Linear)]
    assert len(layers) == 6 and all(type(m) is FactorisedNoisyLinear for m in layers)
    shapes = [(m.in_features, m.out_features) for m in plain.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in layers] == shapes
    assert not any(isinstance(m, FactorisedNoisyLinear) for m in net.encoder.modules())  # encoder unchanged
    assert len(noisy_layers(net)) == 6
    with pytest.raises(ValueError, match="already noisy"):
        noisify_head(net.head)
    with pytest.raises(ValueError, match="sigma0"):
        noisify_head(DuelingHead(), sigma0=-0.1)


@pytest.mark.parametrize("sigma0", [0.5, 0.1])
def test_sigma_and_mu_init_follow_the_paper(sigma0):
    head = noisify_head(DuelingHead(), sigma0=sigma0)
    for layer in noisy_layers(head):
        s = sigma0 / math.sqrt(layer.in_features)  # paper: σ0 / sqrt(p), biases included
        assert torch.allclose(layer.weight_sigma, torch.full_like(layer.weight_sigma, s))
        assert torch.allclose(layer.bias_sigma, torch.full_like(layer.bias_sigma, s))
        bound = 1 / math.sqrt(layer.in_features)
        assert layer.weight_mu.abs().max() <= bound and layer.bias_mu.abs().max() <= bound


def test_noise_is_factorised_rank_one_with_right_statistics():
    layer = FactorisedNoisyLinear(128, 81)
    samples = []
    for _ in range(50):
        layer.reset_noise()
        eps_w, f_out = layer.weight_epsilon, layer.bias_epsilon  # bias noise is f(eps_out)
        assert eps_w.shape == (81, 128) and f_out.shape == (81,)
        assert torch.linalg.matrix_rank(eps_w).item() == 1
        f_in = eps_w[0] / f_out[0]
        assert torch.allclose(eps_w, torch.outer(f_out, f_in), rtol=1e-4, atol=1e-5)
        samples.append(torch.cat([f_in, f_out]))
    f = torch.cat(samples)  # f(x) = sign(x) sqrt|x|, x ~ N(0, 1): E f = 0, E f^2 = E|x| = sqrt(2/pi)
    assert abs(f.mean().item()) < 0.03
    assert abs(f.pow(2).mean().item() - math.sqrt(2 / math.pi)) < 0.03


def test_noisy_q_resamples_and_mean_weights_when_disabled():
    net = _noisy_net()
    robot, humans = _obs()
    with torch.no_grad():
        q1, q1_again = net(robot, humans), net(robot, humans)
        reset_noise(net)
        q2 = net(robot, humans)
        with noise_disabled(net):
            off1 = net(robot, humans)
            reset_noise(net)
            off2 = net(robot, humans)
        q3 = net(robot, humans)  # the flag is restored on exit
        mean_q = _plain_head_from_noisy(net.head)(net.encoder(robot, humans))
        set_noise(net, False)
        off3 = net(robot, humans)
        set_noise(net, True)
        net.eval()
        off4 = net(robot, humans)  # eval() also turns the noise off
    assert torch.equal(q1, q1_again)  # fixed noise between resamples
    assert not torch.allclose(q1, q2)
    assert not torch.allclose(q2, q3)  # noise on again, with the sample drawn inside the block
    assert torch.equal(off1, off2) and torch.equal(off1, off3) and torch.equal(off1, off4)
    assert torch.allclose(off1, mean_q, atol=1e-5)


def test_gradients_reach_mu_and_sigma():
    net = _noisy_net()
    net(*_obs()).pow(2).mean().backward()
    for layer in noisy_layers(net):
        for p in (layer.weight_mu, layer.weight_sigma, layer.bias_mu, layer.bias_sigma):
            assert p.grad is not None and p.grad.abs().sum() > 0
    net.zero_grad(set_to_none=True)
    with noise_disabled(net):
        net(*_obs()).pow(2).mean().backward()
    assert all(layer.weight_sigma.grad is None for layer in noisy_layers(net))


def test_state_dict_round_trip_between_noisy_nets():
    a = _noisy_net()
    torch.manual_seed(1)
    b = _noisy_net()
    obs = _obs()
    with torch.no_grad():
        assert not torch.allclose(a(*obs), b(*obs))
        sd = a.state_dict()
        assert any(k.endswith("weight_epsilon") for k in sd)  # the noise sample travels with it
        b.load_state_dict(sd)
        assert torch.equal(a(*obs), b(*obs))
        with noise_disabled(a), noise_disabled(b):
            assert torch.equal(a(*obs), b(*obs))
        reset_noise(b)
        assert not torch.equal(a(*obs), b(*obs))


def test_dqn_loss_trains_sigma_and_target_noise_is_independent():
    net = _noisy_net()
    loss, updater = _dqn_loss(net)
    online, target = loss.value_network_params, loss.target_value_network_params
    eps_keys = [k for k in online.keys(True, True) if k[-1] in ("weight_epsilon", "bias_epsilon")]
    assert len(eps_keys) == 12
    before = {k: (online.get(k).clone(), target.get(k).clone()) for k in eps_keys}
    reset_noise(loss)
    for k in eps_keys:
        assert not torch.equal(online.get(k), before[k][0]) and not torch.equal(target.get(k), before[k][1])
        assert not torch.equal(online.get(k), target.get(k))
    assert torch.equal(online.get(eps_keys[0]), net.head.trunk[0].weight_epsilon)  # same storage as the net
    loss(_transitions())["loss"].backward()
    for layer in noisy_layers(net):  # the DQN loss sees the noisy weights
        assert layer.weight_sigma.grad is not None and layer.weight_sigma.grad.abs().sum() > 0
    with torch.no_grad():
        for layer in noisy_layers(net):
            layer.weight_sigma.mul_(2)
    updater.step()  # interval 0: copy now; HardUpdate copies parameters, not the noise buffers
    sigma_key = eps_keys[0][:-1] + ("weight_sigma",)
    assert torch.equal(online.get(sigma_key), target.get(sigma_key))
    assert not torch.equal(online.get(eps_keys[0]), target.get(eps_keys[0]))


def test_reset_noise_on_a_module_holding_online_and_target_copies():
    """The layout of a loss that keeps ``net`` and a deep-copied ``target_net`` as children."""
    net = _noisy_net()
    pair = nn.ModuleDict({"net": net, "target_net": copy.deepcopy(net).requires_grad_(False)})
    obs = _obs()
    # allclose, not equal: the pairwise kernel is compiled lazily per module, and which kernel each
    # copy gets (static or dynamic shapes) depends on what earlier tests compiled (last-bit rounding)
    close = dict(rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        assert torch.allclose(pair["net"](*obs), pair["target_net"](*obs), **close)  # the copy carries the noise
        reset_noise(pair)
        assert not torch.allclose(pair["net"](*obs), pair["target_net"](*obs), rtol=1e-3, atol=1e-3)
        with noise_disabled(pair):
            assert torch.allclose(pair["net"](*obs), pair["target_net"](*obs), **close)


# -------------------------------------------------------------------------------------- dropout
def test_dropout_after_each_hidden_relu_and_same_state_dict_keys():
    plain = DuelingHead()
    head = add_action_dropout(DuelingHead(), p=0.3)
    n_relu = sum(isinstance(m, nn.ReLU) for m in plain.modules())
    assert n_relu == 4 and len(dropout_layers(head)) == 4
    for seq in (head.trunk[1], head.trunk[3], head.value[1], head.advantage[1]):
        assert isinstance(seq[0], nn.ReLU) and isinstance(seq[1], ScheduledDropout) and seq[1].p == 0.3
    assert head.state_dict().keys() == plain.state_dict().keys()
    plain.load_state_dict(head.state_dict())  # a dropout-trained head evaluates as a plain one
    with pytest.raises(ValueError, match="already"):
        add_action_dropout(head, 0.1)


def test_dropout_only_when_acting():
    net = _dropout_net(0.5)
    plain = make_q_network("sgd3qn")
    plain.load_state_dict(net.state_dict())
    obs = _obs()
    with torch.no_grad():
        ref = plain(*obs)
        assert torch.equal(net(*obs), ref)  # plain call: no exploration type -> off
        for mode in (ExplorationType.DETERMINISTIC, ExplorationType.MODE):
            with set_exploration_type(mode):
                assert torch.equal(net(*obs), ref)
        with acting(net):
            a1, a2 = net(*obs), net(*obs)
            with acting(net, False), set_exploration_type(ExplorationType.RANDOM):
                assert torch.equal(net(*obs), ref)  # explicit off beats the exploration type
        assert not torch.allclose(a1, ref) and not torch.allclose(a1, a2)  # a fresh mask per call
        assert all(layer.acting is None for layer in dropout_layers(net))  # restored
        with set_exploration_type(ExplorationType.RANDOM):  # what a Collector sets
            assert not torch.allclose(net(*obs), ref)
        set_acting(net, True)
        net.eval()
        assert torch.equal(net(*obs), ref)  # eval() is a global off
        net.train()
        set_dropout_p(net, 0.0)
        assert torch.equal(net(*obs), ref)  # p = 0 while acting
        set_acting(net, None)


def test_set_dropout_p_and_bad_p():
    net = _dropout_net(0.5)
    set_dropout_p(net, 0.2)
    assert [layer.p for layer in dropout_layers(net)] == [0.2] * 4
    for bad in (-0.1, 1.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"p="):
            set_dropout_p(net, bad)
        with pytest.raises(ValueError, match=r"p="):
            add_action_dropout(DuelingHead(), bad)
        with pytest.raises(ValueError, match=r"p="):
            ScheduledDropout(bad)
    assert [layer.p for layer in dropout_layers(net)] == [0.2] * 4
    with pytest.raises(TypeError):
        set_acting(net, 1)


def test_dropout_p_follows_the_shared_linear_schedule():
    """The trainer anneals dropout p with the same linear schedule as ε (0.5 -> 0.01 by default)."""
    assert linear_schedule(0.5, 0.01, 100, 0) == pytest.approx(0.5)
    assert linear_schedule(0.5, 0.01, 100, 50) == pytest.approx(0.255)
    assert linear_schedule(0.5, 0.01, 100, 100) == pytest.approx(0.01)
    assert linear_schedule(0.5, 0.01, 100, 10**6) == pytest.approx(0.01)
    assert linear_schedule(0.4, 0.1, 10, -5) == pytest.approx(0.4)   # never beyond start


def test_dqn_loss_is_deterministic_with_dropout():
    net = _dropout_net(0.5)
    loss, _ = _dqn_loss(net)
    td = _transitions()
    with set_exploration_type(ExplorationType.RANDOM):  # LossModule switches to DETERMINISTIC
        l1, l2 = loss(td.clone())["loss"], loss(td.clone())["loss"]
    assert torch.equal(l1, l2)


# ------------------------------------------------------------------------------------ generic
def test_surgery_works_on_any_module():
    torch.manual_seed(0)
    head = nn.Sequential(nn.Linear(4, 8), nn.ReLU(), nn.Linear(8, 3))
    plain = copy.deepcopy(head)
    noisy = noisify_head(copy.deepcopy(head), sigma0=0.3)
    assert [type(m) for m in noisy] == [FactorisedNoisyLinear, nn.ReLU, FactorisedNoisyLinear]
    assert [(m.in_features, m.out_features) for m in noisy_layers(noisy)] == [(4, 8), (8, 3)]
    x = torch.randn(5, 4)
    with torch.no_grad():
        assert noisy(x).shape == (5, 3)
    dropped = add_action_dropout(head, p=0.5)
    assert len(dropout_layers(dropped)) == 1 and isinstance(dropped[1][1], ScheduledDropout)
    assert dropped.state_dict().keys() == plain.state_dict().keys()
    with torch.no_grad():
        assert torch.equal(dropped(x), plain(x))  # not acting: the plain network
        with acting(dropped):
            assert dropped(x).shape == (5, 3)
    with pytest.raises(ValueError, match="nn.Linear"):
        noisify_head(nn.Sequential(nn.ReLU()))
    with pytest.raises(ValueError, match="nn.ReLU"):
        add_action_dropout(nn.Sequential(nn.Linear(4, 3), nn.Tanh()))


def test_noisy_and_dropout_import_no_crowd_code():
    code = ("import json, sys; import crowdrl.exploration.noisy, crowdrl.exploration.dropout; "
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('crowdrl.'))))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    modules = json.loads(proc.stdout.splitlines()[-1])
    assert "crowdrl.exploration.noisy" in modules and "crowdrl.exploration.dropout" in modules
    assert not [m for m in modules if m.startswith(("crowdrl.models", "crowdrl.sim", "crowdrl.envs"))], modules


# --------------------------------------------------------------------------- TorchRL integration
@pytest.mark.parametrize("kind", ["noisy", "dropout"])
def test_q_value_actor_actions_in_range(kind):
    net = _noisy_net() if kind == "noisy" else _dropout_net(0.5)
    actor = _actor(net)
    robot, humans = _obs(16)
    with set_exploration_type(ExplorationType.RANDOM):
        td = actor(TensorDict({"robot_rc": robot, "humans_rc": humans}, [16]))
    action = td["action"]
    assert action.shape == (16,) and action.dtype == torch.long
    assert ((action >= 0) & (action < 81)).all()
    assert torch.equal(action, td["action_value"].argmax(-1))


def test_collector_acts_with_dropout_and_shares_noisy_weights():
    base = CrowdNavEnv(num_envs=2, seed=0, split="train")
    env = TransformedEnv(base, RobotCentric())
    net = _dropout_net(0.5)
    collector = Collector(env, _actor(net), frames_per_batch=4, total_frames=-1, auto_register_policy_transforms=False)
    batch = next(iter(collector))
    collector.shutdown()
    with torch.no_grad():
        assert not torch.allclose(batch["action_value"], net(batch["robot_rc"], batch["humans_rc"]))
    noisy = _noisy_net()
    collector = Collector(env, _actor(noisy), frames_per_batch=2, total_frames=-1, auto_register_policy_transforms=False)
    it = iter(collector)
    for _ in range(2):  # the collector uses the net's own noise buffers: reset_noise between batches acts
        batch = next(it)
        with torch.no_grad():
            assert torch.allclose(batch["action_value"], noisy(batch["robot_rc"], batch["humans_rc"]), atol=1e-5)
        reset_noise(noisy)
    collector.shutdown()
