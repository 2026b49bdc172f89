"""A sweep's summary: one row per override set of a ``train.py -m`` sweep folder, seeds pooled.

Each job folder of the sweep (``<num>-<overrides>/``, as ``train.py`` writes it) gives its overrides
(``.hydra/overrides.yaml``, else the folder's name), its state (``status.json``), its test on its
training scenario (``eval.json``), its best validation score and frames (``summary.json``, else
``status.json``). Jobs whose overrides differ only in ``seed`` are one row: the mean over the
seeds that finished and each seed's value. A job that failed, was interrupted or left no record is
a row (or a seed) saying so. ``summary.md`` and ``summary.json`` are written into the sweep folder
by the :class:`SweepSummary` Hydra callback (``hydra.callbacks`` in ``conf/config.yaml``) when the
sweep ends, and by this module's command for an existing folder:

    python -m crowdrl.training.sweep_summary multirun/<sweep>
"""

from __future__ import annotations

import argparse
import atexit
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from crowdrl.evaluation.report import RecordError, read_own_test_record
from crowdrl.files import atomic_write_bytes, atomic_write_json
from crowdrl.tables import markdown_table

SUMMARY_MD = "summary.md"
SUMMARY_JSON = "summary.json"
JOB_MARKERS = (".lock", "status.json", ".hydra")  # what train.py leaves in a job folder it started
METRICS = (("success_rate", "test success", 3), ("collision_rate", "collision", 3),
           ("navigation_time", "nav time (s)", 2), ("best_val_score", "best val. score", 4))
SEED_KEY = "seed"


class SweepError(ValueError):
    """A folder that is not a sweep folder ``train.py -m`` wrote (no job folders)."""


def _job_number(folder: Path) -> tuple[int, str]:
    match = re.match(r"(\d+)-", folder.name)
    return (int(match.group(1)) if match else sys.maxsize, folder.name)


def job_folders(sweep: Path | str) -> list[Path]:
    """The job folders of ``sweep`` (those holding a run's ``.lock``, ``status.json`` or ``.hydra/``), by job number."""
    sweep = Path(sweep)
    return sorted((p for p in sweep.iterdir() if p.is_dir() and any((p / m).exists() for m in JOB_MARKERS)),
                  key=_job_number)


def job_overrides(job: Path | str) -> list[str]:
    """A job's command-line overrides: its ``.hydra/overrides.yaml``, else its folder name
    (``<num>-<k=v,...>``, split at the commas)."""
    job = Path(job)
    try:
        data = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text())
    except (OSError, ValueError, yaml.YAMLError):  # missing or damaged: the folder name
        data = None
    if isinstance(data, list) and all(isinstance(o, str) for o in data):
        return data
    name = re.sub(r"^\d+-", "", job.name)
    return [o for o in name.split(",") if o]


def _is_seed(override: str) -> bool:
    return override.split("=", 1)[0].lstrip("+~") == SEED_KEY


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) \
        else None


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def job_record(job: Path | str) -> dict[str, Any]:
    """One job of a sweep: its folder, overrides, seed, state, frames, best validation score and test
    metrics (``None`` where it has none); never raises for a job's missing or damaged files."""
    job = Path(job)
    overrides = job_overrides(job)
    seed = next((o.split("=", 1)[1] for o in overrides if _is_seed(o)), None)
    if seed is None:  # the default seed: the job's config.yaml says which
        try:
            config = yaml.safe_load((job / "config.yaml").read_text())
        except (OSError, ValueError, yaml.YAMLError):
            config = None
        if isinstance(config, dict) and config.get(SEED_KEY) is not None:
            seed = str(config[SEED_KEY])
    status = _read_json(job / "status.json")
    state = str(status.get("state")) if status is not None else ("no status.json" if not (job / "status.json").exists()
                                                                 else "unreadable status.json")
    summary = _read_json(job / "summary.json") or {}
    record: dict[str, Any] = {"folder": job.name, "overrides": overrides, "seed": seed, "status": state,
                              "frames": _number(summary.get("frames", (status or {}).get("frames"))),
                              "best_val_score": _number(summary.get("best_val_score",
                                                                    (status or {}).get("best_val_score"))),
                              "episodes": None, "scenario": None,
                              **{key: None for key, _, _ in METRICS if key != "best_val_score"}}
    if record["frames"] is not None:
        record["frames"] = int(record["frames"])
    if status is not None and status.get("error"):
        record["error"] = str(status["error"])
    if state == "completed":
        try:
            test = read_own_test_record(job)
        except RecordError as exc:
            record.update(status="completed, test record unreadable", error=str(exc))
        else:
            record.update({key: test.get(key) for key, _, _ in METRICS if key != "best_val_score"},
                          episodes=test["episodes"], scenario=test["scenario"])
    return record


