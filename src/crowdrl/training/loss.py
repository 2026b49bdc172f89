"""Double DQN loss with n-step targets, as a TorchRL ``LossModule`` (the D3QN update).

Same function as ``torchrl.objectives.DQNLoss(double_dqn=True, delay_value=True,
loss_function="l2")`` with a TD(0) estimator reading ``steps_to_next_obs`` (a test checks the
two agree on loss and gradients), written directly on the Q network:

    y = r + γ^m (1 - terminated) Q_target(s', argmax_a Q(s', a)),   loss = mean (Q(s, a) - y)²

where ``m`` is the transition's ``steps_to_next_obs`` (1 when absent). The whole target, piece by piece
and where each is computed:

* ``r = Σ_{k<m} γ^k r_{t+k}``: the n-step extrinsic return, written when a collected batch enters the
  replay buffer (``training/nstep.py``; the window stops at the first step that ends an episode, and
  ``terminated`` is that step's);
* ``+ β·r_in(s_t, a_t, s_{t+1})``: ICM's or RE3's bonus, added when the batch is sampled, with the
  current networks and the β schedule (``exploration/intrinsic.py``, ``IntrinsicRewardTransform``); with
  ``exploration.terminal_value`` a terminal transition also gets ``β γ^m mean(r_in) / (1 - γ)``, the bonus
  forgone by ending the episode (so ``(1 - terminated)`` below never makes ending cost the bonus);
* counterfactual transitions (``training/counterfactual.py``) are one-step: ``r`` is the simulator's
  reward of the alternative action (plus the bonus), ``m = 1``, ``terminated`` its collision or goal;
  with ``mode="merged"`` the batch carries ``loss_weight`` and the loss is ``Σ weight·(Q(s, a) - y)²``;
* ``γ^m (1 - terminated) Q_target(s', argmax_a Q(s', a))``: the double-DQN bootstrap, here
  (:meth:`D3QNLoss.bootstrap`); a truncation (timeout) bootstraps;
* ``huber_delta`` (``train.huber_delta``, off by default): the Huber loss of that δ in place of the
  square; the target network is refreshed by hard copies (:meth:`D3QNLoss.update_target`) or, with
  ``train.target_tau < 1``, Polyak steps (:meth:`D3QNLoss.update_target_polyak`).

``DQNLoss`` swaps the target parameters into the online module and routes every pass through
tensordict modules (a cost measured in ``docs/benchmarks.md``); here the target network is a plain
frozen copy.

The math is written once, as functions of the parameters (:meth:`D3QNLoss.bootstrap`,
:meth:`D3QNLoss.objective`, through ``torch.func.functional_call``). ``forward`` evaluates them
with the networks' own parameters (the reference: ``loss.backward()`` then gives the
gradients); :meth:`D3QNLoss.loss_and_grad` returns the loss and writes the gradients, and with
``compile=True`` it runs the target, the three forward passes and the backward pass as **one**
``torch.compile`` graph (``torch.func.grad_and_value`` of the same objective): inductor fuses
across forward and backward, and the autograd engine, the per-call guards of separate compiled
forwards and the input gradients nobody needs are gone (``experiments/bench_train.py --loss
eager compiled`` measures it; tests keep both paths equal to float tolerance). Compiled on first
use and cached on disk by inductor; falls back to eager with a warning if compilation fails.
"""

from __future__ import annotations

import copy
from typing import NamedTuple, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torch.func import functional_call, grad_and_value
from torchrl.objectives import LossModule

from crowdrl.compile import CPP_WRAPPER, LazyCompiled


WEIGHT_KEY = "loss_weight"  # optional [batch] weights of a batch's squared TD errors (they sum to 1)


class D3QNBatch(NamedTuple):
    """The tensors of a sampled batch that the loss reads: ``n`` states, ``g`` transitions from each.

    A sampled batch has ``g = 1``; a batch of ``k`` alternative actions from each of ``n`` states
    (counterfactual experience, a tensordict shaped ``[n, k]``) has ``g = k``, and each state is
    encoded once for its ``k`` Q values.
    """

    obs: tuple[Tensor, ...]  # [n, ...]: the states
    next_obs: tuple[Tensor, ...]  # [n * g, ...]: the bootstrap states, row i * g + j
    action: Tensor  # [n, g] int64 action indices
    reward: Tensor  # [n, g]
    terminated: Tensor  # [n, g] bool
    steps: Tensor  # [n, g] int64: m, the steps to the bootstrap state (the discount is γ^m)
    weight: Tensor | None = None  # [n, g]: the loss is sum weight·(Q - y)² (None: the mean)


