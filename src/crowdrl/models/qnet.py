"""Q network = registered encoder + dueling head, and its TorchRL ``QValueActor``."""

from __future__ import annotations

from typing import Sequence

from tensordict.nn import TensorDictModule
from torch import Tensor, nn
from torchrl.data import Categorical
from torchrl.modules import QValueActor

from crowdrl.models.dueling import DuelingHead
from crowdrl.models.registry import make_encoder


class CrowdQNetwork(nn.Module):
    """``(robot_rc [*, 9], humans_rc [*, N, 5], humans_mask [*, N]?) -> Q [*, num_actions]``: ``head(encoder(...))``."""

    def __init__(self, encoder: nn.Module, head: nn.Module) -> None:
        super().__init__()
        enc_dim = getattr(encoder, "embedding_dim", None)
        head_dim = getattr(head, "embedding_dim", None)
        if enc_dim is not None and head_dim is not None and enc_dim != head_dim:
            raise ValueError(f"encoder embedding_dim {enc_dim} != head embedding_dim {head_dim}")
        self.encoder = encoder
        self.head = head

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        """``humans_mask [*, N]`` (bool, True = present) is passed to the encoder when given."""
        if humans_mask is None:
            return self.head(self.encoder(robot_rc, humans_rc))
        return self.head(self.encoder(robot_rc, humans_rc, humans_mask))


def make_q_network(encoder_name: str = "sgd3qn", num_actions: int = 81, hidden: int = 128,
                   head_layer_norm: bool = False, **encoder_kwargs) -> CrowdQNetwork:
    """A :class:`CrowdQNetwork` with the registered encoder ``encoder_name`` and a :class:`DuelingHead`
    (with LayerNorm in its hidden layers when ``head_layer_norm``)."""
    encoder = make_encoder(encoder_name, **encoder_kwargs)
    head = DuelingHead(encoder.embedding_dim, num_actions=num_actions, hidden=hidden, layer_norm=head_layer_norm)
    return CrowdQNetwork(encoder, head)


def make_q_actor(
    encoder_name: str,
    action_spec: Categorical,
    in_keys: Sequence[str] = ("robot_rc", "humans_rc"),
    net: nn.Module | None = None,
    **encoder_kwargs,
) -> QValueActor:
    """A ``QValueActor`` reading ``in_keys`` and writing ``"action_value"`` ``[*, n]``, the greedy
    integer ``"action"`` and ``"chosen_action_value"``.

    ``action_spec`` is the unbatched ``Categorical(n)`` action spec (a batched env spec such as
    ``CrowdNavEnv.action_spec`` ``[B]`` is reduced to its unbatched form). The Q network is the
    actor's ``module[0].module`` (a :class:`CrowdQNetwork`); pass ``net`` to wrap a network
    built elsewhere (e.g. with a noisy or dropout head) instead of a fresh one.
    """
    if not isinstance(action_spec, Categorical):
        raise TypeError(f"action_spec must be a torchrl Categorical, got {type(action_spec).__name__}")
    num_actions = int(action_spec.n)
    if action_spec.shape != ():
        action_spec = Categorical(num_actions, dtype=action_spec.dtype, device=action_spec.device)
    if net is None:
        net = make_q_network(encoder_name, num_actions=num_actions, **encoder_kwargs)
    module = TensorDictModule(net, in_keys=list(in_keys), out_keys=["action_value"])
    return QValueActor(module, in_keys=list(in_keys), spec=action_spec)
