"""Counterfactual experience, ablated on validation: trains each setting x seed at a preset's budget
(resuming killed runs, skipping finished ones) and tabulates what the runs logged on their validation
episodes (never the test cases).

Per setting, over seeds: the best validation success, the mean of the last 5 validations, the
validations that fell more than 0.2 below the run's running best (collapses), and the frames and
training minutes (collection + updates + validation, from the run's own timers) to the first
validation >= 0.90; completed runs only (unfinished ones are counted apart, with their frames).

    python experiments/counterfactual_ablation.py --out results/counterfactual-ablation --jobs 2
    python experiments/counterfactual_ablation.py --out results/counterfactual-ablation --table-only
    python experiments/counterfactual_ablation.py --out /tmp/cf --preset smoke --seeds 0 --settings off top5
    python experiments/counterfactual_ablation.py --out results/counterfactual-levers --jobs 2 \
        --settings off top5 top5-polyak top5-huber top5-clip top5-lrdecay top5-layernorm  # levers beside top5

``--test circle square`` then evaluates every finished run's best checkpoint on the 1000 test cases of
each scenario (test seed 0) into ``<run>/eval-<scenario>/eval.json``, for ``compare_runs.py``; settings
are chosen on the validation table above, the test is for the final comparison only.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from crowdrl.files import atomic_write_bytes, atomic_write_json, dumps_json
from crowdrl.reproduction.plan import train_to_completion
from crowdrl.tables import markdown_table

ROOT = Path(__file__).resolve().parent.parent
SETTINGS = {  # name -> train.counterfactual overrides
    "off": {"mode": "off"},
    "top5": {"mode": "second_update", "actions": "topk", "k": 5},  # upstream SG-D3QN's
    "merged5": {"mode": "merged", "actions": "topk", "k": 5, "weight": 0.5},
    "random5": {"mode": "second_update", "actions": "random", "k": 5},
    "all81": {"mode": "second_update", "actions": "all"},
    # top5 with one stability lever each (train.* keys, off in BASE's plain learner)
    "top5-polyak": {"mode": "second_update", "actions": "topk", "k": 5},
    "top5-huber": {"mode": "second_update", "actions": "topk", "k": 5},
    "top5-clip": {"mode": "second_update", "actions": "topk", "k": 5},
    "top5-lrdecay": {"mode": "second_update", "actions": "topk", "k": 5},
    "top5-layernorm": {"mode": "second_update", "actions": "topk", "k": 5},
}
LEVERS = {  # setting -> the other train.* overrides it adds
    "top5-polyak": ["train.target_tau=0.005"],  # about the hard copy's horizon: 1/0.005 = 200 updates of memory
    "top5-huber": ["train.huber_delta=1.0"],
    "top5-clip": ["train.grad_clip_norm=10.0"],
    "top5-lrdecay": ["train.lr_end=0.0001"],  # 1e-3 -> 1e-4 over the run
    "top5-layernorm": ["train.q_layer_norm=true"],
}
# learner=plain: no counterfactual experience, hard target copies (the default before issue 50, with which
# results/counterfactual-* were trained); each setting then sets its own keys over it
BASE = ["learner=plain", "logger=csv", "logger.progress_bar=false", "logger.render=false", "train.compile_acting=true",
        "train.test_episodes=100"]  # the test is not what this compares: validation only
THRESHOLD, LAST, COLLAPSE = 0.90, 5, 0.2


def overrides(setting: str) -> list[str]:
    return [f"train.counterfactual.{k}={v}" for k, v in SETTINGS[setting].items()] + LEVERS.get(setting, [])


def run_one(folder: Path, setting: str, seed: int, preset: str, extra: list[str]) -> tuple[str, int]:
    """Train one run to completion (resume when it has a checkpoint); returns (folder, exit code)."""
    return str(folder), train_to_completion(folder, [f"seed={seed}", f"preset={preset}", *BASE, *overrides(setting),
                                                     *extra], cwd=ROOT)


def test_run(folder: Path, scenario: str) -> int:
    """``evaluate.py`` of a finished run's best checkpoint on ``scenario``'s 1000 test cases (skipped when done)."""
    out = folder / f"eval-{scenario}"
    if (out / "eval.json").exists():
        return 0
    cmd = [sys.executable, str(ROOT / "experiments" / "evaluate.py"), f"checkpoint={folder}", f"env={scenario}",
           f"hydra.run.dir={out}"]
    with open(folder.parent / f"{folder.name}.log", "ab") as log:
        return subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)


def validations(folder: Path) -> tuple[list[tuple[int, float]], list[tuple[int, float]]]:
    """``(frames, val success)`` and ``(frames, training seconds)`` rows of a run's scalars.jsonl."""
    vals, times = [], []
    path = folder / "scalars.jsonl"
    if not path.exists():
        return vals, times
    for line in path.read_text().splitlines():
        row = json.loads(line)
        if row.get("kind") == "val":
            vals.append((row["frames"], row["val/success_rate"]))
        elif row.get("kind") == "train" and "time/update_s" in row:
            times.append((row["frames"], row["time/collect_s"] + row["time/update_s"] + row["time/validate_s"]))
    return vals, times


