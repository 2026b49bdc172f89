"""Value networks: SG-D3QN encoder (vs a naive reference), dueling head, registry, Q actor."""

import pytest
import torch
from torchrl.data import Categorical
from torchrl.envs import TransformedEnv

from crowdrl_testing import robot_centric_states
from crowdrl.envs import CrowdNavEnv, RobotCentric
from crowdrl.models import (
    ENCODERS,
    CrowdQNetwork,
    DuelingHead,
    SGD3QNEncoder,
    SGD3QNEncoderNaive,
    make_encoder,
    make_q_actor,
    make_q_network,
    register_encoder,
)
from crowdrl.models import sgd3qn
from crowdrl.models.sgd3qn import _PairwiseScore


def _states(*batch: int, n: int = 10, dtype=torch.float32):
    return robot_centric_states(*batch, n=n, dtype=dtype)


def _pair(dtype=torch.float32):
    enc = SGD3QNEncoder().to(dtype)
    naive = SGD3QNEncoderNaive().to(dtype)
    naive.load_state_dict(enc.state_dict())
    return enc, naive


@pytest.mark.parametrize("batch", [(), (1,), (4,), (2, 3)])
@pytest.mark.parametrize("n", [1, 3, 10])
def test_shapes(batch, n):
    net = make_q_network("sgd3qn")
    robot, humans = _states(*batch, n=n)
    emb = net.encoder(robot, humans)
    assert emb.shape == (*batch, 32) and net.encoder.embedding_dim == 32
    q = net(robot, humans)
    assert q.shape == (*batch, 81)
    assert torch.isfinite(q).all()


def test_bad_shapes_raise():
    enc = SGD3QNEncoder()
    with pytest.raises(ValueError):
        enc(torch.zeros(4, 8), torch.zeros(4, 3, 5))
    with pytest.raises(ValueError):
        enc(torch.zeros(4, 9), torch.zeros(5, 3, 5))
    with pytest.raises(ValueError):
        enc(torch.zeros(4, 9), torch.zeros(4, 0, 5))


def test_parameters_match_the_spec_layout():
    enc = SGD3QNEncoder()
    shapes = {k: tuple(v.shape) for k, v in enc.state_dict().items()}
    assert shapes == {
        "w_r.0.weight": (64, 9), "w_r.0.bias": (64,), "w_r.2.weight": (32, 64), "w_r.2.bias": (32,),
        "w_h.0.weight": (64, 5), "w_h.0.bias": (64,), "w_h.2.weight": (32, 64), "w_h.2.bias": (32,),
        "gat0.w_a.0.weight": (64, 64), "gat0.w_a.0.bias": (64,), "gat0.w_a.2.weight": (1, 64), "gat0.w_a.2.bias": (1,),
        "gat1.w_a.0.weight": (64, 64), "gat1.w_a.0.bias": (64,), "gat1.w_a.2.weight": (1, 64), "gat1.w_a.2.bias": (1,),
    }  # fmt: skip
    head = DuelingHead(32)
    assert [type(m).__name__ for m in head.trunk] == ["Linear", "ReLU", "Linear", "ReLU"]
    assert [type(m).__name__ for m in head.value] == ["Linear", "ReLU", "Linear"]
    assert [type(m).__name__ for m in head.advantage] == ["Linear", "ReLU", "Linear"]
    assert head.value[-1].out_features == 1 and head.advantage[-1].out_features == 81


@pytest.mark.parametrize("n", [1, 2, 10])
def test_optimised_encoder_equals_naive(n):
    enc, naive = _pair()
    robot, humans = _states(6, n=n)
    out, ref = enc(robot, humans), naive(robot, humans)
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    # gradients too, for every parameter
    g = torch.randn_like(out)
    grads = torch.autograd.grad(out, list(enc.parameters()), g)
    ref_grads = torch.autograd.grad(ref, list(naive.parameters()), g)
    for (name, _), a, b in zip(enc.named_parameters(), grads, ref_grads):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4, msg=name)


def test_optimised_encoder_equals_naive_float64_with_input_grads():
    enc, naive = _pair(torch.float64)
    robot, humans = _states(3, n=4, dtype=torch.float64)
    robot.requires_grad_(True)
    humans.requires_grad_(True)
    out, ref = enc(robot, humans), naive(robot, humans)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-12)
    g = torch.randn_like(out)
    a = torch.autograd.grad(out, (robot, humans), g)
    b = torch.autograd.grad(ref, (robot, humans), g)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, atol=1e-11, rtol=1e-10)


