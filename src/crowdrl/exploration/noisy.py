"""Noisy-net exploration for the head of a Q-network (Fortunato et al. 2018).

:func:`noisify_head` turns every plain ``nn.Linear`` of a module (any ``nn.Module``; crowdrl's
trainer passes the dueling head of its Q-network, see ``docs/mdp.md``, "Exploration variants")
into a :class:`FactorisedNoisyLinear`: ``w = mu_w + sigma_w * f(eps_out) f(eps_in)^T``,
``b = mu_b + sigma_b * f(eps_out)``, ``f(x) = sign(x) sqrt|x|``, ``eps ~ N(0, 1)``; whatever is
outside that module (e.g. the encoder) stays deterministic, and ε-greedy is not used (ε = 0).

When the noise is on, and why:

* **collection** — on, one noise sample shared by all ``B`` envs and all steps of a collected
  batch. The paper acts with a fixed sample between two optimisation steps, and here the
  updates run between collected batches, so "resample once per collected batch" is the paper's
  cadence (per-step resampling would need a hook inside the collector and buys nothing here).
* **loss** — on, with independent samples for the online network (``Q(s, ·)`` and the double-DQN
  argmax at ``s'``) and the target network (``Q⁻(s', ·)``), both resampled before every update
  (NoisyNet-DQN / Rainbow). The noise must be on in the loss, otherwise ``sigma`` never gets a
  gradient and never learns to shrink.
* **target network** — its own noise sample, resampled every update (above).
* **evaluation / validation / test** — off: the mean weights ``mu`` (greedy policy).

Gating. A layer adds noise iff it is in training mode **and** its ``noise_enabled`` flag is set
(:func:`set_noise`, :func:`noise_disabled`); ``module.eval()`` (used by torchrl's ``Evaluator``
and :func:`crowdrl.training.pipeline.evaluate_best`) therefore also turns it off. torchrl's own
:class:`~torchrl.modules.NoisyLinear` is gated by the exploration type by default, and
``LossModule.forward`` sets ``ExplorationType.DETERMINISTIC``: with the stock layer the DQN loss
would see the mean weights only and ``sigma`` would receive no gradient. Hence the subclass.

Initialisation. torchrl's layer initialises ``sigma_w = std_init / sqrt(in_features)`` (the
paper's ``σ0 / sqrt(p)``) but ``sigma_b = std_init / sqrt(out_features)``; the paper sets every
``σ`` to ``σ0 / sqrt(p)``, ``p`` = number of inputs, which the subclass does for the bias too
(it matters for narrow outputs: the value stream's ``128 -> 1`` bias would start at σ 0.5
instead of 0.044). ``mu ~ U[-1/sqrt(p), 1/sqrt(p)]`` as in torchrl and the paper.

Online vs target copies. The noise samples ``weight_epsilon``/``bias_epsilon`` are buffers, so
``state_dict``/``load_state_dict`` carry them (a checkpoint round trip restores them exactly).
:func:`reset_noise` on crowdrl's loss (``crowdrl.training.loss.D3QNLoss``: ``net`` and
``target_net`` child modules) walks both copies, each getting its own sample. On a torchrl
``LossModule`` it also reaches what that keeps outside its child modules: the online network and
the epsilons of each ``target_<name>_params`` (torchrl's ``HardUpdate`` copies parameters only,
and ``loss.apply(reset_noise)`` reaches neither), so the target noise is a fresh sample every
update there too.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ContextManager, Iterator, TypeVar

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import NoisyLinear

from crowdrl.exploration._surgery import replace_children
from crowdrl.exploration.strategy import ExplorationStrategy, register_strategy

M = TypeVar("M", bound=nn.Module)


class FactorisedNoisyLinear(NoisyLinear):
    """torchrl's factorised :class:`~torchrl.modules.NoisyLinear` with the paper's bias ``σ``
    init (``σ0 / sqrt(in_features)``) and noise gated by ``self.training and self.noise_enabled``
    instead of the torchrl exploration type (which the DQN loss sets to deterministic)."""

    def __init__(self, in_features: int, out_features: int, bias: bool = True, sigma0: float = 0.5,
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> None:
        if not sigma0 >= 0:
            raise ValueError(f"sigma0 must be >= 0, got sigma0={sigma0}")
        super().__init__(in_features, out_features, bias=bias, device=device, dtype=dtype, std_init=sigma0,
                         use_exploration_type=False)
        self.noise_enabled = True

    def reset_parameters(self) -> None:
        super().reset_parameters()
        if self.bias_mu is not None:
            self.bias_sigma.data.fill_(self.std_init / math.sqrt(self.in_features))

    def _should_use_noise(self) -> bool:
        return self.training and self.noise_enabled

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, sigma0={self.std_init}, noise_enabled={self.noise_enabled}"


def noisify_head(head: M, sigma0: float = 0.5) -> M:
    """Replace, in place, every plain ``nn.Linear`` under ``head`` (any module; e.g. the 6 layers of
    crowdrl's dueling head: trunk, value and advantage) by a freshly initialised
    :class:`FactorisedNoisyLinear` of the same shape, dtype and device; returns ``head``.

    Call it before building the loss and the optimiser (they capture the parameters). The
    ``state_dict`` keys of the replaced layers change (``weight`` -> ``weight_mu``, ...). Only
    ``nn.Linear`` child modules are seen (not subclasses, not ``F.linear`` calls); a ``head`` with
    none is a ``ValueError``.
    """
    if not sigma0 >= 0:
        raise ValueError(f"sigma0 must be >= 0, got sigma0={sigma0}")

    def noisy(layer: nn.Module) -> nn.Module:
        w = layer.weight
        return FactorisedNoisyLinear(layer.in_features, layer.out_features, bias=layer.bias is not None,
                                     sigma0=sigma0, device=w.device, dtype=w.dtype)

    replaced = replace_children(head, lambda m: type(m) is nn.Linear, noisy)
    if replaced == 0:
        raise ValueError(f"{type(head).__name__} has no plain nn.Linear child module to make noisy "
                         "(already noisy, or no nn.Linear layers?)")
    return head


def noisy_layers(module: nn.Module) -> list[NoisyLinear]:
    """The noisy layers of ``module``'s tree; for a torchrl ``LossModule`` also those of the
    networks it keeps outside its child modules (e.g. ``DQNLoss.value_network``)."""
    seen: dict[int, NoisyLinear] = {}
    for root in (module, *_functional_networks(module)):
        for m in root.modules():
            if isinstance(m, NoisyLinear):
                seen.setdefault(id(m), m)
    return list(seen.values())


def _functional_networks(module: nn.Module) -> list[nn.Module]:
    # torchrl's LossModule.convert_to_functional stores `loss.<name>` in __dict__ (not a child)
    return [v for k, v in vars(module).items() if isinstance(v, nn.Module) and k not in module._modules]


@torch.no_grad()
def reset_noise(module: nn.Module) -> None:
    """Resample the factorised noise of every noisy layer under ``module``.

    For a torchrl ``LossModule`` (e.g. ``DQNLoss(delay_value=True)``) this resamples the online
    network's noise and, independently, the noise stored in each ``target_<name>_params`` (which
    neither ``HardUpdate`` nor ``loss.apply(reset_noise)`` would refresh).
    """
    for layer in noisy_layers(module):
        layer.reset_noise()
    for name, net in vars(module).items():
        target = module._modules.get(f"target_{name}_params") if isinstance(net, nn.Module) else None
        if isinstance(target, TensorDictBase):
            # load the target tensors into the network and resample its epsilon buffers in place
            with target.to_module(net):
                for layer in noisy_layers(net):
                    layer.reset_noise()


def _gated_layers(module: nn.Module) -> list[FactorisedNoisyLinear]:
    return [layer for layer in noisy_layers(module) if isinstance(layer, FactorisedNoisyLinear)]


def set_noise(module: nn.Module, enabled: bool) -> None:
    """Switch the noise of every :class:`FactorisedNoisyLinear` under ``module`` on (``True``) or
    off (``False``: mean weights). It stays off in ``eval()`` mode whatever the flag."""
    for layer in _gated_layers(module):
        layer.noise_enabled = bool(enabled)


@contextmanager
def noise_disabled(module: nn.Module) -> Iterator[nn.Module]:
    """Evaluate ``module`` with its mean weights; every layer's previous flag is restored after."""
    layers = _gated_layers(module)
    previous = [layer.noise_enabled for layer in layers]
    try:
        for layer in layers:
            layer.noise_enabled = False
        yield module
    finally:
        for layer, flag in zip(layers, previous):
            layer.noise_enabled = flag