def summarise(folder: Path) -> dict | None:
    vals, times = validations(folder)
    if not vals:
        return None
    success = [s for _, s in vals]
    best_so_far = np.maximum.accumulate(success)
    first = next((f for f, s in vals if s >= THRESHOLD), None)
    minutes = None
    if first is not None and times:  # the training time logged at (or just after) that validation
        after = [t for f, t in times if f >= first]
        minutes = (after[0] if after else times[-1][1]) / 60
    status = json.loads((folder / "status.json").read_text()) if (folder / "status.json").exists() else {}
    return {"frames": vals[-1][0], "state": status.get("state"), "resumed": status.get("resumed_from") is not None,
            "best": max(success), "last5": float(np.mean(success[-LAST:])),
            "collapses": int(sum(b - s > COLLAPSE for b, s in zip(best_so_far, success))),
            "late_drop": float(max((b - s for (f, s), b in zip(vals, best_so_far) if f > 0.5 * vals[-1][0]), default=0)),
            "frames_to_90": first, "minutes_to_90": minutes,
            "update_s": times[-1][1] if times else None}


def fmt(values: list, digits: int) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "–"
    mean = float(np.mean(values))
    return f"{mean:.{digits}f} ({', '.join(f'{v:.{digits}f}' for v in values)})"


def table(out: Path, settings: list[str], seeds: list[int]) -> str:
    rows, records = [], {}
    for setting in settings:
        runs = {seed: summarise(out / "runs" / f"{setting}-s{seed}") for seed in seeds}
        records[setting] = runs
        # a run still training (or killed before its end) is counted apart, not averaged in
        done = [r for r in runs.values() if r is not None and r["state"] == "completed"]
        unfinished = [r for r in runs.values() if r is not None and r["state"] != "completed"]
        if not done:
            continue
        reach = [r["frames_to_90"] for r in done]
        later = f"; {len(unfinished)} unfinished ({', '.join(str(r['frames'] // 1000) + 'k' for r in unfinished)})"
        rows.append([setting, f"{len(done)} ({', '.join(str(r['frames'] // 1000) + 'k' for r in done)})"
                     + (later if unfinished else ""),
                     fmt([r["best"] for r in done], 2), fmt([r["last5"] for r in done], 3),
                     str(sum(r["collapses"] for r in done)), fmt([r["late_drop"] for r in done], 2),
                     fmt([f / 1000 if f is not None else None for f in reach], 0) + f" [{sum(f is None for f in reach)} never]",
                     fmt([r["minutes_to_90"] for r in done], 1)])
    header = ["setting", "runs (frames)", "best val.", f"mean last {LAST} val.", f"collapses (>{COLLAPSE})",
              "largest drop, 2nd half", f"k frames to val. >= {THRESHOLD}", f"train minutes to val. >= {THRESHOLD}"]
    text = markdown_table(header, rows) + "\n"
    atomic_write_bytes(out / "table.md", text.encode())
    levers = {s: LEVERS[s] for s in settings if s in LEVERS}
    atomic_write_json(out / "table.json", {"settings": {s: SETTINGS[s] for s in settings},
                                           **({"levers": levers} if levers else {}), "seeds": seeds,
                                           "base": BASE, "runs": records})
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--settings", nargs="+", default=["off", "top5", "merged5", "random5"], choices=sorted(SETTINGS))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--test", nargs="*", default=[], metavar="SCENARIO",
                    help="evaluate every finished run on these scenarios' 1000 test cases (for compare_runs.py)")
    ap.add_argument("--json", action="store_true", help="print table.json instead of the table")
    ap.add_argument("extra", nargs="*", help="Hydra overrides given to every new run")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs: must be >= 1, got {args.jobs}")
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    failed: list[str] = []
    if not args.table_only:
        order = [(seed, s) for seed in args.seeds for s in args.settings]  # seed by seed: partial results stay balanced
        start = time.time()
        with ThreadPoolExecutor(args.jobs) as pool:
            results = list(pool.map(lambda item: run_one(args.out / "runs" / f"{item[1]}-s{item[0]}", item[1],
                                                         item[0], args.preset, args.extra), order))
        failed = [f for f, code in results if code != 0]
        print(f"{len(results) - len(failed)}/{len(results)} runs finished in {(time.time() - start) / 60:.0f} min"
              + (f"; failed: {', '.join(failed)}" if failed else ""))
    if args.test:
        done = [args.out / "runs" / f"{s}-s{seed}" for seed in args.seeds for s in args.settings]
        done = [f for f in done if (f / "status.json").exists()
                and json.loads((f / "status.json").read_text()).get("state") == "completed"]
        jobs = [(f, scenario) for f in done for scenario in args.test]
        with ThreadPoolExecutor(args.jobs) as pool:
            codes = list(pool.map(lambda job: test_run(*job), jobs))
        failed += [f"{f}/eval-{sc}" for (f, sc), code in zip(jobs, codes) if code != 0]
    text = table(args.out, args.settings, args.seeds)
    print(dumps_json(json.loads((args.out / "table.json").read_text())) if args.json else text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
