"""Statistics over seeds with rliable: stratified-bootstrap confidence intervals of a mean and
the probability of improvement (Agarwal et al., 2021), for one scenario at a time.

Scores are arrays ``[num_seeds]`` (one task); rliable's stratified bootstrap then resamples
seeds. With 3 seeds the intervals are wide: they say how little 3 seeds can settle.

The intervals are a pure function of the scores and ``seed``. rliable (1.2) draws its resamples
from numpy's global generator (``np.random.choice`` in its bootstraps' ``update_indices``), not from
the ``random_state`` it is given, so each estimate here runs with the global generator seeded by
``seed`` and then puts the caller's global state back.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np


def _quiet_rliable():
    try:
        import rliable  # noqa: F401
    except ImportError as exc:
        from crowdrl._extras import missing

        raise missing("rliable", "train", "confidence intervals over seeds") from exc
    from absl import logging as absl_logging
    from rliable import library as rly

    absl_logging.set_verbosity(absl_logging.WARNING)  # rliable logs every estimate at INFO
    return rly


@contextmanager
def _seeded_bootstrap(seed: int) -> Iterator[np.random.RandomState]:
    """rliable's ``random_state`` (for arch) and numpy's global generator, both seeded with ``seed``; the
    global state is restored afterwards. Also silences arch's deprecation of the RandomState rliable passes."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield np.random.RandomState(seed)
    finally:
        np.random.set_state(saved)


def mean_interval(scores: dict[str, np.ndarray], *, reps: int = 2000, confidence: float = 0.95,
                  seed: int = 0) -> dict[str, tuple[float, float, float]]:
    """Per method, ``(mean, low, high)``: the mean over seeds and its percentile-bootstrap CI.

    NaN scores (e.g. the navigation time of a seed with no success) are left out of the mean.
    """
    rly = _quiet_rliable()
    out: dict[str, tuple[float, float, float]] = {}
    for method, values in scores.items():
        x = np.asarray(values, dtype=np.float64).reshape(-1)
        x = x[~np.isnan(x)]
        if x.size == 0:
            out[method] = (np.nan, np.nan, np.nan)
            continue
        if x.size == 1 or np.all(x == x[0]):
            out[method] = (float(x[0]) if x.size == 1 else float(x.mean()),) * 3
            continue
        with _seeded_bootstrap(seed) as random_state:
            point, ci = rly.get_interval_estimates({method: x[:, None]}, lambda s: np.array([s.mean()]), reps=reps,
                                                   confidence_interval_size=confidence, random_state=random_state)
        out[method] = (float(point[method][0]), float(ci[method][0, 0]), float(ci[method][1, 0]))
    return out


def probability_of_improvement(x: np.ndarray, y: np.ndarray, *, reps: int = 2000, confidence: float = 0.95,
                               seed: int = 0) -> tuple[float, float, float]:
    """``P(X > Y)`` over seeds of two methods (ties count half) with its bootstrap CI."""
    rly = _quiet_rliable()
    from rliable import metrics

    x = np.asarray(x, dtype=np.float64).reshape(-1, 1)
    y = np.asarray(y, dtype=np.float64).reshape(-1, 1)
    with _seeded_bootstrap(seed) as random_state:
        point, ci = rly.get_interval_estimates({"xy": (x, y)}, metrics.probability_of_improvement, reps=reps,
                                               confidence_interval_size=confidence, random_state=random_state)
    return float(np.ravel(point["xy"])[0]), float(ci["xy"][0].item()), float(ci["xy"][1].item())
