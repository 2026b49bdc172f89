"""Counter-based random numbers: every draw is a pure function of (key, indices).

Scenario ``i`` of a stream must be the same whatever the batch size or device, so the
simulator never consumes a sequential generator. Instead each value is a hash of its episode
key and a tuple of integer indices (which human, which rejection round, which component).
Keys carry 63 bits in two lanes (so train, validation and test episodes of a long run do not
collide, as they would with 32 bits), and all arithmetic stays below 2**63 in int64, so it is
exact on every backend.

The hash is written with Python operators only, so one implementation runs on torch tensors,
on NumPy arrays and on Python ints alike. CPU draws run it on NumPy views of the tensors
(NumPy's integer loops and per-call cost are lighter than ATen's here; docs/benchmarks.md), and an
index given as a Python int is hashed once in Python; the bits are the same either way (tested).
"""

from __future__ import annotations

from typing import Union

import numpy as np
import torch
from torch import Tensor

Ints = Union[Tensor, np.ndarray, int]  # what the hash runs on: int64 tensors or arrays, or Python ints

_MASK32 = 0xFFFFFFFF
MAX_SEED = 2**63 - 1  # the largest seed a run, an evaluation or the Gymnasium face accepts (int64, torch.manual_seed)
STREAMS = {"train": 0x1B873593, "val": 0x68E31DA4, "test": 0x5F3759DF}


def _mul32(x: Ints, c: int) -> Ints:
    """``(x * c) mod 2**32`` for ``0 <= x < 2**32`` without int64 overflow (uint32 arrays: their own
    wrapping product, the same bits)."""
    if isinstance(x, (np.ndarray, np.generic)) and x.dtype == np.uint32:
        return x * np.uint32(c)
    lo = x * (c & 0xFFFF)
    hi = ((x * (c >> 16)) & 0xFFFF) << 16
    return (lo + hi) & _MASK32


def hash32(x: Ints) -> Ints:
    """A well-mixing bijection on 32-bit integers (held in int64, or in uint32 NumPy arrays)."""
    x = x & _MASK32
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    x = x ^ (x >> 16)
    return x


def fold(key: Tensor, *indices: Tensor | int) -> Tensor:
    """Hash the 63-bit ``key`` with each index in turn (broadcasting), giving a new key (CPU keys hash as NumPy arrays).

    For a fixed key, distinct indices give distinct low lanes, so episodes of one stream never
    share a key.
    """
    key = key.to(torch.int64)
    idx = [i.to(key.device, torch.int64) if isinstance(i, Tensor) else int(i) for i in indices]
    if key.device.type != "cpu" or torch.compiler.is_compiling():
        return fold_ints(key, *idx)
    arrays = [i.numpy() if isinstance(i, Tensor) else i for i in idx]  # views: no copies
    return torch.from_numpy(np.asarray(fold_ints(key.numpy(), *arrays), dtype=np.int64))


def fold_ints(h: Ints, *indices: Ints) -> Ints:
    """:func:`fold` on any integer type: int64 tensors (any device), int64 NumPy arrays or Python ints,
    mixed and broadcast; the bits are the same for all (a Python-int index is hashed in Python).

    With NumPy arrays the key's two lanes (and the indices' low 32 bits, all the hash reads) are
    held as uint32, whose products wrap mod 2**32 by themselves (:func:`_mul32`): the same bits
    with a third of the integer ops (``experiments/bench_reset.py``)."""
    on_numpy = isinstance(h, np.ndarray) or any(isinstance(i, np.ndarray) for i in indices)
    if on_numpy:
        h = np.asarray(h, dtype=np.int64)
        lo, hi = (h & _MASK32).astype(np.uint32), (h >> 32).astype(np.uint32)
        indices = tuple(i.astype(np.uint32) if isinstance(i, np.ndarray) else i for i in indices)
    else:
        lo, hi = h & _MASK32, h >> 32
    with np.errstate(over="ignore"):  # uint32 sums wrap on purpose (0-d arrays would warn as scalars)
        for idx in indices:
            i = hash32(idx + 0x9E3779B9)
            lo = hash32(lo ^ i ^ hash32(hi + 0x85EBCA6B))
            hi = hash32(hi ^ hash32(i ^ 0xC2B2AE35) ^ lo) & 0x7FFFFFFF
    if on_numpy:
        return (hi.astype(np.int64) << 32) | lo.astype(np.int64)
    return (hi << 32) | lo


def uniform(key: Tensor, *indices: Tensor | int, dtype: torch.dtype = torch.float32) -> Tensor:
    """Uniform floats in ``[0, 1)`` (24-bit resolution), one per broadcast element."""
    return ((fold(key, *indices) & _MASK32) >> 8).to(dtype) * (1.0 / (1 << 24))


def episode_keys(stream: str, seed: int, episode_ids: Tensor) -> Tensor:
    """Keys of episodes ``episode_ids`` in ``stream`` (``train``, ``val`` or ``test``) of ``seed``."""
    if stream not in STREAMS:
        raise ValueError(f"stream must be one of {tuple(STREAMS)}, got {stream!r}")
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    base = torch.tensor(STREAMS[stream] << 32 | STREAMS[stream], dtype=torch.int64, device=episode_ids.device)
    seed_lo = int(seed) & _MASK32
    seed_hi = (int(seed) >> 32) & _MASK32
    return fold(base, seed_lo, seed_hi, episode_ids.to(torch.int64))