@pytest.mark.parametrize("backend", ["eager", "compiled"])
def test_pairwise_score_matches_autograd(backend, monkeypatch):
    monkeypatch.setattr(sgd3qn, "PAIRWISE", sgd3qn.PairwiseKernels(backend))
    rows = torch.randn(2, 3, 6, dtype=torch.float64, requires_grad=True)
    cols = torch.randn(2, 5, 6, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(6, dtype=torch.float64, requires_grad=True)
    w = torch.randn(6, dtype=torch.float64, requires_grad=True)
    out = _PairwiseScore.apply(rows, cols, bias, w)
    ref = torch.relu(rows.unsqueeze(-2) + cols.unsqueeze(-3) + bias) @ w
    torch.testing.assert_close(out, ref)
    g = torch.randn_like(out)
    inputs = (rows, cols, bias, w)
    for x, y in zip(torch.autograd.grad(out, inputs, g), torch.autograd.grad(ref, inputs, g)):
        torch.testing.assert_close(x, y)


def test_compiled_and_eager_pairwise_kernels_agree_on_the_network(monkeypatch):
    """The whole Q network with compiled kernels == with eager ones (values and gradients), at two batch sizes."""
    torch.manual_seed(0)
    net = make_q_network("sgd3qn")
    results = {}
    for backend in ("eager", "compiled"):
        monkeypatch.setattr(sgd3qn, "PAIRWISE", sgd3qn.PairwiseKernels(backend))
        out = []
        for batch in (7, 100):
            torch.manual_seed(batch)
            robot, humans = _states(batch, n=10)
            net.zero_grad()
            q = net(robot, humans)
            q.square().mean().backward()
            out.append((q.detach(), [p.grad.clone() for p in net.parameters()]))
        results[backend] = out
    for (qe, ge), (qc, gc) in zip(results["eager"], results["compiled"]):
        torch.testing.assert_close(qc, qe, rtol=1e-5, atol=1e-6)
        for a, b in zip(gc, ge):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_unknown_pairwise_backend_is_rejected():
    with pytest.raises(ValueError, match="compiled' or 'eager"):
        sgd3qn.PairwiseKernels("cuda-graphs")


def test_humans_do_not_attend_to_the_robot():
    enc, naive = _pair()
    robot, humans = _states(5, n=4)
    x = enc.node_features(robot, humans)
    x2 = x.clone()
    x2[:, 0] += torch.randn(5, 32)  # perturb only the robot node
    h1, h1p = enc.first_layer(x), enc.first_layer(x2)
    assert torch.equal(h1[:, 1:], h1p[:, 1:])  # human rows: not at all
    assert not torch.allclose(h1[:, 0], h1p[:, 0])  # the robot row attends to itself
    # same through the naive reference, from the robot's raw state
    robot2 = robot.clone()
    robot2[:, 2:4] += 1.0
    (xa, h1a, h2a), (xb, h1b, h2b) = naive.naive_layers(robot, humans), naive.naive_layers(robot2, humans)
    assert torch.equal(xa[:, 1:], xb[:, 1:]) and torch.equal(h1a[:, 1:], h1b[:, 1:]) and torch.equal(h2a[:, 1:], h2b[:, 1:])
    assert not torch.allclose(h1a[:, 0], h1b[:, 0])


def test_robot_attends_to_humans():
    enc = SGD3QNEncoder()
    robot, humans = _states(3, n=4)
    humans2 = humans.clone()
    humans2[:, 2, :2] += 1.0
    assert not torch.allclose(enc(robot, humans), enc(robot, humans2))


def test_dueling_head_per_sample_mean():
    head = DuelingHead(32)
    z = torch.randn(8, 32)
    q = head(z)
    v = head.value(head.trunk(z))
    torch.testing.assert_close((q - v).mean(-1), torch.zeros(8), atol=1e-6, rtol=0)
    # a sample's Q does not depend on the rest of its batch
    z2 = z.clone()
    z2[1:] = 10 * torch.randn(7, 32)
    torch.testing.assert_close(head(z2)[0], q[0])
    torch.testing.assert_close(head(z[:1])[0], q[0])


def test_registry():
    assert ENCODERS["sgd3qn"] is SGD3QNEncoder
    assert isinstance(make_encoder("sgd3qn"), SGD3QNEncoder)
    with pytest.raises(ValueError, match="sgd3qn"):
        make_encoder("no-such-encoder")
    with pytest.raises(ValueError, match="already registered"):
        register_encoder("sgd3qn")(SGD3QNEncoderNaive)


def test_gradient_reaches_every_parameter():
    net = CrowdQNetwork(SGD3QNEncoder(), DuelingHead(32))
    robot, humans = _states(16, n=5)
    net(robot, humans).pow(2).mean().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("spec_kind", ["unbatched", "env"])
def test_q_actor_on_env(spec_kind):
    env = TransformedEnv(CrowdNavEnv("circle", num_envs=4, num_humans=5), RobotCentric())
    spec = Categorical(81) if spec_kind == "unbatched" else env.action_spec
    actor = make_q_actor("sgd3qn", spec)
    td = actor(env.reset())
    action, values = td["action"], td["action_value"]
    assert values.shape == (4, 81)
    assert action.dtype == torch.int64 and action.shape == (4,)
    assert ((action >= 0) & (action <= 80)).all()
    assert torch.equal(action, values.argmax(-1))
    net = actor.module[0].module
    assert isinstance(net, CrowdQNetwork)
    torch.testing.assert_close(values, net(td["robot_rc"], td["humans_rc"]))
    td = env.step(td)  # the action is accepted by the env
    assert td["next", "robot_rc"].shape == (4, 9)


def test_q_actor_rejects_non_categorical():
    with pytest.raises(TypeError):
        make_q_actor("sgd3qn", object())
    with pytest.raises(ValueError, match="allowed"):
        make_q_actor("nope", Categorical(81))
