"""Compare exploration variants: train each with several seeds, test on the fixed test cases,
print mean ± std of success rate, navigation time and average return.

    python experiments/compare_exploration.py                       # 5 variants x seeds 0,1,2, preset=demo
    python experiments/compare_exploration.py --jobs 2 --out runs/compare -- train.total_frames=30000
    python experiments/compare_exploration.py --summarize runs/compare   # only aggregate finished runs

Each (variant, seed) is one ``experiments/train.py`` run in ``<out>/<variant>-s<seed>`` (a
killed comparison resumes: finished runs are skipped, unfinished ones continue from their last
checkpoint). Arguments after ``--`` are Hydra overrides applied to every run. Runs go ``--jobs``
at a time, one torch thread each. Model selection uses the validation stream only; the test
cases are touched once per run, by the best validation checkpoint.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("egreedy", "noisy", "dropout", "icm", "re3")
METRICS = ("success_rate", "collision_rate", "navigation_time", "average_return")


def _check_overrides(run_dir: Path, overrides: list[str]) -> None:
    """A run folder is reused only for the overrides it was started with (no mixed budgets)."""
    stored = run_dir / "compare_overrides.json"
    if stored.is_file() and json.loads(stored.read_text()) != overrides:
        raise SystemExit(f"{run_dir} was trained with overrides {json.loads(stored.read_text())}, not {overrides}; "
                         "use another --out")


def run_one(out: Path, variant: str, seed: int, overrides: list[str]) -> Path:
    """Train (or resume, or skip if finished) one run; returns its folder."""
    run_dir = out / f"{variant}-s{seed}"
    _check_overrides(run_dir, overrides)
    if (run_dir / "eval.json").is_file():
        return run_dir
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "compare_overrides.json").write_text(json.dumps(overrides))
    cmd = [sys.executable, str(ROOT / "experiments" / "train.py"), f"exploration={variant}", f"seed={seed}",
           "logger.progress_bar=false", *overrides]
    if (run_dir / "checkpoints" / "last.pt").is_file():
        cmd += [f"resume={run_dir}", f"hydra.run.dir={out / '.scratch' / run_dir.name}"]
    else:
        cmd += [f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "WANDB_MODE": os.environ.get("WANDB_MODE", "offline")}
    start = time.perf_counter()
    with open(out / f"{variant}-s{seed}.log", "a") as log:
        proc = subprocess.run(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        raise RuntimeError(f"{variant} seed {seed} failed (exit {proc.returncode}); see {out / (variant + f'-s{seed}.log')}")
    print(f"  done {variant} seed {seed} in {(time.perf_counter() - start) / 60:.1f} min", flush=True)
    return run_dir


def summarize(out: Path) -> dict:
    """Mean ± std over seeds of each variant's test metrics, from the finished runs in ``out``
    (all of them trained with the folder's ``overrides.json``; NaN values are reported as null and
    left out of the mean, ``n`` says how many entered it)."""
    table: dict[str, dict] = {}
    overrides = json.loads((out / "overrides.json").read_text()) if (out / "overrides.json").is_file() else None
    for eval_file in sorted(out.glob("*-s*/eval.json")):
        if overrides is not None:
            _check_overrides(eval_file.parent, overrides)
        variant, seed = eval_file.parent.name.rsplit("-s", 1)
        metrics = json.loads(eval_file.read_text())["metrics"]
        entry = table.setdefault(variant, {"seeds": [], **{m: [] for m in METRICS}})
        entry["seeds"].append(int(seed))
        for m in METRICS:
            entry[m].append(metrics[m])
    summary = {}
    for variant in [v for v in VARIANTS if v in table] + sorted(set(table) - set(VARIANTS)):
        entry = table[variant]
        row = {"seeds": entry["seeds"]}
        for m in METRICS:
            values = [v for v in entry[m] if not math.isnan(v)]
            row[m] = {"mean": statistics.fmean(values) if values else math.nan,
                      "std": statistics.stdev(values) if len(values) > 1 else math.nan, "n": len(values),
                      "values": [None if math.isnan(v) else v for v in entry[m]]}
        summary[variant] = row
    return summary


def format_summary(summary: dict) -> str:
    lines = [f"{'variant':<9} {'seeds':<7} {'success':>15} {'collision':>15} {'nav time (s)':>15} {'return':>17}"]
    for variant, row in summary.items():
        cells = [f"{row[m]['mean']:.3f} ± {row[m]['std']:.3f}" for m in METRICS[:3]]
        cells.append(f"{row['average_return']['mean']:.4f} ± {row['average_return']['std']:.4f}")
        seeds = ",".join(map(str, row["seeds"]))
        lines.append(f"{variant:<9} {seeds:<7} {cells[0]:>15} {cells[1]:>15} {cells[2]:>15} {cells[3]:>17}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    overrides: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, overrides = argv[:cut], argv[cut + 1:]
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--jobs", type=int, default=1, help="runs at a time (one thread each)")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "compare")
    p.add_argument("--summarize", type=Path, default=None, help="only aggregate the finished runs in this folder")
    args = p.parse_args(argv)
    if args.jobs < 1 or any(s < 0 for s in args.seeds):
        p.error("--jobs must be >= 1 and seeds >= 0")
    out = args.summarize or args.out
    if args.summarize is None:
        out.mkdir(parents=True, exist_ok=True)
        if (out / "overrides.json").is_file() and json.loads((out / "overrides.json").read_text()) != overrides:
            p.error(f"{out} holds runs with overrides {json.loads((out / 'overrides.json').read_text())}; use another --out")
        (out / "overrides.json").write_text(json.dumps(overrides))
        jobs = [(v, s) for s in args.seeds for v in args.variants]
        print(f"{len(jobs)} runs, {args.jobs} at a time, overrides {overrides} -> {out}", flush=True)
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            for future in [pool.submit(run_one, out, v, s, overrides) for v, s in jobs]:
                future.result()
    summary = summarize(out)
    if not summary:
        raise SystemExit(f"no finished runs (eval.json) under {out}")
    (out / "summary.json").write_text(json.dumps(summary, indent=1).replace("NaN", "null"))
    print(format_summary(summary))
    return summary


if __name__ == "__main__":
    main()
