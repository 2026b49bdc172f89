"""The robot's lidar scan as tokens beside the human tokens (``encoder.lidar``).

A scan ``[*, R]`` (metres, ray 0 along the heading, counter-clockwise: already egocentric,
:mod:`crowdrl.sim.lidar`) is divided by its range, read by a small network and turned into
``num_tokens`` tokens of the encoder's token width, which the Q network appends to the human (or
entity) tokens as present entities: every encoder reads them as it reads the crowd, so one option
serves all four encoders.

* ``mlp``: two hidden layers over the rays.
* ``conv``: two circular 1-D convolutions over the rays (kernel 5, stride 2: the scan wraps around
  the robot), then one hidden layer.

>>> import torch
>>> tokens = ScanTokens("conv", num_rays=72, max_range=4.0, token_dim=5)
>>> tokens(torch.full((3, 72), 4.0)).shape
torch.Size([3, 4, 5])
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

SCAN_KINDS = ("off", "mlp", "conv")  # encoder.lidar: off = the network reads no scan
SCAN_TOKENS = 4  # tokens per scan
SCAN_HIDDEN = 64


class ScanTokens(nn.Module):
    """``scan [*, R] -> tokens [*, num_tokens, token_dim]`` (see the module docstring).

    Args:
        kind: ``"mlp"`` or ``"conv"``.
        num_rays: ``R``, the rays per scan; max_range: the scan's range (readings are divided by it).
        token_dim: the width of the encoder's human (entity) tokens; num_tokens: tokens per scan.
    """

    def __init__(self, kind: str, num_rays: int, max_range: float, token_dim: int, num_tokens: int = SCAN_TOKENS,
                 hidden: int = SCAN_HIDDEN) -> None:
        super().__init__()
        if kind not in SCAN_KINDS[1:]:
            raise ValueError(f"kind: got {kind!r}; allowed: {', '.join(SCAN_KINDS[1:])}")
        if isinstance(num_rays, bool) or int(num_rays) != num_rays or num_rays < 1:
            raise ValueError(f"num_rays: must be an integer >= 1, got {num_rays!r}")
        if not (math.isfinite(max_range) and max_range > 0):
            raise ValueError(f"max_range: must be a finite number > 0, got {max_range!r}")
        self.kind, self.num_rays, self.max_range = kind, int(num_rays), float(max_range)
        self.token_dim, self.num_tokens = int(token_dim), int(num_tokens)
        if kind == "mlp":
            self.body = nn.Sequential(nn.Linear(self.num_rays, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())
        else:
            width = math.ceil(math.ceil(self.num_rays / 2) / 2)  # two stride-2 convolutions with "same" padding
            self.body = nn.Sequential(
                nn.Unflatten(-1, (1, self.num_rays)),
                nn.Conv1d(1, 8, 5, stride=2, padding=2, padding_mode="circular"), nn.ReLU(),
                nn.Conv1d(8, 16, 5, stride=2, padding=2, padding_mode="circular"), nn.ReLU(),
                nn.Flatten(), nn.Linear(16 * width, hidden), nn.ReLU())
        self.out = nn.Linear(hidden, self.num_tokens * self.token_dim)

    def forward(self, scan: Tensor) -> Tensor:
        if scan.shape[-1] != self.num_rays:
            raise ValueError(f"lidar: expected {self.num_rays} rays in the last dimension, got {tuple(scan.shape)}")
        lead = scan.shape[:-1]
        x = (scan / self.max_range).reshape(-1, self.num_rays)
        return self.out(self.body(x)).reshape(*lead, self.num_tokens, self.token_dim)


def with_scan_tokens(tokens: Tensor, mask: Tensor | None, scan_tokens: Tensor) -> tuple[Tensor, Tensor]:
    """The crowd's ``tokens [*, N, D]`` and ``mask [*, N]`` (``None``: every one present) with the scan's
    ``[*, T, D]`` appended as present tokens: ``([*, N+T, D], [*, N+T])``."""
    lead, n, t = tokens.shape[:-2], tokens.shape[-2], scan_tokens.shape[-2]
    if mask is None:
        mask = torch.ones((*lead, n), dtype=torch.bool, device=tokens.device)
    present = torch.ones((*lead, t), dtype=torch.bool, device=tokens.device)
    return torch.cat((tokens, scan_tokens.to(tokens.dtype)), -2), torch.cat((mask, present), -1)


__all__ = ["SCAN_KINDS", "SCAN_TOKENS", "ScanTokens", "with_scan_tokens"]
