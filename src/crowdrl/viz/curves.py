"""Learning curves of a run from its ``scalars.jsonl`` rows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from crowdrl.files import atomic_write_with


def plot_learning_curves(rows: list[dict[str, Any]], path: Path | str, *, title: str | None = None) -> Path:
    """Training success/collision rates and validation success versus frames, saved as PNG."""
    train = [r for r in rows if r.get("kind") == "train"]
    val = [r for r in rows if r.get("kind") == "val"]
    fig = Figure(figsize=(8, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if train:
        x = [r["frames"] for r in train]
        ax.plot(x, [r["train/success_rate"] for r in train], color="tab:green", alpha=0.35, lw=1, label="train success")
        ax.plot(x, [r["train/collision_rate"] for r in train], color="tab:red", alpha=0.35, lw=1, label="train collision")
    if val:
        ax.plot([r["frames"] for r in val], [r["val/success_rate"] for r in val], "o-", color="tab:blue",
                lw=2, label="validation success (greedy)")
    ax.set_xlabel("frames (robot steps)")
    ax.set_ylabel("rate")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    return atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=110), suffix=path.suffix)