def _label(overrides: list[str], shared: set[str]) -> str:
    varying = [o for o in overrides if o not in shared]
    return " ".join(varying or overrides) or "(defaults)"


def _status(members: list[dict[str, Any]]) -> str:
    """``completed`` when every seed completed, else each other seed's state (``seed 1: failed``)."""
    if all(m["status"] == "completed" for m in members):
        return "completed"
    if len(members) == 1:
        return members[0]["status"]
    names = [f"seed {m['seed']}" if m["seed"] is not None else f"job {_job_number(Path(m['folder']))[0]}"
             for m in members]
    if len(set(names)) < len(names):  # the same seed twice (a sweep folder reused): the job numbers
        names = [f"job {_job_number(Path(m['folder']))[0]}" for m in members]
    return "; ".join(f"{n}: {m['status']}" for n, m in zip(names, members) if m["status"] != "completed")


def summarize_sweep(sweep: Path | str) -> list[dict[str, Any]]:
    """The rows of a sweep folder: one per override set (seeds pooled), in job order. Each row: ``label``
    (the overrides that vary across the sweep's rows; all of them for a one-row sweep), ``overrides``
    (all but ``seed``), ``seeds``, ``status``, per metric the mean over the finished seeds and
    ``<metric>_per_seed``, ``frames`` and ``jobs`` (:func:`job_record` of each). :class:`SweepError`
    for a folder that holds no job folder."""
    sweep = Path(sweep)
    if not sweep.is_dir():
        raise SweepError(f"{sweep} is not a folder")
    jobs = [job_record(j) for j in job_folders(sweep)]
    if not jobs:
        raise SweepError(f"{sweep} holds no job folder of train.py -m (no <num>-<overrides>/ with status.json)")
    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for job in jobs:
        groups.setdefault(tuple(sorted(o for o in job["overrides"] if not _is_seed(o))), []).append(job)
    sets = [[o for o in members[0]["overrides"] if not _is_seed(o)] for members in groups.values()]
    shared = set.intersection(*(set(s) for s in sets)) if len(sets) > 1 else set()
    rows = []
    for overrides, members in zip(sets, groups.values()):
        done = [m for m in members if m["status"] == "completed"]
        row: dict[str, Any] = {"label": _label(overrides, shared), "overrides": overrides,
                               "seeds": [m["seed"] for m in members], "completed": len(done),
                               "status": _status(members),
                               "episodes": sorted({m["episodes"] for m in done}),
                               "frames": sorted({m["frames"] for m in members if m["frames"] is not None})}
        for key, _, _ in METRICS:
            values = [m[key] for m in done]
            present = [v for v in values if v is not None]
            row[key] = sum(present) / len(present) if present else None
            row[f"{key}_per_seed"] = values
        row["jobs"] = members
        rows.append(row)
    return rows


def _cell(row: dict[str, Any], key: str, digits: int) -> str:
    def fmt(v: float | None) -> str:
        return "–" if v is None else f"{v:.{digits}f}"

    per_seed = row[f"{key}_per_seed"]
    return fmt(row[key]) + (f" ({', '.join(fmt(v) for v in per_seed)})" if len(per_seed) > 1 else "")


