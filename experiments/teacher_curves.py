"""Frames and minutes to quality, with and without the oracle's demonstrations (docs/ceiling.md, "The oracle as
a teacher").

Reads run folders (their ``config.yaml`` and ``scalars.jsonl``; validation rows only, never test results) and
prints, per run: the collected frames at the first validation whose success reaches ``--threshold`` (0.95), the
training minutes to that validation, the best validation success and where it was reached, the mean success
over all its validations (the area under the validation curve, per validation), and the demonstrations stored.
Runs are grouped by ``train.demonstrations.cases`` (0: without).

The minutes are the run's own timers (``time/*_s`` of its ``train`` rows: collection, updates, validation and,
with demonstrations, the oracle's search and replay), read at the first ``train`` row at or after the
validation's frame count (the same batch, or the next one when that batch logged no train row). They leave out
process start-up and the final test.

    python experiments/teacher_curves.py results/oracle-teacher/runs/*
    python experiments/teacher_curves.py results/oracle-teacher/runs/* --json results/oracle-teacher/table.json
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path
from typing import Any

import yaml


def read_rows(run: Path) -> list[dict[str, Any]]:
    """The rows of ``run/scalars.jsonl``."""
    return [json.loads(line) for line in (run / "scalars.jsonl").read_text().splitlines() if line.strip()]


def minutes_at(rows: list[dict[str, Any]], frames: int) -> float:
    """Training minutes (the sum of a train row's ``time/*_s`` timers, ``time/demo_s`` included) at the first
    train row at or after ``frames`` (nan: none)."""
    for r in rows:
        if r.get("kind") == "train" and r["frames"] >= frames:
            return sum(v for k, v in r.items() if k.startswith("time/") and k.endswith("_s") and v is not None) / 60
    return math.nan


def run_record(run: Path, threshold: float) -> dict[str, Any]:
    """One run's frames and minutes to ``threshold``, its best validation and its demonstrations."""
    config = yaml.safe_load((run / "config.yaml").read_text())
    rows = read_rows(run)
    vals = [r for r in rows if r.get("kind") == "val"]
    if not vals:
        raise SystemExit(f"{run}: no validation rows in scalars.jsonl")
    demo = next((r for r in rows if r.get("kind") == "demo"), {})
    reached = next((r for r in vals if r["val/success_rate"] >= threshold), None)
    best = max(vals, key=lambda r: (r["val/success_rate"], r["val/average_return"]))
    return {
        "run": str(run), "seed": int(config["seed"]),
        "demo_cases": int(config["train"].get("demonstrations", {}).get("cases", 0)),
        "demo_transitions": demo.get("train/demo_transitions", 0), "demo_solved": demo.get("train/demo_solved", 0),
        "demo_minutes": (demo.get("time/demo_search_s", 0.0) + demo.get("time/demo_play_s", 0.0)) / 60,
        "frames_to_threshold": reached["frames"] if reached else None,
        "minutes_to_threshold": minutes_at(rows, reached["frames"]) if reached else None,
        "best_val_success": best["val/success_rate"], "best_val_frames": best["frames"],
        "mean_val_success": statistics.mean(r["val/success_rate"] for r in vals),
        "last_val_frames": vals[-1]["frames"], "validations": len(vals),
    }


def _cell(value: Any, digits: int = 1, scale: float = 1.0) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "never"
    return f"{value / scale:.{digits}f}"


def table(records: list[dict[str, Any]], threshold: float) -> str:
    """A markdown table: one row per run, then one per group with the means (over the runs that reached it)."""
    head = (f"| demonstrations | seed | k frames to val. ≥ {threshold:g} | minutes to val. ≥ {threshold:g} | "
            f"best val. success (k frames) | mean val. success | demo transitions (solved cases) | demo minutes |")
    lines = [head, "|" + "---|" * 8]
    groups: dict[int, list[dict[str, Any]]] = {}
    for r in sorted(records, key=lambda r: (r["demo_cases"], r["seed"])):
        groups.setdefault(r["demo_cases"], []).append(r)
        lines.append(f"| {r['demo_cases'] or 'none'} | {r['seed']} | {_cell(r['frames_to_threshold'], 0, 1000)} | "
                     f"{_cell(r['minutes_to_threshold'])} | {r['best_val_success']:.2f} "
                     f"({r['best_val_frames'] / 1000:.0f}) | {r['mean_val_success']:.3f} | "
                     f"{r['demo_transitions']} ({r['demo_solved']}) | "
                     f"{r['demo_minutes']:.1f} |")
    for cases, rs in groups.items():
        hit = [r for r in rs if r["frames_to_threshold"] is not None]
        frames = statistics.mean(r["frames_to_threshold"] for r in hit) / 1000 if hit else None
        minutes = statistics.mean(r["minutes_to_threshold"] for r in hit) if hit else None
        never = f" [{len(rs) - len(hit)} never]" if len(hit) < len(rs) else ""
        lines.append(f"| **{cases or 'none'}: mean** | {len(rs)} runs | {_cell(frames, 0)}{never} | "
                     f"{_cell(minutes)} | {statistics.mean(r['best_val_success'] for r in rs):.3f} | "
                     f"{statistics.mean(r['mean_val_success'] for r in rs):.3f} | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (config.yaml and scalars.jsonl)")
    parser.add_argument("--threshold", type=float, default=0.95, help="validation success to reach (default 0.95)")
    parser.add_argument("--json", type=Path, default=None, help="also write the records to this file")
    args = parser.parse_args(argv)
    if not 0 < args.threshold <= 1:
        raise SystemExit(f"--threshold: must lie in (0, 1], got {args.threshold}")
    for run in args.runs:
        if not (run / "config.yaml").is_file() or not (run / "scalars.jsonl").is_file():
            raise SystemExit(f"{run}: not a run folder (needs config.yaml and scalars.jsonl)")
    records = [run_record(run, args.threshold) for run in args.runs]
    print(table(records, args.threshold))
    if args.json is not None:
        args.json.write_text(json.dumps({"threshold": args.threshold, "runs": records}, indent=1) + "\n")


if __name__ == "__main__":
    main()