class NoisyExploration(ExplorationStrategy):
    """Noisy nets as an exploration strategy: the Q network's ``head`` noisified (``config.sigma0``),
    a fresh noise sample for each collected batch, independent online and target samples before
    each update, the mean weights for greedy evaluation (see the module docstring)."""

    def __init__(self, config: Any) -> None:
        super().__init__(config)
        self.net: nn.Module | None = None

    def modify_network(self, net: nn.Module) -> nn.Module:
        noisify_head(net.head, self.config.sigma0)
        self.net = net
        return net

    def before_collection(self, frames: int) -> None:
        super().before_collection(frames)
        reset_noise(self.net)

    def before_update(self, loss: nn.Module) -> None:
        reset_noise(loss)

    def evaluating(self) -> ContextManager:
        return noise_disabled(self.net)


@dataclass
class NoisyConfig:
    """``exploration=noisy``'s own key: the factorised NoisyLinear's ``σ0``."""

    sigma0: float = 0.5

    @staticmethod
    def check(config: Any, limits: Any, active: bool) -> None:
        if config.sigma0 <= 0:
            raise ValueError(f"sigma0: must be > 0, got {config.sigma0}")


register_strategy("noisy", NoisyExploration, NoisyConfig)

__all__ = [
    "FactorisedNoisyLinear",
    "NoisyExploration",
    "noise_disabled",
    "noisify_head",
    "noisy_layers",
    "reset_noise",
    "set_noise",
]
