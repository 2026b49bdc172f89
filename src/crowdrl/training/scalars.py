"""Run logging: every scalar to CSV/JSONL in the run folder, optionally mirrored to wandb; the progress bar."""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

from crowdrl.files import atomic_write_bytes, atomic_write_with, dumps_json, read_json_lines


def _json_line(row: dict[str, Any]) -> str:
    """One row of ``scalars.jsonl``: strict JSON (NaN/inf as null), keys sorted."""
    return dumps_json(row, indent=None, sort_keys=True) + "\n"


class ScalarLog:
    """Append-only scalar log with one strict JSON line per row (``scalars.jsonl``), fsynced per row;
    a non-finite value (NaN, ±inf) is written as ``null``, as in every JSON file crowdrl writes.

    ``scalars.csv`` is rewritten from it at ``close``/``flush_csv`` (columns can appear over
    time). On resume, ``truncate_after(frames)`` drops rows written after the checkpoint being
    resumed, and a half-written last line from a kill.
    """

    def __init__(self, run_dir: Path) -> None:
        self.dir = Path(run_dir)
        self.path = self.dir / "scalars.jsonl"
        self.dir.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "a", encoding="utf-8")

    def log(self, row: dict[str, Any]) -> None:
        self._f.write(_json_line(row))
        self._f.flush()
        os.fsync(self._f.fileno())

    def rows(self) -> list[dict[str, Any]]:
        return read_json_lines(self.path)

    def truncate_after(self, frames: int) -> int:
        """Keep rows with ``frames <= frames``; return how many rows were dropped."""
        self._f.close()
        rows = self.rows()
        kept = [r for r in rows if r.get("frames", 0) <= frames]
        atomic_write_bytes(self.path, "".join(map(_json_line, kept)).encode())
        self._f = open(self.path, "a", encoding="utf-8")
        return len(rows) - len(kept)

    def flush_csv(self) -> Path:
        rows = self.rows()
        columns = sorted({k for r in rows for k in r})
        first = [c for c in ("kind", "frames", "updates", "episodes") if c in columns]
        columns = first + [c for c in columns if c not in first]
        path = self.dir / "scalars.csv"

        def write(tmp: Path) -> None:
            with open(tmp, "w", newline="", encoding="utf-8") as f:
                writer = csv.DictWriter(f, fieldnames=columns)
                writer.writeheader()
                writer.writerows(rows)

        return atomic_write_with(path, write)

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()
        self.flush_csv()


def progress_bar(total: int, initial: int):
    """A tqdm bar over frames (``logger.progress_bar``), from ``initial`` of ``total``."""
    try:
        from tqdm.auto import tqdm
    except ImportError as exc:
        from crowdrl._extras import missing

        raise missing("tqdm", "train", "the progress bar (logger.progress_bar=false does without)") from exc

    return tqdm(total=total, initial=initial, unit="frame", dynamic_ncols=True, smoothing=0.05)


def wandb_mode(mode: str) -> str:
    """The mode a wandb run starts in: ``WANDB_MODE`` when set, else ``logger.mode``."""
    return os.environ.get("WANDB_MODE", mode)


def has_wandb_credentials() -> bool:
    """Whether wandb could log in without asking: ``WANDB_API_KEY``, or a netrc entry (``NETRC`` or
    ``~/.netrc``) for the wandb host (``WANDB_BASE_URL``, default ``api.wandb.ai``)."""
    import netrc
    from urllib.parse import urlparse

    if os.environ.get("WANDB_API_KEY"):
        return True
    host = urlparse(os.environ.get("WANDB_BASE_URL", "https://api.wandb.ai")).hostname or "api.wandb.ai"
    try:
        return netrc.netrc(os.environ.get("NETRC") or None).authenticators(host) is not None
    except (OSError, netrc.NetrcParseError):
        return False


class WandbMirror:
    """Mirror of the scalar rows into a wandb run, through TorchRL's ``WandbLogger`` (offline unless the
    mode says otherwise); a resumed run passes its ``resume_id`` and continues the same wandb run."""

    def __init__(self, run_dir: Path, config: dict, project: str, mode: str, resume_id: str | None) -> None:
        try:
            import wandb  # noqa: F401
        except ImportError as exc:
            from crowdrl._extras import missing

            raise missing("wandb", "train", "logger=wandb (logger=csv does without)") from exc
        from torchrl.record.loggers.wandb import WandbLogger

        os.environ.setdefault("WANDB_SILENT", "true")
        # mode goes to wandb.init: WandbLogger's offline=True would set WANDB_MODE for the whole process
        self.logger = WandbLogger(exp_name=Path(run_dir).name, save_dir=str(run_dir), id=resume_id, project=project,
                                  log_env_packages=False, mode=wandb_mode(mode), config=config,
                                  reinit="finish_previous")
        self.id = self.logger.experiment.id

    def log(self, row: dict[str, Any]) -> None:
        numbers = {k: v for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        self.logger.log_metrics(numbers, step=int(row.get("frames", 0)), override_global_step=True)  # x: frames

    def close(self) -> None:
        self.logger.experiment.finish()
