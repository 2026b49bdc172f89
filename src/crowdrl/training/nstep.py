"""n-step returns for a replay buffer, computed when a collected batch is written.

For each transition ``t`` of a ``[B, T]`` collector batch the window ``t .. t+m-1`` runs for
``m <= n`` steps: it stops after the first step that ends an episode (terminated *or*
truncated) and at the end of the batch. The stored transition then holds

* ``("next", "reward")`` = ``sum_{k<m} gamma**k r_{t+k}``,
* ``("next", obs)`` = the observation after step ``t+m-1`` (the real final observation when the
  window ended with the episode),
* ``("next", "terminated")`` = whether step ``t+m-1`` terminated the episode, so a target never
  bootstraps through a collision or a goal inside the window (a truncation still bootstraps),
* ``"steps_to_next_obs"`` = ``m``, which TorchRL's value estimators read as ``gamma**m``.

Windows cut by the batch end are shorter, never wrong. ``n = 1`` leaves every transition as
collected (plus ``steps_to_next_obs = 1``).

With ``one_step_key`` set (e.g. ``"one_step_next"``), the one-step successor ``s_{t+1}`` is kept
under ``(one_step_key, obs)`` for every observation key: intrinsic rewards (ICM's forward
model, RE3's embedding of ``s'``) are defined on single transitions even when the target is n-step.
"""

from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from torchrl.envs import Transform


def nstep_transitions(batch: TensorDictBase, n: int, gamma: float, obs_keys: Sequence[str],
                      one_step_key: str | None = None) -> TensorDictBase:
    """Rewrite a ``[B, T]`` batch (time last) into n-step transitions; see the module docstring."""
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"n (n-step) must be an integer >= 1, got {n!r}")
    if not 0.0 < gamma <= 1.0:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
    if batch.batch_dims != 2:
        raise ValueError(f"expected a [B, T] batch, got batch_size {tuple(batch.batch_size)}")
    nxt = batch.get("next")
    for key in ("reward", "done", "terminated"):
        if key not in nxt.keys():
            raise KeyError(f"n-step returns need ('next', {key!r}) in the batch")
    B, T = batch.batch_size
    reward = nxt.get("reward").squeeze(-1)  # [B, T]
    done = nxt.get("done").squeeze(-1)
    terminated = nxt.get("terminated").squeeze(-1)

    out = batch.clone(False)
    out_next = out.get("next").clone(False)
    if one_step_key is not None:
        for key in obs_keys:
            out.set((one_step_key, key), nxt.get(key))
    if n == 1:
        out.set("steps_to_next_obs", torch.ones(B, T, 1, dtype=torch.int64, device=batch.device))
        return out

    times = torch.arange(T, device=batch.device)
    ret = torch.zeros_like(reward)
    open_ = torch.ones(B, T, dtype=torch.bool, device=batch.device)  # window still running at step k
    last = times.expand(B, T).clone()  # index of the window's last step
    for k in range(n):
        idx = (times + k).clamp(max=T - 1)
        inside = open_ & (times + k < T).expand(B, T)
        ret = ret + torch.where(inside, (gamma ** k) * reward[:, idx], 0.0)
        last = torch.where(inside, (times + k).expand(B, T), last)
        open_ = inside & ~done[:, idx]
    steps = last - times + 1

    gather = last  # [B, T]
    out_next.set("reward", ret.unsqueeze(-1).to(nxt.get("reward").dtype))
    out_next.set("terminated", torch.gather(terminated, 1, gather).unsqueeze(-1))
    out_next.set("done", torch.gather(done, 1, gather).unsqueeze(-1))
    if "truncated" in nxt.keys():
        out_next.set("truncated", torch.gather(nxt.get("truncated").squeeze(-1), 1, gather).unsqueeze(-1))
    rows = torch.arange(B, device=batch.device).unsqueeze(-1).expand(B, T)
    for key in obs_keys:
        out_next.set(key, nxt.get(key)[rows, gather])
    out.set("next", out_next)
    out.set("steps_to_next_obs", steps.unsqueeze(-1))
    return out


class NStepReturn(Transform):
    """Replay-buffer transform: ``extend`` with ``[B, T]`` batches stores n-step transitions.

    Put it in a ``TensorDictReplayBuffer(transform=...)``; its ``inv`` runs at ``extend`` and
    the output is flattened to ``[B * T]`` transitions.
    """

    def __init__(self, n: int, gamma: float, obs_keys: Sequence[str], one_step_key: str | None = None) -> None:
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ValueError(f"n (n-step) must be an integer >= 1, got {n!r}")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        super().__init__(in_keys=[], out_keys=[])
        self.n, self.gamma, self.obs_keys = int(n), float(gamma), list(obs_keys)
        self.one_step_key = one_step_key

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return nstep_transitions(tensordict, self.n, self.gamma, self.obs_keys, self.one_step_key).reshape(-1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict
