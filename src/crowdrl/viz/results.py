"""Figures of a multi-seed comparison: smoothed learning curves with a band over seeds, and the
table's interval plot."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from crowdrl.files import atomic_write_with

PAPER_SMOOTHING = 0.99  # the paper's exponential smoothing of training curves


def ema(values: Sequence[float], smoothing: float = PAPER_SMOOTHING, counts: Sequence[float] | None = None
        ) -> np.ndarray:
    """Exponential moving average with bias correction (TensorBoard's smoothing): ``smoothing = 0``
    returns the values, ``0.99`` the paper's per-episode curves. When point ``i`` is the mean of
    ``counts[i]`` episodes, it is weighted as that many episodes (``smoothing ** counts[i]``), so
    the curve is the per-episode EMA whatever the logging period. NaNs are skipped.

    >>> ema([1.0, 3.0], 0.5).tolist()
    [1.0, 2.333333333333333]
    """
    if not 0.0 <= smoothing < 1.0:
        raise ValueError(f"smoothing must lie in [0, 1), got {smoothing}")
    counts = np.ones(len(values)) if counts is None else np.asarray(counts, dtype=np.float64)
    if counts.shape != (len(values),) or bool((counts < 0).any()):
        raise ValueError("counts must hold one non-negative number per value")
    out, acc, weight = [], 0.0, 0.0
    for v, n in zip(values, counts):
        if not np.isnan(v):
            keep = smoothing ** n
            acc = keep * acc + (1 - keep) * v
            weight = keep * weight + (1 - keep)
        out.append(acc / weight if weight > 0 else np.nan)
    return np.asarray(out, dtype=np.float64)


def seed_band(curves: list[tuple[np.ndarray, np.ndarray]], grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, min and max over seeds of curves ``(x, y)`` interpolated onto ``grid`` (NaN beyond a
    curve's last x)."""
    ys = np.stack([np.interp(grid, x, y, left=np.nan, right=np.nan) for x, y in curves])
    with np.errstate(all="ignore"):
        return np.nanmean(ys, 0), np.nanmin(ys, 0), np.nanmax(ys, 0)


def _save(fig: Figure, path: Path | str, dpi: int = 110) -> Path:
    path = Path(path)
    return atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=dpi), suffix=path.suffix)


def plot_seed_curves(runs: dict[str, list[list[dict[str, Any]]]], path: Path | str, *,
                     smoothing: float = PAPER_SMOOTHING, title: str | None = None) -> Path:
    """Per method (key of ``runs``: a list of runs' ``scalars.jsonl`` rows), the training success
    rate smoothed by :func:`ema` and the greedy validation success, as the mean over seeds with a
    min-max band. Saved as PNG."""
    fig = Figure(figsize=(11, 4.2))
    FigureCanvasAgg(fig)
    panels = [("train", "train/success_rate", f"training success (per-episode EMA {smoothing})", smoothing),
              ("val", "val/success_rate", "validation success (greedy)", 0.0)]
    colors = colormaps["tab10"]
    for p, (kind, key, label, s) in enumerate(panels):
        ax = fig.add_subplot(1, 2, p + 1)
        for k, (method, seeds) in enumerate(runs.items()):
            curves = []
            for rows in seeds:
                pts = [(r["frames"], r[key], r.get("episodes", 0)) for r in rows if r.get("kind") == kind and key in r]
                if pts:
                    x, y, episodes = np.array(pts, dtype=np.float64).T
                    counts = np.diff(episodes, prepend=0.0)  # episodes behind each logged rate
                    curves.append((x, ema(y, s, counts)))
            if not curves:
                continue
            grid = np.unique(np.concatenate([x for x, _ in curves]))
            mean, lo, hi = seed_band(curves, grid)
            ax.plot(grid, mean, color=colors(k % 10), lw=1.8, label=f"{method} ({len(curves)} seeds)")
            ax.fill_between(grid, lo, hi, color=colors(k % 10), alpha=0.18, lw=0)
        ax.set_xlabel("frames (robot steps)")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0"))
        ax.set_ylabel(label)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def plot_intervals(rows: list[dict[str, Any]], path: Path | str, *, metric: str = "success_rate",
                   title: str | None = None) -> Path:
    """Interval plot of a results table: per scenario, each method's mean and 95 % CI of ``metric``
    over seeds, the paper's value as a cross. ``rows`` carry ``method``, ``scenario``,
    ``<metric>`` / ``<metric>_lo`` / ``<metric>_hi`` and ``<metric>_paper``."""
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    fig = Figure(figsize=(5.0 * len(scenarios), 3.8))
    FigureCanvasAgg(fig)
    for s, scenario in enumerate(scenarios):
        ax = fig.add_subplot(1, len(scenarios), s + 1)
        sub = [r for r in rows if r["scenario"] == scenario]
        y = np.arange(len(sub))
        mean = np.array([r[metric] for r in sub], dtype=np.float64)
        lo = np.array([r.get(f"{metric}_lo", r[metric]) for r in sub], dtype=np.float64)
        hi = np.array([r.get(f"{metric}_hi", r[metric]) for r in sub], dtype=np.float64)
        ax.errorbar(mean, y, xerr=np.stack([mean - lo, hi - mean]), fmt="o", color="tab:blue", capsize=4,
                    label="crowdrl (mean, 95% CI over seeds)")
        paper = np.array([r.get(f"{metric}_paper", np.nan) for r in sub], dtype=np.float64)
        ax.plot(paper, y, "x", color="tab:red", ms=8, label="paper (one seed)")
        ax.set_yticks(y, [r["method"] for r in sub])
        ax.invert_yaxis()
        ax.set_xlabel(metric.replace("_", " "))
        ax.set_title(scenario)
        ax.grid(alpha=0.3, axis="x")
        if s == 0:
            ax.legend(fontsize=7, loc="center left")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)
