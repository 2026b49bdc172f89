"""Q network = registered encoder + dueling head, and its TorchRL ``QValueActor``."""

from __future__ import annotations

from typing import Sequence

from tensordict.nn import TensorDictModule
from torch import Tensor, nn
from torchrl.data import Categorical
from torchrl.modules import QValueActor

from crowdrl.models.dueling import DuelingHead
from crowdrl.models.registry import make_encoder
from crowdrl.models.scan import ScanTokens, with_scan_tokens


class CrowdQNetwork(nn.Module):
    """``(robot_rc [*, 9], humans_rc [*, N, 5], humans_mask [*, N]?, lidar [*, R]?) -> Q [*, num_actions]``:
    ``head(encoder(...))``; with ``scan`` (:class:`~crowdrl.models.scan.ScanTokens`) the last input is the lidar
    scan, whose tokens the encoder reads beside the humans' (as present tokens)."""

    def __init__(self, encoder: nn.Module, head: nn.Module, scan: ScanTokens | None = None) -> None:
        super().__init__()
        enc_dim = getattr(encoder, "embedding_dim", None)
        head_dim = getattr(head, "embedding_dim", None)
        if enc_dim is not None and head_dim is not None and enc_dim != head_dim:
            raise ValueError(f"encoder embedding_dim {enc_dim} != head embedding_dim {head_dim}")
        self.encoder = encoder
        self.head = head
        self.scan = scan

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, *rest: Tensor) -> Tensor:
        """``rest``: ``humans_mask [*, N]`` (bool, True = present), passed to the encoder when given, then (with a
        scan network) ``lidar [*, R]``."""
        if self.scan is not None:
            if not rest:
                raise ValueError("this Q network reads the lidar scan: call it as net(robot_rc, humans_rc[, humans_mask], lidar)")
            *rest, lidar = rest
            humans_rc, mask = with_scan_tokens(humans_rc, rest[0] if rest else None, self.scan(lidar))
            return self.head(self.encoder(robot_rc, humans_rc, mask))
        if len(rest) > 1:
            raise ValueError(f"net(robot_rc, humans_rc[, humans_mask]): got {2 + len(rest)} inputs; this network reads no scan")
        if not rest or rest[0] is None:
            return self.head(self.encoder(robot_rc, humans_rc))
        return self.head(self.encoder(robot_rc, humans_rc, rest[0]))


def make_q_network(encoder_name: str = "sgd3qn", num_actions: int = 81, hidden: int = 128,
                   head_layer_norm: bool = False, lidar: str = "off", lidar_rays: int = 0, lidar_range: float = 4.0,
                   **encoder_kwargs) -> CrowdQNetwork:
    """A :class:`CrowdQNetwork` with the registered encoder ``encoder_name`` and a :class:`DuelingHead`
    (with LayerNorm in its hidden layers when ``head_layer_norm``); ``lidar`` ``"mlp"`` or ``"conv"``: it reads
    a scan of ``lidar_rays`` rays clipped at ``lidar_range`` too (:class:`~crowdrl.models.scan.ScanTokens`, built
    after the encoder and the head: their initial weights are those of the network without it)."""
    encoder = make_encoder(encoder_name, **encoder_kwargs)
    head = DuelingHead(encoder.embedding_dim, num_actions=num_actions, hidden=hidden, layer_norm=head_layer_norm)
    scan = None
    if lidar != "off":
        token_dim = int(getattr(encoder, "human_dim", encoder_kwargs.get("human_dim", 5)))
        scan = ScanTokens(lidar, lidar_rays, lidar_range, token_dim)
    return CrowdQNetwork(encoder, head, scan)


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
