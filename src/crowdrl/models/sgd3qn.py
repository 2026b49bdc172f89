"""SG-D3QN's graph attention encoder (``docs/mdp.md``, "Models"), optimised for CPU training.

Architecture (the authors' ``GAT_RL`` with skip connections):

* ``w_r``: Linear(9, 64)-ReLU-Linear(64, 32)-ReLU on the robot state, ``w_h``:
  Linear(5, 64)-ReLU-Linear(64, 32)-ReLU on each human; ``X = [w_r(robot); w_h(humans)]``
  ``[B, N+1, 32]``, the robot being node 0.
* two graph attention layers ``gat0``, ``gat1``, each with the pairwise scoring MLP
  ``w_a`` = Linear(64, 64)-ReLU-Linear(64, 1) on ``[h_i, h_j]``,
  ``e_ij = LeakyReLU_0.04(w_a([h_i, h_j]))``, ``A = masked softmax_j(e)``, ``H' = A H``;
  ``H1 = gat0(X)``, ``H2 = gat1(H1)``.
* output ``X + H1 + H2``; the robot node's row ``[B, 32]`` is the state embedding.

Masking (upstream ``GAT_RL.compute_adjectory_matrix``): the adjacency is all ones except
``adj[i, 0] = 0`` for every human ``i >= 1``, i.e. **humans do not attend to the robot** (the
robot is invisible to the humans, as in the simulator), while the robot row attends to every
node, itself included, and every human attends to itself and to all other humans. Upstream
filled masked logits with ``-9e15`` before the softmax; we use ``-inf``: both give masked
weights of exactly 0, and no row is ever fully masked (every row keeps at least its own node).

Optimisations (the function is the same as :class:`SGD3QNEncoderNaive`'s, which applies the
``nn.Sequential`` MLPs to the concatenated pairs; parameters and ``state_dict`` are shared):

* the first scoring layer is split: ``W [h_i; h_j] + b = W_1 h_i + W_2 h_j + b`` with
  ``W = [W_1 | W_2]``, so the two ``32 -> 64`` products are computed per node, not per pair;
  the pairwise work is a broadcast add (with ``b``), a ReLU and a dot with the ``64 -> 1`` weights, done by
  :class:`_PairwiseScore`, an autograd function whose forward and backward are each one fused
  loop compiled by inductor (:class:`PairwiseKernels`; the ``[B, R, C, 64]`` hidden tensor is
  never stored);
* the softmax over the N+1 nodes is written out (:func:`_softmax_last`), ATen's kernel being
  slow for such short rows;
* only the robot node's output is used, so layer 2 is evaluated for the robot row only
  (``[B, 1, N+1, 64]`` instead of ``[B, N+1, N+1, 64]``); layer 1 is evaluated for all rows,
  since its outputs are layer 2's inputs.
"""

from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from crowdrl.compile import LazyCompiled
from crowdrl.models.mlp import mlp
from crowdrl.models.registry import register_encoder

ROBOT_RC_DIM = 9
HUMAN_RC_DIM = 5
LEAKY_SLOPE = 0.04


class GraphAttentionLayer(nn.Module):
    """Holds one layer's scoring MLP ``w_a``: Linear(2D, 2D)-ReLU-Linear(2D, 1) on ``[h_i, h_j]``."""

    def __init__(self, dim: int = 32) -> None:
        super().__init__()
        self.dim = int(dim)
        self.w_a = nn.Sequential(nn.Linear(2 * dim, 2 * dim), nn.ReLU(), nn.Linear(2 * dim, 1))


def _score_forward(rows: Tensor, cols: Tensor, bias: Tensor, w: Tensor) -> Tensor:
    """``s[..., r, c] = w . relu(rows[..., r, :] + cols[..., c, :] + bias)``."""
    return (torch.relu(rows.unsqueeze(-2) + cols.unsqueeze(-3) + bias) * w).sum(-1)


