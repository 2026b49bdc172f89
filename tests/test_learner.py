"""The D3QN learner object (``crowdrl.training.learner``): what one update does, in its order, on a tiny
linear Q network: the target rule, the gradient clip, the part's batches, the auxiliary steps first, the
non-finite checks and the checkpoint keys."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from crowdrl.training.learner import D3QNLearner, NonFiniteError
from crowdrl.training.loss import D3QNLoss
from crowdrl.training.parts import ReplayOnly, UpdatePart


def batch(n: int = 8, reward: float = 1.0, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"obs": torch.randn(n, 2, generator=g), "action": torch.randint(0, 3, (n,), generator=g),
                       "next": {"obs": torch.randn(n, 2, generator=g), "reward": torch.full((n, 1), reward),
                                "terminated": torch.zeros(n, 1, dtype=torch.bool)}}, batch_size=[n])


def learner(**kwargs) -> D3QNLearner:
    torch.manual_seed(0)
    net = torch.nn.Linear(2, 3)
    return D3QNLearner(D3QNLoss(net, ["obs"], gamma=0.9), torch.optim.SGD(net.parameters(), lr=0.1),
                       kwargs.pop("part", ReplayOnly()), **kwargs)


def same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters()))


def test_hard_copies_land_on_the_cadence_and_polyak_moves_by_tau():
    hard = learner(updates_per_copy=2)
    hard.step(batch(), 1)
    assert not same(hard.loss.target_net, hard.net)  # update 1 of 2: no copy yet
    hard.step(batch(seed=1), 2)
    assert same(hard.loss.target_net, hard.net)
    soft = learner(target_tau=0.25)
    before = [p.detach().clone() for p in soft.loss.target_net.parameters()]
    soft.step(batch(), 1)
    for old, new, online in zip(before, soft.loss.target_net.parameters(), soft.net.parameters()):
        torch.testing.assert_close(new, old + 0.25 * (online - old))


def test_gradients_are_clipped_before_the_optimiser_step():
    seen = []
    clipped = learner(grad_clip_norm=1e-3)
    step = clipped.optimizer.step

    def spy():
        seen.append(torch.cat([p.grad.flatten() for p in clipped.net.parameters()]).norm().item())
        return step()

    clipped.optimizer.step = spy
    clipped.step(batch(reward=100.0), 1)
    assert seen and seen[0] <= 1e-3 * (1 + 1e-4)


class TwoBatches(UpdatePart):
    """A part that steps on the sample, then on the sample with its reward doubled."""

    def batches(self, sample):
        yield "real", sample
        twice = sample.clone()
        twice["next", "reward"] = 2 * twice["next", "reward"]
        yield "twice", twice


class Counting:
    """An auxiliary learner that records when it steps."""

    def __init__(self, log):
        self.log = log

    def step(self, sample):
        self.log.append("aux")
        return {"aux_steps": 1.0}

    def scalar_names(self):
        return ["aux_steps"]

    def parameters(self):
        return iter(())


def test_a_part_gets_a_step_per_batch_after_the_auxiliary_learners_and_its_losses_are_logged_apart():
    log = []
    two = learner(part=TwoBatches(), learners=[Counting(log)], before_update=lambda loss: log.append("hook"))
    step = two.optimizer.step
    two.optimizer.step = lambda: (log.append("q"), step())[1]
    first = two.step(batch(), 1)
    assert log == ["aux", "hook", "q", "q"]  # the auxiliary step and the strategy's hook come first
    assert math.isfinite(first)
    losses = two.pop_part_losses()
    assert list(losses) == ["loss_twice"] and losses["loss_twice"] > first  # larger rewards, larger TD error
    assert two.pop_part_losses() == {}  # the window starts anew
    assert two.scalars() == {"aux_steps": 1.0}
    two.reset_scalars()
    assert math.isnan(two.scalars()["aux_steps"])  # a window without updates: NaN, not 0


def test_a_non_finite_loss_or_weight_stops_the_run_naming_the_update():
    bad = learner()
    with pytest.raises(NonFiniteError, match="at update 7"):
        bad.step(batch(reward=math.nan), 7)
    with torch.no_grad():
        next(bad.net.parameters())[0, 0] = math.inf
    with pytest.raises(NonFiniteError, match="by update 8"):
        bad.check_finite_weights(8)


def test_state_round_trips_under_the_trainers_checkpoint_keys():
    a = learner(part=TwoBatches())
    a.step(batch(), 1)
    state = a.state_dict()
    assert sorted(state) == ["loss", "optimizer", "part_losses", "update_part"]
    b = learner(part=TwoBatches())
    b.load_state_dict(state)
    assert same(a.net, b.net) and same(a.loss.target_net, b.loss.target_net)
    assert b.pop_part_losses() == a.pop_part_losses()
    old = {k: v for k, v in state.items() if k in ("loss", "optimizer")}  # a checkpoint before parts existed
    learner().load_state_dict(old)


def test_bad_settings_are_refused_naming_them():
    with pytest.raises(ValueError, match="target_tau"):
        learner(target_tau=0.0)
    with pytest.raises(ValueError, match="updates_per_copy"):
        learner(updates_per_copy=0)