def markdown(sweep: Path | str, rows: list[dict[str, Any]]) -> str:
    """The summary table of a sweep's rows (:func:`summarize_sweep`), with a line on what the cells are."""
    sets = [set(r["overrides"]) for r in rows]
    shared = [o for o in rows[0]["overrides"] if all(o in s for s in sets)] if len(rows) > 1 else []
    episodes = sorted({e for r in rows for e in r["episodes"]})
    cases = ("/".join(map(str, episodes)) + " test cases") if episodes else "test cases"
    lines = [f"# Sweep {Path(sweep).name}", "",
             f"Test: each run's best checkpoint on {cases} of its training scenario (its eval.json); cells: the "
             f"mean over the seeds that completed (each seed's value in brackets); best val. score: the best "
             f"validation's success rate + 0.001 x return (the checkpoint tested). Why a job did not complete: "
             f"its \"error\" in summary.json.", ""]
    if shared:
        lines += [f"Every row also ran with: {' '.join(shared)}", ""]
    cells = [[r["label"], ", ".join(s if s is not None else "–" for s in r["seeds"]),
              *(_cell(r, key, digits) for key, _, digits in METRICS),
              "/".join(str(f) for f in r["frames"]) or "–", r["status"]] for r in rows]
    lines.append(markdown_table(["overrides", "seeds", *(h for _, h, _ in METRICS), "frames", "status"], cells))
    return "\n".join(lines) + "\n"


def write_summary(sweep: Path | str, *, echo: bool = True) -> list[dict[str, Any]]:
    """Write ``summary.md`` and ``summary.json`` into ``sweep`` (atomically) and return its rows;
    ``echo``: print the table too. :class:`SweepError` for a folder without job folders."""
    sweep = Path(sweep)
    rows = summarize_sweep(sweep)
    text = markdown(sweep, rows)
    atomic_write_json(sweep / SUMMARY_JSON, {"sweep": str(sweep), "rows": rows})
    atomic_write_bytes(sweep / SUMMARY_MD, text.encode())
    if echo:
        print(text, end="")
        print(f"sweep summary: {(sweep / SUMMARY_MD).resolve()}")
    return rows


def _summarize_at_end(sweep: Path) -> None:
    """Write the summary of a sweep that ended, never raising: a sweep refused before any job wrote
    anything (no folder, no job folder) gets none, and a summary that cannot be written is one line on stderr."""
    try:
        if not sweep.is_dir() or not job_folders(sweep):
            return
        write_summary(sweep)
    except Exception as exc:  # the sweep's own outcome stands; its summary is an extra
        print(f"sweep summary of {sweep} not written: {exc}", file=sys.stderr)


class SweepSummary(Callback):
    """Hydra callback: when a sweep (``-m``) ends, write and print its summary (:func:`write_summary`).
    A sweep that stops at a failed or interrupted job (``train.py`` exits) gets its summary as the process exits."""

    def __init__(self) -> None:
        self._pending: Path | None = None

    def _at_exit(self) -> None:
        if self._pending is not None:
            sweep, self._pending = self._pending, None
            _summarize_at_end(sweep)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._pending = Path(str(config.hydra.sweep.dir)).absolute()
        atexit.register(self._at_exit)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        atexit.unregister(self._at_exit)
        self._pending = None
        _summarize_at_end(Path(str(config.hydra.sweep.dir)).absolute())


def main(argv: list[str] | None = None) -> int:
    """``python -m crowdrl.training.sweep_summary SWEEP [...]``: (re)write each sweep folder's summary."""
    p = argparse.ArgumentParser(prog="python -m crowdrl.training.sweep_summary",
                                description="Write summary.md and summary.json of train.py -m sweep folders.")
    p.add_argument("sweep", nargs="+", type=Path, help="a sweep folder (multirun/<time>-<uid>)")
    args = p.parse_args(argv)
    for sweep in args.sweep:  # every folder checked before anything is written
        if not sweep.is_dir() or not job_folders(sweep):
            p.exit(2, f"{p.prog}: sweep: {sweep} is no sweep folder of train.py -m (no job folder with status.json)\n")
    for sweep in args.sweep:
        write_summary(sweep)
    return 0


if __name__ == "__main__":
    sys.exit(main())
