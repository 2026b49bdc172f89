"""Intrinsic rewards for off-policy RL, computed when a replay buffer is *sampled*.

:class:`IntrinsicRewardTransform` sits in a ``TensorDictReplayBuffer(transform=...)`` (alone, or
in a ``Compose`` after transforms whose ``inv`` runs at ``extend``). On every sampled batch it
asks an :class:`IntrinsicBonus` (ICM, RE3, ...) for ``r_in`` with the bonus's *current* networks,
so bonuses are never stale, and writes ``r = r_ext + beta * r_in``. The buffer's storage is never
touched: sampling returns a copy, and only that copy is rewritten.

Options that keep a bonus on a fixed scale work with any bonus (:mod:`crowdrl.exploration.normalize`):
``obs_norm`` whitens the bonus's input observations, ``reward_norm`` divides ``r_in`` by a running
std, optionally centres and clips it, and ``terminal_value_gamma`` adds at every terminal
transition the bonus the agent forgoes by ending the episode (see :class:`IntrinsicRewardTransform`).

Nothing here depends on the crowd simulator: any TorchRL env whose transitions carry the
observation keys, the action and ``("next", "reward")`` works.
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Callable, Iterator, Sequence, Union

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.envs import Transform

from crowdrl.exploration.normalize import ObservationNormalizer, RewardNormalizer, RunningMeanStd

Beta = Union[float, Callable[[], float]]


def _as_key(key: NestedKey) -> NestedKey:
    """Nested keys as tuples, plain string keys as strings."""
    if isinstance(key, str):
        return key
    key = tuple(key)
    return key[0] if len(key) == 1 else key


def _check_beta(beta: float, where: str) -> float:
    beta = float(beta)
    if not math.isfinite(beta) or beta < 0.0:
        raise ValueError(f"beta (intrinsic reward scale) must be a finite float >= 0, got {beta} ({where})")
    return beta


class IntrinsicBonus(nn.Module):
    """Base class of intrinsic-reward models.

    ``in_keys`` is a sequence of keys (a single string is one key; a nested key must be wrapped,
    e.g. ``[("agent", "obs")]``), in the order the feature encoder takes them as arguments.

    Both methods take a flat-layout tensordict with batch dims ``[*B]``: the observation of ``s``
    under each key of :attr:`in_keys`, the observation of ``s'`` under ``("next", key)`` and the
    action under ``"action"``. :class:`IntrinsicRewardTransform` builds that layout from whatever
    keys the buffer uses.

    * :meth:`bonus` returns ``r_in`` shaped ``[*B]``, without gradients, computed with the
      current networks;
    * :meth:`update` takes one training step on the batch and returns scalars to log (a no-op
      returning ``{}`` for models that do not learn).
    * :meth:`bonus_then_step` returns the bonus and that step as a callable to run later (ICM: one
      pass through its networks for both).
    """

    def __init__(self, in_keys: Sequence[NestedKey]) -> None:
        super().__init__()
        if isinstance(in_keys, str):
            in_keys = [in_keys]
        in_keys = [_as_key(k) for k in in_keys]
        if not in_keys:
            raise ValueError("an intrinsic bonus needs at least one observation key")
        self.in_keys: list[NestedKey] = in_keys

    def obs(self, td: TensorDictBase, next_: bool = False) -> list[Tensor]:
        """The observation tensors of ``s`` (or of ``s'`` with ``next_=True``), in ``in_keys`` order."""
        return [td.get(("next", *_tuple(k)) if next_ else k) for k in self.in_keys]

    def bonus(self, td: TensorDictBase) -> Tensor:  # pragma: no cover - abstract
        """``r_in`` ``[*B]`` with the current networks, no gradient."""
        raise NotImplementedError

    def update(self, td: TensorDictBase) -> dict[str, float]:
        """One training step on the batch; scalars to log. The base class learns nothing."""
        return {}

    def bonus_and_update(self, td: TensorDictBase) -> tuple[Tensor, dict[str, float]]:
        """``bonus(td)`` with the networks as they are, then ``update(td)``."""
        r_in, step = self.bonus_then_step(td)
        return r_in, step()

    def bonus_then_step(self, td: TensorDictBase) -> tuple[Tensor, Callable[[], dict[str, float]]]:
        """``bonus(td)`` with the networks as they are, and the training step on ``td`` as a callable to
        run later (before the networks change otherwise): ``update(td)``; subclasses may share one pass
        between the two."""
        with torch.no_grad():
            r_in = self.bonus(td)
        return r_in, lambda: self.update(td)

    def grouped_bonus(self, td: TensorDictBase) -> Tensor:
        """:meth:`bonus` ``[n, g]`` of a batch shaped ``[n, g]`` that holds ``g`` transitions from each of ``n``
        states (``s`` equal along the second dimension; e.g. counterfactual actions from sampled states). The
        base class reads the ``n·g`` transitions one per row; a subclass may read each state once (ICM)."""
        n, g = self.group_shape(td)
        return self.bonus(td.reshape(n * g)).reshape(n, g)

    @staticmethod
    def group_shape(td: TensorDictBase) -> tuple[int, int]:
        """``(n, g)`` of a grouped batch (:meth:`grouped_bonus`); a batch of another shape is refused."""
        if td.batch_dims != 2:
            raise ValueError(f"grouped_bonus takes a batch shaped [n, g] (g transitions from each of n states), "
                             f"got batch {tuple(td.batch_size)}")
        n, g = td.batch_size
        return int(n), int(g)

    def forward(self, td: TensorDictBase) -> Tensor:
        """Same as :meth:`bonus`."""
        return self.bonus(td)


def _tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def seeded_init(seed: int | None) -> contextlib.AbstractContextManager:
    """Context for building parameters: with a ``seed``, a private RNG stream (the global torch RNG
    is left as it was); with ``None``, the global stream as usual."""
    if seed is None:
        return contextlib.nullcontext()
    return _seeded(int(seed))


@contextlib.contextmanager
def _seeded(seed: int) -> Iterator[None]:
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def feature_dim_of(encoder: nn.Module, feature_dim: int | None) -> int:
    """Output width of a feature encoder: ``feature_dim`` if given, else ``encoder.embedding_dim``."""
    if feature_dim is None:
        feature_dim = getattr(encoder, "embedding_dim", None)
        if feature_dim is None:
            raise ValueError(f"cannot tell the output width of {type(encoder).__name__}: give it an "
                             "`embedding_dim` attribute or pass feature_dim=")
    if int(feature_dim) < 1:
        raise ValueError(f"feature_dim must be >= 1, got {feature_dim}")
    return int(feature_dim)


class IntrinsicRewardTransform(Transform):
    """Replay-buffer transform: ``("next", "reward") <- r_ext + beta * r_in`` on sampled batches.

    Args:
        bonus: the intrinsic-reward model.
        beta: scale of ``r_in``, a float ``>= 0`` or a zero-argument callable returning the current
            value (a schedule, read once per sampled batch).
        obs_keys: keys of ``s`` in the buffer, matched one to one with ``bonus.in_keys``
            (default: ``bonus.in_keys``).
        next_obs_keys: keys of ``s'`` (default ``("next", k)`` for each obs key). Point them at a
            one-step successor stored elsewhere when an n-step transform rewrote ``("next", obs)``
            to the n-th successor.
        action_key: key of the action (index ``[*B]``/``[*B, 1]`` or one-hot ``[*B, A]``).
        reward_key, reward_ext_key, reward_int_key: where the total, extrinsic and intrinsic
            rewards go; the latter two get the reward's shape.
        update_bonus: if True, ``bonus.update(batch)`` runs on every sampled batch *after* the
            rewards are computed (so ICM trains on the batches the Q loss sees); if False, the
            caller runs that step when it chooses (:meth:`learn_from_last`).
        obs_norm: an :class:`ObservationNormalizer` applied to the bonus's input observations
            (``s`` and ``s'``, their statistics updated on every sampled batch); ``None``: raw.
        reward_norm: a :class:`RewardNormalizer` applied to ``r_in`` before ``beta``; ``None``: raw.
        terminal_value_gamma: if given (the agent's discount ``gamma``), a transition that ends the
            episode (``terminated_key``) also gets ``beta * gamma**m * mean_r / (1 - gamma)``, where
            ``mean_r`` is the running mean of the (normalised) ``r_in`` and ``m`` the transition's
            ``steps_key`` (1 if absent): the bonus forgone by ending the episode, valued at its
            mean. A positive bonus then never makes staying out worth more than arriving (RND treats
            the intrinsic return as non-episodic for the same reason).
        terminated_key, steps_key: where the termination flag and the n-step count are read.

    ``beta == 0`` returns the extrinsic reward bit for bit. Neither the transform nor the
    bundled bonuses draw from the global RNG. ``inv`` (run at ``extend``) is the identity, and
    stored rewards never change. The scalars of the last call are kept in :attr:`last_stats`.

    Examples:
        An RE3 bonus added to the sampled rewards of a replay buffer (``beta = 0.1``):

        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torch import nn
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from crowdrl.exploration import RE3, IntrinsicRewardTransform
        >>> _ = torch.manual_seed(0)
        >>> batch = TensorDict({"observation": torch.randn(8, 4), "action": torch.randint(0, 3, (8,)),
        ...                     ("next", "observation"): torch.randn(8, 4),
        ...                     ("next", "reward"): torch.zeros(8, 1)}, batch_size=[8])
        >>> transform = IntrinsicRewardTransform(RE3(nn.Linear(4, 16), feature_dim=16, seed=0), beta=0.1)
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=8, transform=transform)
        >>> _ = buffer.extend(batch)
        >>> sample = buffer.sample()
        >>> sorted(sample["next"].keys())
        ['observation', 'reward', 'reward_ext', 'reward_int']
        >>> r = sample["next"]
        >>> bool((r["reward"] > r["reward_ext"]).all())  # RE3's bonus is positive
        True
        >>> torch.allclose(r["reward"], r["reward_ext"] + 0.1 * r["reward_int"])
        True
        >>> bool((buffer.storage.get(slice(None))["next", "reward"] == 0).all())  # the storage is untouched
        True
    """

    def __init__(
        self,
        bonus: IntrinsicBonus,
        beta: Beta = 0.01,
        *,
        obs_keys: Sequence[NestedKey] | None = None,
        next_obs_keys: Sequence[NestedKey] | None = None,
        action_key: NestedKey = "action",
        reward_key: NestedKey = ("next", "reward"),
        reward_ext_key: NestedKey = ("next", "reward_ext"),
        reward_int_key: NestedKey = ("next", "reward_int"),
        update_bonus: bool = True,
        obs_norm: ObservationNormalizer | None = None,
        reward_norm: RewardNormalizer | None = None,
        terminal_value_gamma: float | None = None,
        terminated_key: NestedKey = ("next", "terminated"),
        steps_key: NestedKey = "steps_to_next_obs",
    ) -> None:
        super().__init__(in_keys=[], out_keys=[])
        if not isinstance(bonus, IntrinsicBonus):
            raise TypeError(f"bonus must be an IntrinsicBonus, got {type(bonus).__name__}")
        if not callable(beta):
            beta = _check_beta(beta, "at construction")
        obs_keys = list(bonus.in_keys) if obs_keys is None else [_as_key(k) for k in obs_keys]
        if len(obs_keys) != len(bonus.in_keys):
            raise ValueError(f"obs_keys {obs_keys} must match the bonus's in_keys {bonus.in_keys} one to one")
        if next_obs_keys is None:
            next_obs_keys = [("next", *_tuple(k)) for k in obs_keys]
        else:
            next_obs_keys = [_as_key(k) for k in next_obs_keys]
            if len(next_obs_keys) != len(obs_keys):
                raise ValueError(f"next_obs_keys {next_obs_keys} must match obs_keys {obs_keys} one to one")
        self.bonus = bonus
        self.beta = beta
        self.obs_keys = obs_keys
        self.next_obs_keys = next_obs_keys
        self.action_key = _as_key(action_key)
        self.reward_key = _as_key(reward_key)
        self.reward_ext_key = _as_key(reward_ext_key)
        self.reward_int_key = _as_key(reward_int_key)
        self.update_bonus = bool(update_bonus)
        for name, value, kind in (("obs_norm", obs_norm, ObservationNormalizer),
                                  ("reward_norm", reward_norm, RewardNormalizer)):
            if value is not None and not isinstance(value, kind):
                raise TypeError(f"{name} must be a {kind.__name__} or None, got {type(value).__name__}")
        self.obs_norm = obs_norm
        self.reward_norm = reward_norm
        if terminal_value_gamma is not None:
            terminal_value_gamma = float(terminal_value_gamma)
            if not 0.0 < terminal_value_gamma < 1.0:
                raise ValueError(f"terminal_value_gamma must lie in (0, 1) (the discount), got {terminal_value_gamma}")
        self.terminal_value_gamma = terminal_value_gamma
        self.terminated_key = _as_key(terminated_key)
        self.steps_key = _as_key(steps_key)
        self.bonus_stats = RunningMeanStd()  # of the r_in that beta scales (after reward_norm)
        self.last_stats: dict[str, float] = {}
        self._pending_step: Callable[[], dict[str, float]] | None = None  # learn_from_last's

    def stats_state_dict(self) -> dict[str, Any]:
        """The running statistics of the options (for checkpoints; the bonus saves its own state)."""
        out: dict[str, Any] = {"bonus_stats": self.bonus_stats.state_dict()}
        if self.obs_norm is not None:
            out["obs_norm"] = self.obs_norm.state_dict()
        if self.reward_norm is not None:
            out["reward_norm"] = self.reward_norm.state_dict()
        return out

    def load_stats_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`stats_state_dict` returned."""
        self.bonus_stats.load_state_dict(state["bonus_stats"])
        for name in ("obs_norm", "reward_norm"):
            module = getattr(self, name)
            if (module is None) != (name not in state):
                raise KeyError(f"the saved statistics {'lack' if module is not None else 'hold'} {name!r}, "
                               f"which this transform {'has' if module is not None else 'does not have'}")
            if module is not None:
                module.load_state_dict(state[name])

    def current_beta(self) -> float:
        """The scale in force now (calls the schedule if ``beta`` is callable)."""
        return _check_beta(self.beta(), "returned by the beta schedule") if callable(self.beta) else self.beta

    def _get(self, td: TensorDictBase, key: NestedKey) -> Tensor:
        value = td.get(key, None)
        if value is None:
            present = ", ".join(sorted(repr(k) for k in td.keys(include_nested=True, leaves_only=True)))
            raise KeyError(f"IntrinsicRewardTransform: key {key!r} is missing from the sampled batch; "
                           f"keys present: {present}")
        return value

    def bonus_input(self, td: TensorDictBase) -> TensorDictBase:
        """The batch in the bonus's layout: ``in_keys`` for ``s``, ``("next", k)`` for ``s'``, ``"action"``."""
        out = TensorDict({}, batch_size=td.batch_size, device=td.device)
        obs = [self._get(td, key) for key in self.obs_keys]
        next_obs = [self._get(td, key) for key in self.next_obs_keys]
        if self.obs_norm is not None:  # s and s' share each key's statistics
            both = self.obs_norm([torch.cat((a, b)) for a, b in zip(obs, next_obs)], batch_dims=td.batch_dims)
            n = td.batch_size[0]
            obs, next_obs = [x[:n] for x in both], [x[n:] for x in both]
        for bonus_key, o, o_next in zip(self.bonus.in_keys, obs, next_obs):
            out.set(bonus_key, o)
            out.set(("next", *_tuple(bonus_key)), o_next)
        out.set("action", self._get(td, self.action_key))
        return out

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.add_bonus(tensordict)

    def add_bonus(self, tensordict: TensorDictBase, *, learn: bool = True, record: bool = True,
                  grouped: bool = False) -> TensorDictBase:
        """``r = r_ext + beta * r_in`` on a batch of transitions (what sampling does). ``learn=False``:
        the bonus takes no training step on it (even with ``update_bonus``); ``record=False``:
        :attr:`last_stats` keeps the last recorded batch's scalars. The options' running statistics
        are updated either way. E.g. transitions built from a sampled batch (counterfactual ones)
        get the bonus with ``add_bonus(batch, learn=False, record=False)``. ``grouped=True``: the batch is
        shaped ``[n, g]``, ``g`` transitions from each of ``n`` states (:meth:`IntrinsicBonus.grouped_bonus`;
        without learning only)."""
        r_ext = self._get(tensordict, self.reward_key)
        lead = tuple(tensordict.batch_size)
        if grouped and (learn or len(lead) != 2):
            raise ValueError(f"add_bonus(grouped=True) takes a batch shaped [n, g] and learn=False; got batch {lead}, "
                             f"learn={learn}")
        if r_ext.shape[: len(lead)] != lead:
            raise ValueError(f"reward {self.reward_key!r} shaped {tuple(r_ext.shape)} does not start with the batch {lead}")
        inputs = self.bonus_input(tensordict)
        beta = self.current_beta()
        update_stats = {}
        if learn and self.update_bonus:
            r_in, update_stats = self.bonus.bonus_and_update(inputs)
        elif learn and record:  # the step is the caller's: learn_from_last
            r_in, self._pending_step = self.bonus.bonus_then_step(inputs)
        else:
            with torch.no_grad():
                r_in = self.bonus.grouped_bonus(inputs) if grouped else self.bonus.bonus(inputs)
        raw = r_in.detach()
        if tuple(raw.shape) != lead:
            raise RuntimeError(f"{type(self.bonus).__name__}.bonus returned shape {tuple(raw.shape)}, expected {lead}")
        r_in = raw if self.reward_norm is None else self.reward_norm(raw)
        self.bonus_stats.update(r_in)
        shape = (*lead, *([1] * (r_ext.dim() - len(lead))))
        bonus = beta * r_in
        terminal = None
        if self.terminal_value_gamma is not None:
            g = self.terminal_value_gamma
            steps = tensordict.get(self.steps_key, None)
            steps = torch.ones(lead, dtype=r_in.dtype, device=r_in.device) if steps is None else steps.reshape(lead)
            ended = self._get(tensordict, self.terminated_key).reshape(lead)
            terminal = ended.to(r_in.dtype) * (beta * float(self.bonus_stats.mean) / (1.0 - g)) * g ** steps.to(r_in.dtype)
            bonus = bonus + terminal
        r_in_out = r_in.reshape(shape).expand_as(r_ext).to(r_ext.dtype)
        # beta == 0: exactly r_ext (0 * r_in could turn -0.0 into +0.0, or inf into nan)
        total = r_ext.clone() if beta == 0.0 else r_ext + bonus.reshape(shape).expand_as(r_ext).to(r_ext.dtype)
        # ``set`` replaces entries of the sampled copy; nothing is written in place
        tensordict.set(self.reward_ext_key, r_ext)
        tensordict.set(self.reward_int_key, r_in_out.contiguous())
        tensordict.set(self.reward_key, total)
        if record:
            self.last_stats = {**self._stats(beta, raw, r_in, bonus, r_ext, terminal), **update_stats}
        return tensordict

    def learn_from_last(self) -> dict[str, float]:
        """The bonus's training step on the last batch sampled through a transform built with
        ``update_bonus=False`` (its input as the bonus saw it; :meth:`IntrinsicBonus.bonus_then_step`):
        the bonus was computed before the step, with the networks as they were, as with
        ``update_bonus=True``. Run it before the bonus is used again; its scalars join :attr:`last_stats`."""
        if self._pending_step is None:
            raise RuntimeError("IntrinsicRewardTransform.learn_from_last: no batch sampled through it since its last step")
        step, self._pending_step = self._pending_step, None
        stats = step()
        self.last_stats = {**self.last_stats, **stats}
        return stats

    @staticmethod
    def _stats(beta: float, raw: Tensor, r_in: Tensor, bonus: Tensor, r_ext: Tensor, terminal: Tensor | None
               ) -> dict[str, float]:
        """Diagnostics of one batch: ``r_in`` before (``raw``) and after normalisation, ``beta * r_in``
        (``scaled``, with the terminal value), and the share of the bonus in the total reward's size."""
        ext = r_ext.detach().abs().sum().double()
        added = bonus.detach().abs().sum().double()
        stats = {"beta": beta,
                 "reward_int_mean": float(r_in.mean()), "reward_int_std": float(r_in.std(correction=0)),
                 "reward_int_max": float(r_in.max()), "reward_int_min": float(r_in.min()),
                 "reward_int_raw_mean": float(raw.mean()), "reward_int_raw_std": float(raw.std(correction=0)),
                 "reward_int_raw_max": float(raw.max()),
                 "reward_int_scaled_mean": float(bonus.mean()), "reward_int_scaled_max": float(bonus.max()),
                 "reward_int_share": float(added / (ext + added)) if float(ext + added) > 0 else 0.0}
        if terminal is not None:
            stats["reward_int_terminal_mean"] = float(terminal.mean())
        return stats

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("IntrinsicRewardTransform needs whole transitions (s, a, s'); use it in a replay "
                           "buffer (TensorDictReplayBuffer(transform=...)), not inside an environment")
