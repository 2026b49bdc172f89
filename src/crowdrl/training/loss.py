"""Double DQN loss with n-step targets, as a TorchRL ``LossModule`` (the D3QN update).

Same function as ``torchrl.objectives.DQNLoss(double_dqn=True, delay_value=True,
loss_function="l2")`` with a TD(0) estimator reading ``steps_to_next_obs`` (a test checks the
two agree on loss and gradients), written directly on the Q network:

    y = r + γ^m (1 - terminated) Q_target(s', argmax_a Q(s', a)),   loss = mean (Q(s, a) - y)²

where ``r`` is the (n-step, possibly intrinsic-augmented) ``("next", "reward")`` and ``m`` the
transition's ``steps_to_next_obs`` (1 when absent). ``DQNLoss`` swaps the target parameters into
the online module and routes every pass through tensordict modules, which costs about a third
of an update on CPU at batch 100; here the target network is a plain frozen copy, refreshed by
:meth:`D3QNLoss.update_target`.

``compile=True`` runs both networks' forwards through ``torch.compile`` (inductor fuses the
encoder's small ops per pass and their backward; ``experiments/bench_train.py --loss eager
compiled`` measures the gain), compiled on first use and cached on disk by inductor. It falls
back to eager with a warning if compilation fails (no C++ compiler).
"""

from __future__ import annotations

import copy
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torchrl.objectives import LossModule

from crowdrl.models.lazy_compile import LazyCompiled


class D3QNLoss(LossModule):
    """Double DQN loss for a Q network ``net(*obs) -> [batch, num_actions]``.

    ``obs_keys`` name the network's inputs in the sampled tensordict (and under ``"next"``);
    ``"action"`` is an integer index (``[batch]`` or ``[batch, 1]``) or a one-hot ``[batch,
    num_actions]``. ``double=False`` bootstraps with ``max_a Q_target(s', a)`` instead.
    ``compile=True`` compiles the two networks' forwards (see the module docstring).
    """

    def __init__(self, net: nn.Module, obs_keys: Sequence[str], gamma: float, double: bool = True,
                 compile: bool = False) -> None:
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        if not obs_keys:
            raise ValueError("obs_keys must name at least one observation key")
        super().__init__()
        self.net = net
        self.target_net = copy.deepcopy(net).requires_grad_(False)
        self.obs_keys = list(obs_keys)
        self.gamma = float(gamma)
        self.double = bool(double)
        self.compile = bool(compile)
        # (online, target) forwards; compiled bound methods keep the modules the only registered children
        self._forwards = tuple(LazyCompiled(n.forward, dynamic=False, what="the Q network", enabled=self.compile)
                               for n in (self.net, self.target_net))

    @property
    def in_keys(self) -> list:
        return [*self.obs_keys, "action", "steps_to_next_obs",
                *[("next", k) for k in (*self.obs_keys, "reward", "terminated")]]

    @property
    def out_keys(self) -> list[str]:
        return ["loss", "q_mean", "td_error_abs"]

    @torch.no_grad()
    def update_target(self) -> None:
        """Copy the online parameters and buffers into the target network (a hard update)."""
        for dst, src in zip(self.target_net.parameters(), self.net.parameters()):
            dst.copy_(src)
        for dst, src in zip(self.target_net.buffers(), self.net.buffers()):
            dst.copy_(src)

    def _q(self, which: int, obs: list[Tensor]) -> Tensor:
        """Q values of the online (``which=0``) or target (``1``) network, compiled if asked."""
        return self._forwards[which](*obs)

    def _obs(self, td: TensorDictBase, prefix: tuple = ()) -> list[Tensor]:
        out = []
        for key in self.obs_keys:
            full = (*prefix, key) if prefix else key
            value = td.get(full, None)
            if value is None:
                raise KeyError(f"D3QNLoss: key {full!r} missing from the batch (keys: {list(td.keys(True))})")
            out.append(value)
        return out

    @torch.no_grad()
    def target(self, td: TensorDictBase) -> Tensor:
        """The bootstrapped target ``y`` ``[batch]`` (no gradient)."""
        nxt = self._obs(td, ("next",))
        q_target = self._q(1, nxt)
        if self.double:
            best = self._q(0, nxt).argmax(-1, keepdim=True)
            boot = q_target.gather(-1, best).squeeze(-1)
        else:
            boot = q_target.amax(-1)
        reward = td.get(("next", "reward")).reshape(boot.shape)
        terminated = td.get(("next", "terminated")).reshape(boot.shape)
        steps = td.get("steps_to_next_obs", None)
        discount = self.gamma if steps is None else self.gamma ** steps.reshape(boot.shape).to(boot.dtype)
        return reward + discount * boot * (~terminated)

    def chosen_q(self, td: TensorDictBase) -> Tensor:
        """``Q(s, a)`` ``[batch]`` for the stored actions, with gradient."""
        q = self._q(0, self._obs(td))
        action = td.get("action")
        if action.dtype == torch.bool or (action.dim() == q.dim() and action.shape[-1] == q.shape[-1] and q.shape[-1] > 1):
            index = action.to(torch.int64).argmax(-1, keepdim=True)  # one-hot
        else:
            index = action.reshape(q.shape[:-1] + (1,)).to(torch.int64)
        if bool(((index < 0) | (index >= q.shape[-1])).any()):
            raise ValueError(f"actions must lie in 0..{q.shape[-1] - 1}")
        return q.gather(-1, index).squeeze(-1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        y = self.target(tensordict)
        q = self.chosen_q(tensordict)
        diff = q - y
        loss = diff.pow(2).mean()
        return TensorDict({"loss": loss, "q_mean": q.detach().mean(), "td_error_abs": diff.detach().abs().mean()}, [])


__all__ = ["D3QNLoss"]
