"""Running statistics that keep an intrinsic bonus on a fixed scale, as RND does.

* :class:`RunningMeanStd`: exact running mean and variance of a stream, element-wise over an
  event shape (pooled batch moments: the union of all batches seen, in float64).
* :class:`RewardNormalizer`: ``r -> clip((r - mean) / std)``, each part optional: divide by the
  running std (``scale="std"``, RND) or standardise over the batch at hand (``scale="batch"``:
  mean and std of this batch, which follow a bonus whose raw scale drifts, as ICM's falls while its
  forward model learns), subtract the mean (``center=True``: the bonus is then no net per-step
  reward, so it cannot pay the agent for making episodes longer), clip to ``[-clip, clip]``.
* :class:`ObservationNormalizer`: the bonus's *input* observations whitened element-wise by their
  running mean/std and clipped (RND's observation normalisation; a bounded input cannot turn "far
  away" into novelty that never runs out).

Every normaliser folds the batch it is given into its statistics *before* normalising it, so the
first batch is scaled by its own moments. Statistics are buffers (saved in ``state_dict``).

Why not ``torchrl.envs.transforms.RunningMeanStd`` (torchrl 0.14): it starts from a pseudo-count
(``epsilon=1e-4``) at mean 0 and variance 1, so its moments are not those of the stream (far off
for a stream of small variance, docs/benchmarks.md), float32, whereas the tests here hold these
statistics equal to numpy's over everything seen; and its buffers differ from the ones the
checkpoints of intrinsic runs hold.

>>> norm = RewardNormalizer(scale="std", center=True, clip=5.0)
>>> r = norm(torch.tensor([1.0, 2.0, 3.0]))  # zero mean, unit std over what was seen
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

REWARD_SCALES = ("none", "std", "batch")


class RunningMeanStd(nn.Module):
    """Running mean/variance of a stream of tensors shaped ``[*batch, *shape]`` (``shape=()``:
    scalars), exact for the union of the batches (Chan et al.'s pooled update, float64)."""

    def __init__(self, shape: Sequence[int] = ()) -> None:
        super().__init__()
        self.shape = tuple(int(s) for s in shape)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(self.shape, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(self.shape, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: Tensor) -> None:
        """Fold ``x`` (``[*batch, *shape]``) into the statistics."""
        event = len(self.shape)
        if tuple(x.shape[x.dim() - event:]) != self.shape or x.dim() < event:
            raise ValueError(f"RunningMeanStd of shape {self.shape} got a tensor shaped {tuple(x.shape)}")
        x = x.detach().to(self.mean.dtype).reshape(-1, *self.shape)
        n = x.shape[0]
        if n == 0:
            return
        batch_mean = x.mean(0)
        batch_m2 = (x - batch_mean).pow(2).sum(0)
        total = self.count + n
        delta = batch_mean - self.mean
        self.mean.add_(delta * (n / total))
        self.m2.add_(batch_m2 + delta.pow(2) * (self.count * n / total))
        self.count.copy_(total)

    @property
    def var(self) -> Tensor:
        """Population variance (0 before any data)."""
        return self.m2 / self.count.clamp_min(1.0)

    @property
    def std(self) -> Tensor:
        """Population standard deviation (0 before any data)."""
        return self.var.sqrt()




def _check_clip(clip: float | None, name: str) -> float | None:
    if clip is None:
        return None
    clip = float(clip)
    if not clip > 0 or clip != clip or clip == float("inf"):
        raise ValueError(f"{name} must be a finite number > 0 or None, got {clip}")
    return clip


class RewardNormalizer(nn.Module):
    """``r -> clip((r - center * mean) / std)`` with running (or the batch's) statistics of the raw ``r``.

    Args:
        scale: ``"std"`` divides by the running std (floored at ``eps``); ``"batch"`` by the batch's
            std, and ``center`` then subtracts the batch's mean; ``"none"`` keeps the scale.
        center: subtract the mean (running, or the batch's with ``scale="batch"``): a zero-mean bonus.
        clip: clip the result to ``[-clip, clip]`` (``None``: no clip).
    """

    def __init__(self, scale: str = "std", center: bool = False, clip: float | None = None, eps: float = 1e-8) -> None:
        super().__init__()
        if scale not in REWARD_SCALES:
            raise ValueError(f"scale: unknown reward normalisation {scale!r}; allowed: {', '.join(REWARD_SCALES)}")
        self.scale = scale
        self.center = bool(center)
        self.clip = _check_clip(clip, "clip")
        self.eps = float(eps)
        self.stats = RunningMeanStd()

    @property
    def is_identity(self) -> bool:
        return self.scale == "none" and not self.center and self.clip is None

    @torch.no_grad()
    def forward(self, r: Tensor) -> Tensor:
        """Fold ``r`` into the statistics, then return it normalised (same shape and dtype)."""
        self.stats.update(r)
        out = r.to(torch.float64)
        if self.scale == "batch":
            mean, std = out.mean(), out.std(correction=0)
        else:
            mean, std = self.stats.mean, self.stats.std
        if self.center:
            out = out - mean
        if self.scale != "none":
            out = out / std.clamp_min(self.eps)
        if self.clip is not None:
            out = out.clamp(-self.clip, self.clip)
        return out.to(r.dtype)


class ObservationNormalizer(nn.Module):
    """Element-wise running whitening of observation tensors, clipped to ``[-clip, clip]``.

    ``forward(tensors, batch_dims)`` takes a list of tensors (one per observation key, each shaped
    ``[*batch, *event]``); floating-point tensors are whitened by their own running statistics over
    the event shape, others (masks, indices) pass through. The statistics are made on first use
    (their shapes come from the data) and rebuilt by ``load_state_dict``.
    """

    def __init__(self, clip: float = 5.0, eps: float = 1e-8) -> None:
        super().__init__()
        self.clip = _check_clip(clip, "clip")
        self.eps = float(eps)
        self.stats = nn.ModuleDict()

    @torch.no_grad()
    def forward(self, tensors: Sequence[Tensor], batch_dims: int, update: bool = True) -> list[Tensor]:
        out = []
        for i, x in enumerate(tensors):
            if not x.is_floating_point():
                out.append(x)
                continue
            key = str(i)
            if key not in self.stats:
                self.stats[key] = RunningMeanStd(x.shape[batch_dims:]).to(x.device)
            stats = self.stats[key]
            if update:
                stats.update(x)
            y = (x.to(torch.float64) - stats.mean) / stats.std.clamp_min(self.eps)
            if self.clip is not None:
                y = y.clamp(-self.clip, self.clip)
            out.append(y.to(x.dtype))
        return out

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs) -> None:
        # statistics are created on first use: make those the saved state holds before loading them
        head = prefix + "stats."
        for name, value in state_dict.items():
            if name.startswith(head) and name.endswith(".mean"):
                key = name[len(head):-len(".mean")]
                if key not in self.stats:
                    self.stats[key] = RunningMeanStd(value.shape).to(value.device)
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)


__all__ = ["RunningMeanStd", "RewardNormalizer", "ObservationNormalizer", "REWARD_SCALES"]