def _score_backward(rows: Tensor, cols: Tensor, bias: Tensor, w: Tensor, grad: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gradients of :func:`_score_forward` w.r.t. ``rows``, ``cols``, ``bias`` and ``w`` for the output gradient ``grad``."""
    pre = rows.unsqueeze(-2) + cols.unsqueeze(-3) + bias
    g = grad.unsqueeze(-1)
    # summed over the columns first: inductor then fuses it into the loop of grad_rows (same [B, R, K]
    # space) instead of a separate strided pass over [B*R*C, K] (a faster backward; docs/benchmarks.md)
    grad_w = (g * torch.relu(pre)).sum(-2).reshape(-1, w.shape[-1]).sum(0)
    gm = torch.where(pre > 0, g, 0.0)  # d score / d pre-activation, without w
    grad_rows = gm.sum(-2) * w
    return grad_rows, gm.sum(-3) * w, grad_rows.reshape(-1, w.shape[-1]).sum(0), grad_w


class PairwiseKernels:
    """The pairwise score's forward and backward, compiled by inductor into fused loops.

    Eager torch materialises the ``[B, R, C, 64]`` pre-activation several times per pass (add,
    ReLU, product, reduction, and as many again in the backward); inductor fuses each pass into
    one loop nest that never writes it to memory (faster forward and backward on CPU:
    docs/benchmarks.md). Compiled lazily on first use (cached by inductor on disk); the
    forward specialises to its first shape and then compiles one dynamic-shape version, the
    backward specialises to every shape it sees (training uses one or two). ``backend="eager"``
    (or ``CROWDRL_PAIRWISE=eager``) uses the same functions uncompiled; if compilation fails (no
    C++ compiler), it falls back to eager with a warning; inside a compiled network the outer
    graph traces them (:class:`LazyCompiled`). Both compute the same function; tests compare them.
    """

    def __init__(self, backend: str | None = None) -> None:
        backend = backend or os.environ.get("CROWDRL_PAIRWISE", "compiled")
        if backend not in ("compiled", "eager"):
            raise ValueError(f"pairwise backend must be 'compiled' or 'eager', got {backend!r}")
        self.backend = backend
        compiled, hint = backend == "compiled", "set CROWDRL_PAIRWISE=eager to silence"
        self.forward = LazyCompiled(_score_forward, dynamic=None, what="the pairwise attention kernel",
                                    hint=hint, enabled=compiled)
        # static shapes: the dynamic-shape backward kernel is slower (docs/benchmarks.md), and training sees few shapes
        self.backward = LazyCompiled(_score_backward, dynamic=False, what="the pairwise attention kernel",
                                     hint=hint, enabled=compiled)


PAIRWISE = PairwiseKernels()


class _PairwiseScore(torch.autograd.Function):
    """``s[..., r, c] = w . relu(rows[..., r, :] + cols[..., c, :] + bias)``.

    ``rows [B, R, K]``, ``cols [B, C, K]``, ``bias [K]``, ``w [K]`` -> ``[B, R, C]``. The bias is
    added inside the fused loop (as ``addmm`` it would be copied into a ``[B, C, K]`` output first,
    a slow broadcast copy on CPU). Saves only its inputs (the
    ``[B, R, C, K]`` hidden tensor is recomputed inside the fused backward, never stored) and
    runs :data:`PAIRWISE`'s kernels. Not twice differentiable. Written with ``setup_context`` so
    that ``torch.func`` transforms (``grad``, as in the compiled D3QN update) can apply it.
    """

    @staticmethod
    def forward(rows: Tensor, cols: Tensor, bias: Tensor, w: Tensor) -> Tensor:
        # detached: the kernel needs no autograd graph (with inputs that require grad, the compiled
        # kernel would be a second, slower training variant, compiled again)
        return PAIRWISE.forward(rows.detach(), cols.detach(), bias.detach(), w.detach())

    @staticmethod
    def setup_context(ctx, inputs: tuple[Tensor, Tensor, Tensor, Tensor], output: Tensor) -> None:
        ctx.save_for_backward(*inputs)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        # all four, always (autograd drops those not needed; under torch.compile + torch.func.grad,
        # ctx.needs_input_grad reads False for a parameter passed straight in, e.g. the bias)
        return PAIRWISE.backward(*ctx.saved_tensors, grad.contiguous())


def _softmax_last(logits: Tensor) -> Tensor:
    """``softmax(logits, -1)`` for a short last dim (the N+1 nodes).

    Same values and gradient as ``torch.softmax``; cheaper on CPU for rows of ~10, where
    ATen's softmax kernel is slow (docs/benchmarks.md). The max is detached: softmax does not depend on the
    shift, so its gradient through the max is exactly zero.
    """
    e = torch.exp(logits - logits.detach().amax(dim=-1, keepdim=True))
    return e / e.sum(dim=-1, keepdim=True)


def _attend(layer: GraphAttentionLayer, queries: Tensor, nodes: Tensor, mask: Tensor | None) -> Tensor:
    """One attention layer for the rows ``queries [B, R, D]`` over ``nodes [B, C, D]``.

    ``mask`` (bool, True = not attended, broadcastable to ``[B, R, C]``) or ``None``. Same
    function as applying ``layer.w_a`` to every concatenated pair ``[q_r, n_c]``.
    """
    lin1, lin2 = layer.w_a[0], layer.w_a[2]
    d = queries.shape[-1]
    rows = F.linear(queries, lin1.weight[:, :d])
    cols = F.linear(nodes, lin1.weight[:, d:])
    scores = _PairwiseScore.apply(rows, cols, lin1.bias, lin2.weight.reshape(-1)) + lin2.bias
    logits = F.leaky_relu(scores, LEAKY_SLOPE)
    if mask is not None:
        logits = logits.masked_fill(mask, float("-inf"))
    return torch.matmul(_softmax_last(logits), nodes)


def human_mask(num_nodes: int, device: torch.device | None = None) -> Tensor:
    """``[N+1, N+1]`` bool, True where attention is masked: human rows (``i >= 1``), robot column (``j = 0``)."""
    mask = torch.zeros(num_nodes, num_nodes, dtype=torch.bool, device=device)
    mask[1:, 0] = True
    return mask


@register_encoder("sgd3qn")
class SGD3QNEncoder(nn.Module):
    """SG-D3QN graph attention encoder: ``(robot_rc [*, 9], humans_rc [*, N, 5]) -> [*, 32]``.

    Works for any ``N >= 1`` and any leading batch dims (including none). See the module
    docstring for the architecture, the masking convention and the optimisations.
    """

    def __init__(
        self,
        robot_dim: int = ROBOT_RC_DIM,
        human_dim: int = HUMAN_RC_DIM,
        hidden_dim: int = 64,
        embedding_dim: int = 32,
    ) -> None:
        super().__init__()
        self.robot_dim = int(robot_dim)
        self.human_dim = int(human_dim)
        self.embedding_dim = int(embedding_dim)
        self.w_r = mlp([robot_dim, hidden_dim, embedding_dim])
        self.w_h = mlp([human_dim, hidden_dim, embedding_dim])
        self.gat0 = GraphAttentionLayer(embedding_dim)
        self.gat1 = GraphAttentionLayer(embedding_dim)

    def _node_mask(self, mask: Tensor, humans_mask: Tensor | None, humans_rc: Tensor) -> Tensor:
        """``mask [N+1, N+1]`` joined with the absent humans' columns: ``[B, 1, N+1]``-broadcast, or as is."""
        if humans_mask is None:
            return mask
        if humans_mask.dtype != torch.bool or humans_mask.shape != humans_rc.shape[:-1]:
            raise ValueError(f"humans_mask must be a bool tensor shaped {tuple(humans_rc.shape[:-1])}, "
                             f"got {humans_mask.dtype} {tuple(humans_mask.shape)}")
        n = humans_rc.shape[-2]
        absent = torch.cat((torch.zeros_like(humans_mask[..., :1]), ~humans_mask), dim=-1).reshape(-1, 1, n + 1)
        return mask | absent

    def _check(self, robot_rc: Tensor, humans_rc: Tensor) -> tuple[torch.Size, int]:
        if robot_rc.shape[-1:] != (self.robot_dim,):
            raise ValueError(f"robot_rc must be shaped [..., {self.robot_dim}], got {tuple(robot_rc.shape)}")
        if humans_rc.dim() < 2 or humans_rc.shape[-1] != self.human_dim or humans_rc.shape[:-2] != robot_rc.shape[:-1]:
            raise ValueError(
                f"humans_rc must be shaped [..., N, {self.human_dim}] with batch {tuple(robot_rc.shape[:-1])}, "
                f"got {tuple(humans_rc.shape)}"
            )
        if humans_rc.shape[-2] < 1:
            raise ValueError("SGD3QNEncoder needs at least one human")
        return robot_rc.shape[:-1], humans_rc.shape[-2]

    def node_features(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        """``X [B, N+1, D]`` with the batch flattened; the robot is node 0 (absent humans' inputs zeroed)."""
        n = humans_rc.shape[-2]
        humans_rc = humans_rc.reshape(-1, n, self.human_dim)
        if humans_mask is not None:  # whatever padding absent humans hold (even NaN) never reaches a sum
            humans_rc = torch.where(humans_mask.reshape(-1, n, 1), humans_rc, 0.0)
        robot = self.w_r(robot_rc.reshape(-1, 1, self.robot_dim))
        return torch.cat((robot, self.w_h(humans_rc)), dim=1)

    def first_layer(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        """``H1 = gat0(X)`` for every node, ``[B, N+1, D]`` (``mask``: :func:`human_mask`, possibly
        joined with absent humans' columns)."""
        # built per call (two tiny ops; a constant inside a compiled graph): a cache would be a side
        # effect that makes torch.compile recompile
        return _attend(self.gat0, x, x, human_mask(x.shape[-2], x.device) if mask is None else mask)

    def forward(self, robot_rc: Tensor, humans_rc: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        """``humans_mask [*, N]`` (bool, True = present), optional: absent humans are attended by no
        one, so the output equals that of the crowd without them (padding-invariant)."""
        lead, n = self._check(robot_rc, humans_rc)
        mask = self._node_mask(human_mask(n + 1, robot_rc.device), humans_mask, humans_rc)
        x = self.node_features(robot_rc, humans_rc, humans_mask)
        h1 = self.first_layer(x, mask)
        robot_row = None
        if humans_mask is not None:  # the robot row attends to every present node
            robot_row = mask[:, :1]
            # an absent human's row of H1 is never used; zero it so that a crowd with nobody present
            # (every human row fully masked, hence NaN) cannot leak NaN through a zero weight
            h1 = torch.where(robot_row.transpose(-1, -2), 0.0, h1)
        h2_robot = _attend(self.gat1, h1[:, :1], h1, robot_row)
        out = x[:, 0] + h1[:, 0] + h2_robot[:, 0]
        return out.reshape(*lead, self.embedding_dim)

    def node_embeddings(self, robot: Tensor, humans: Tensor, humans_mask: Tensor | None = None) -> Tensor:
        """``X + H1 + H2`` for every node, ``[*, N+1, D]`` (the robot is node 0): the per-human
        outputs a state predictor reads. Row 0 equals :meth:`forward`'s output; the rows of
        absent humans are zeros."""
        lead, n = self._check(robot, humans)
        mask = self._node_mask(human_mask(n + 1, robot.device), humans_mask, humans)
        x = self.node_features(robot, humans, humans_mask)
        h1 = self.first_layer(x, mask)
        if humans_mask is not None:  # as in forward: absent rows of H1 are never attended; zero them
            h1 = torch.where(mask[:, :1].transpose(-1, -2), 0.0, h1)
        out = x + h1 + _attend(self.gat1, h1, h1, mask)
        if humans_mask is not None:
            out = torch.where(mask[:, :1].transpose(-1, -2), 0.0, out)
        return out.reshape(*lead, n + 1, self.embedding_dim)


class SGD3QNEncoderNaive(SGD3QNEncoder):
    """Reference implementation of the same function (same parameters), written as upstream:
    every ``[h_i, h_j]`` pair is concatenated and fed to the ``nn.Sequential`` scoring MLP, and
    both layers are computed for every node. Slow; for tests and benchmarks."""

    @staticmethod
    def _naive_attend(layer: GraphAttentionLayer, h: Tensor, mask: Tensor) -> Tensor:
        m = h.shape[-2]
        pairs = torch.cat((h.unsqueeze(-2).expand(-1, m, m, -1), h.unsqueeze(-3).expand(-1, m, m, -1)), dim=-1)
        logits = F.leaky_relu(layer.w_a(pairs).squeeze(-1), LEAKY_SLOPE)
        logits = logits.masked_fill(mask, float("-inf"))
        return torch.matmul(torch.softmax(logits, dim=-1), h)

    def naive_layers(self, robot_rc: Tensor, humans_rc: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(X, H1, H2)`` for every node, batch flattened."""
        self._check(robot_rc, humans_rc)
        x = self.node_features(robot_rc, humans_rc)
        mask = human_mask(x.shape[-2], x.device)
        h1 = self._naive_attend(self.gat0, x, mask)
        h2 = self._naive_attend(self.gat1, h1, mask)
        return x, h1, h2

    def forward(self, robot_rc: Tensor, humans_rc: Tensor) -> Tensor:
        lead, _ = self._check(robot_rc, humans_rc)
        x, h1, h2 = self.naive_layers(robot_rc, humans_rc)
        return (x + h1 + h2)[:, 0].reshape(*lead, self.embedding_dim)