class D3QNLoss(LossModule):
    """Double DQN loss for a Q network ``net(*obs) -> [batch, num_actions]``.

    ``obs_keys`` name the network's inputs in the sampled tensordict (and under ``"next"``);
    ``"action"`` is an integer index (``[batch]`` or ``[batch, 1]``) or a one-hot ``[batch,
    num_actions]``. ``double=False`` bootstraps with ``max_a Q_target(s', a)`` instead.
    ``compile=True`` compiles :meth:`loss_and_grad` into one graph (see the module docstring).

    Example::

        loss = D3QNLoss(net, ["robot_rc", "humans_rc"], gamma=0.9)
        out = loss.loss_and_grad(batch)      # gradients now in net's .grad
        optimizer.step()
    """

    def __init__(self, net: nn.Module, obs_keys: Sequence[str], gamma: float, double: bool = True,
                 compile: bool = False, huber_delta: float | None = None) -> None:
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        if huber_delta is not None and not huber_delta > 0:
            raise ValueError(f"huber_delta must be > 0 or None, got {huber_delta}")
        if not obs_keys:
            raise ValueError("obs_keys must name at least one observation key")
        super().__init__()
        self.net = net
        self.target_net = copy.deepcopy(net).requires_grad_(False)
        self.obs_keys = list(obs_keys)
        self.gamma = float(gamma)
        self.double = bool(double)
        self.compile = bool(compile)
        self.huber_delta = None if huber_delta is None else float(huber_delta)
        self._num_actions: int | None = None
        self._gradients_fn = LazyCompiled(self.gradients, dynamic=False, what="the D3QN update", options=CPP_WRAPPER,
                                          enabled=self.compile)

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

    @torch.no_grad()
    def update_target_polyak(self, tau: float) -> None:
        """Move the target parameters towards the online ones: ``θ' ← θ' + τ (θ - θ')``; buffers are copied."""
        if not 0.0 < tau <= 1.0:
            raise ValueError(f"tau must lie in (0, 1], got {tau}")
        for dst, src in zip(self.target_net.parameters(), self.net.parameters()):
            dst.lerp_(src, tau)
        for dst, src in zip(self.target_net.buffers(), self.net.buffers()):
            dst.copy_(src)

    # ------------------------------------------------------------------ the batch
    def _obs(self, td: TensorDictBase, prefix: tuple = ()) -> tuple[Tensor, ...]:
        out = []
        for key in self.obs_keys:
            full = (*prefix, key) if prefix else key
            value = td.get(full, None)
            if value is None:
                raise KeyError(f"D3QNLoss: key {full!r} missing from the batch (keys: {list(td.keys(True))})")
            out.append(value)
        return tuple(out)

    def batch(self, td: TensorDictBase, num_actions: int | None = None) -> D3QNBatch:
        """The loss's tensors from a sampled tensordict; actions are checked against ``num_actions``.

        A tensordict shaped ``[n, g]`` holds ``g`` transitions from each of ``n`` states (its
        observations equal along the second dimension: the first is read)."""
        obs, next_obs = self._obs(td), self._obs(td, ("next",))
        n = td.batch_size[0] if td.batch_dims else obs[0].shape[0]
        g = 1
        if td.batch_dims == 2:
            g = td.batch_size[1]
            obs = tuple(o[:, 0] for o in obs)
            next_obs = tuple(o.reshape(n * g, *o.shape[2:]) for o in next_obs)
        elif td.batch_dims > 2:
            raise ValueError(f"D3QNLoss: a batch has one or two dimensions, got {tuple(td.batch_size)}")
        action = td.get("action")
        if action.dtype == torch.bool or (num_actions is not None and num_actions > 1
                                          and action.dim() > max(td.batch_dims, 1) and action.shape[-1] == num_actions):
            index = action.to(torch.int64).argmax(-1).reshape(n, g)  # one-hot
        else:
            index = action.reshape(n, g).to(torch.int64)
        if num_actions is not None and bool(((index < 0) | (index >= num_actions)).any()):
            raise ValueError(f"actions must lie in 0..{num_actions - 1}")
        steps = td.get("steps_to_next_obs", None)
        steps = torch.ones(n, g, dtype=torch.int64, device=index.device) if steps is None else steps.reshape(n, g)
        weight = td.get(WEIGHT_KEY, None)
        return D3QNBatch(obs, next_obs, index, td.get(("next", "reward")).reshape(n, g),
                         td.get(("next", "terminated")).reshape(n, g), steps,
                         None if weight is None else weight.reshape(n, g).to(obs[0].dtype))

    def num_actions(self, td: TensorDictBase) -> int:
        """Q-values per state (from one cheap forward pass: probes the network on one row)."""
        if self._num_actions is None:
            with torch.no_grad():
                self._num_actions = int(self.net(*(o[:1] for o in self._obs(td))).shape[-1])
        return self._num_actions

    # ------------------------------------------------------------------ the math (functions of the parameters)
    @staticmethod
    def _q(net: nn.Module, params: dict[str, Tensor] | None, obs: tuple[Tensor, ...]) -> Tensor:
        """``net``'s Q values with ``params`` swapped in (``None``: its own parameters, called directly,
        which skips ``functional_call``'s module walk)."""
        return net(*obs) if params is None else functional_call(net, params, obs)

    @staticmethod
    def online_state_dict(loss_state: dict[str, Tensor]) -> dict[str, Tensor]:
        """The online network's ``state_dict`` inside this loss's ``state_dict`` (a training
        checkpoint's ``"loss"`` entry), for loading into a fresh network."""
        return {k[len("net."):]: v for k, v in loss_state.items() if k.startswith("net.")}

    def online_params(self) -> dict[str, Tensor]:
        return dict(self.net.named_parameters())

    def target_params(self) -> dict[str, Tensor]:
        return dict(self.target_net.named_parameters())

    @torch.no_grad()
    def bootstrap(self, params: dict[str, Tensor] | None, target_params: dict[str, Tensor] | None,
                  b: D3QNBatch) -> Tensor:
        """The n-step double-DQN target ``y`` ``[n, g]`` (no gradient); ``None`` params: the networks' own.

        The ``n·g`` bootstrap states are evaluated ``n`` rows at a time (``g`` chunks; a sampled batch is
        one), target then online network on each chunk: each row's value is the same, and a grouped
        batch's passes keep the working set of a sampled batch's (on CPU ~20 % faster at ``g = 5``,
        docs/benchmarks.md, than both networks on all ``n·g`` rows in one graph)."""
        n = b.action.shape[0]
        boot = []
        for chunk in zip(*(o.split(n) for o in b.next_obs)):
            q_target = self._q(self.target_net, target_params, chunk)
            if self.double:
                best = self._q(self.net, params, chunk).argmax(-1, keepdim=True)
                boot.append(q_target.gather(-1, best).squeeze(-1))
            else:
                boot.append(q_target.amax(-1))
        value = (boot[0] if len(boot) == 1 else torch.cat(boot)).reshape(b.action.shape)
        return b.reward + self.gamma ** b.steps.to(value.dtype) * value * (~b.terminated)

    def objective(self, params: dict[str, Tensor] | None, b: D3QNBatch, y: Tensor
                  ) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        """``mean (Q_params(s, a) - y)²`` (``sum weight·(Q - y)²`` for a weighted batch; with ``huber_delta``
        the Huber loss of the difference in place of its square) and, detached, ``(mean Q(s, a), mean |Q(s, a) - y|)``."""
        q = self._q(self.net, params, b.obs).gather(-1, b.action)  # [n, g]: each state encoded once
        diff = q - y
        if self.huber_delta is None:
            per = diff.pow(2)
        else:
            per = torch.nn.functional.huber_loss(q, y, reduction="none", delta=self.huber_delta)
        loss = per.mean() if b.weight is None else (b.weight * per).sum()
        return loss, (q.detach().mean(), diff.detach().abs().mean())

    def gradients(self, params: dict[str, Tensor], target_params: dict[str, Tensor], b: D3QNBatch
                  ) -> tuple[dict[str, Tensor], Tensor, tuple[Tensor, Tensor]]:
        """``(d loss / d params, loss, (q_mean, td_error_abs))``: what :meth:`loss_and_grad` compiles."""
        y = self.bootstrap(params, target_params, b)
        grads, (loss, aux) = grad_and_value(self.objective, has_aux=True)(params, b, y)
        return grads, loss, aux

    # ------------------------------------------------------------------ the two faces
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        b = self.batch(tensordict, self.num_actions(tensordict))
        y = self.bootstrap(None, None, b)
        loss, (q_mean, td_abs) = self.objective(None, b, y)
        return TensorDict({"loss": loss, "q_mean": q_mean, "td_error_abs": td_abs}, [])

    def loss_and_grad(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The loss on ``tensordict`` (detached) with its gradients written into the online
        network's ``.grad`` (replacing what was there): one compiled graph with ``compile=True``,
        ``forward`` + ``backward`` otherwise. Then step the optimiser."""
        if not self.compile or not self._gradients_fn.enabled:
            for p in self.net.parameters():
                p.grad = None
            out = self(tensordict)
            out["loss"].backward()
            return out.apply(torch.Tensor.detach)
        b = self.batch(tensordict, self.num_actions(tensordict))
        params = {k: v.detach() for k, v in self.online_params().items()}
        grads, loss, (q_mean, td_abs) = self._gradients_fn(params, self.target_params(), b)
        for name, p in self.net.named_parameters():
            p.grad = grads[name]
        return TensorDict({"loss": loss, "q_mean": q_mean, "td_error_abs": td_abs}, [])


__all__ = ["D3QNBatch", "D3QNLoss", "WEIGHT_KEY"]
