"""Time to quality: training minutes on one core until a learner's network reaches a test success rate.

Trains each learner x seed at a preset's budget with ``train.keep_val_checkpoints=true`` (every
validation keeps its network and the run's timers then; killed runs resume, finished ones are skipped),
then tests the kept networks in training order on the scenario's test cases (test seed 0) until the
first one whose test success reaches ``--target``. Its minutes are the run's own timers when it was
kept (collection + updates + validation, as in ``counterfactual_ablation.py``); compiling and the test
itself are not counted.

Only networks whose validation success reached ``--screen`` are tested (a 100-episode validation below
0.90 is far from a 0.95 test); the table says how many were tested. A run that never reaches the target
shows its whole training minutes as a lower bound (``> m``) and the best test success it reached.

    python experiments/time_to_quality.py --out results/time-to-quality --jobs 2
    python experiments/time_to_quality.py --out results/time-to-quality --table-only
    python experiments/time_to_quality.py --out /tmp/ttq --preset smoke --seeds 0 --episodes 20 --target 0.1
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
from crowdrl.training.checkpoint import load_checkpoint, val_checkpoints
from crowdrl.training.pipeline import completed_summary

ROOT = Path(__file__).resolve().parent.parent
LEARNERS = ("recommended", "plain", "paper")  # conf/learner/: the default, the default before issue 50, the paper's
BASE = ["logger=csv", "logger.progress_bar=false", "logger.render=false", "threads=1", "train.compile_acting=true",
        "train.keep_val_checkpoints=true", "train.test_episodes=100"]  # its own test is not what this measures
RECORD = "time_to_quality.json"  # per run: each tested network's frames, minutes, validation and test success


def run_one(folder: Path, learner: str, seed: int, preset: str, scenario: str, extra: list[str]) -> int:
    """Train one run to its budget (resuming a killed one, skipping a finished one); its exit code."""
    return train_to_completion(folder, [f"seed={seed}", f"preset={preset}", f"learner={learner}", f"env={scenario}",
                                        *BASE, *extra], cwd=ROOT)


def minutes_trained(timers: dict[str, float]) -> float:
    """A run's training minutes from its timers (collection, updates, validation, demonstrations)."""
    return sum(timers.values()) / 60


def test_run(folder: Path, scenario: str, episodes: int, target: float, screen: float) -> dict:
    """Test ``folder``'s kept networks in training order until one reaches ``target``; each tested network is
    recorded in ``<folder>/time_to_quality.json`` as it is done (a rerun goes on from there)."""
    import torch

    from crowdrl.agents import evaluate_spec

    torch.set_num_threads(1)
    path = folder / RECORD
    done = json.loads(path.read_text()) if path.exists() else {}
    settings = {"scenario": scenario, "episodes": episodes, "target": target, "screen": screen}
    if done.get("settings") != settings:  # another test: start again
        done = {"settings": settings, "tested": {}}
    for ckpt in val_checkpoints(folder):
        data = load_checkpoint(ckpt)  # a truncated or foreign file is refused naming it
        entry = {"frames": int(data["frames"]), "minutes": minutes_trained(data["timers_s"]),
                 "val_success": float(data["val"]["success_rate"])}
        if entry["val_success"] < screen:
            continue
        if ckpt.name not in done["tested"]:
            record, _ = evaluate_spec(checkpoint=ckpt, scenario=scenario, episodes=episodes)
            done["tested"][ckpt.name] = {**entry, "test_success": record["success_rate"]}
            atomic_write_json(path, done)
        if done["tested"][ckpt.name]["test_success"] >= target:
            break
    atomic_write_json(path, done)
    return done


def time_to_target(tested: list[dict], target: float, whole_minutes: float) -> dict:
    """The first of the ``tested`` networks (``time_to_quality.json`` entries) whose test success reaches
    ``target``: its minutes and frames; none reaching it, the whole run's minutes as a lower bound."""
    tested = sorted(tested, key=lambda e: e["frames"])
    first = next((e for e in tested if e["test_success"] >= target), None)
    return {"reached": first is not None, "minutes": first["minutes"] if first else whole_minutes,
            "frames": first["frames"] if first else None, "test_success": first["test_success"] if first else None,
            "best_test": max((e["test_success"] for e in tested), default=None), "tested": len(tested),
            "whole_minutes": whole_minutes}


def summarise(folder: Path, target: float) -> dict | None:
    """A finished and tested run's :func:`time_to_target`; ``None`` before."""
    summary = completed_summary(folder)
    if summary is None or not (folder / RECORD).exists():
        return None
    tested = list(json.loads((folder / RECORD).read_text())["tested"].values())
    return time_to_target(tested, target, minutes_trained(summary["timers_s"]))


def table(out: Path, learners: list[str], seeds: list[int], target: float) -> str:
    """``table.md`` and ``table.json`` in ``out``: per learner, minutes (and frames) to the target, over seeds."""
    rows, records = [], {}
    for learner in learners:
        runs = [summarise(out / "runs" / f"{learner}-s{seed}", target) for seed in seeds]
        records[learner] = dict(zip(map(str, seeds), runs))
        have = [r for r in runs if r is not None]
        if not have:
            continue
        minutes = [f"{r['minutes']:.1f}" if r["reached"] else f"> {r['minutes']:.1f}" for r in have]
        reached = [r for r in have if r["reached"]]
        mean = f"{np.mean([r['minutes'] for r in reached]):.1f}" if len(reached) == len(have) else "–"
        frames = ", ".join(f"{r['frames'] // 1000}" if r["reached"] else "never" for r in have)
        best = ", ".join("–" if r["best_test"] is None else f"{r['best_test']:.3f}" for r in have)
        rows.append([learner, f"{len(reached)}/{len(have)}", f"{mean} ({', '.join(minutes)})", frames, best,
                     ", ".join(f"{r['tested']}" for r in have), ", ".join(f"{r['whole_minutes']:.1f}" for r in have)])
    text = markdown_table(["learner", f"seeds reaching {target}", f"minutes to test >= {target}",
                           "k frames there", "best test success tested", "networks tested", "whole run minutes"], rows)
    atomic_write_bytes(out / "table.md", (text + "\n").encode())
    atomic_write_json(out / "table.json", {"target": target, "seeds": seeds, "runs": records})
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--preset", default="demo200k", help="the budget every run trains at (conf/preset/)")
    ap.add_argument("--scenario", default="circle")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--learners", nargs="+", default=["recommended", "plain"], choices=LEARNERS)
    ap.add_argument("--target", type=float, default=0.95, help="the test success rate to reach")
    ap.add_argument("--screen", type=float, default=0.90, help="test only networks whose validation reached this")
    ap.add_argument("--episodes", type=int, default=1000, help="test cases per tested network (test seed 0)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--test-run", type=Path, help=argparse.SUPPRESS)  # one run's tests, in a process of its own
    ap.add_argument("--json", action="store_true", help="print table.json instead of the table")
    ap.add_argument("extra", nargs="*", help="Hydra overrides given to every new run")
    args = ap.parse_args(argv)
    for name, value in (("--target", args.target), ("--screen", args.screen)):
        if not 0 <= value <= 1:
            ap.error(f"{name}: must lie in [0, 1], got {value}")
    for name, value in (("--jobs", args.jobs), ("--episodes", args.episodes)):
        if value < 1:
            ap.error(f"{name}: must be >= 1, got {value}")
    if args.test_run is not None:
        test_run(args.test_run, args.scenario, args.episodes, args.target, args.screen)
        return 0
    (args.out / "runs").mkdir(parents=True, exist_ok=True)
    failed: list[str] = []
    if not args.table_only:
        order = [(learner, seed) for seed in args.seeds for learner in args.learners]  # partial results stay balanced

        def train_and_test(item: tuple[str, int]) -> int:
            folder = args.out / "runs" / f"{item[0]}-s{item[1]}"
            code = run_one(folder, item[0], item[1], args.preset, args.scenario, args.extra)
            if code == 0:
                cmd = [sys.executable, __file__, "--out", str(args.out), "--test-run", str(folder), "--scenario",
                       args.scenario, "--episodes", str(args.episodes), "--target", str(args.target),
                       "--screen", str(args.screen)]
                with open(folder.parent / f"{folder.name}.log", "ab") as log:
                    code = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)
            if code != 0:
                failed.append(str(folder))
            return code

        start = time.time()
        with ThreadPoolExecutor(args.jobs) as pool:
            list(pool.map(train_and_test, order))
        print(f"{len(order) - len(failed)}/{len(order)} runs trained and tested in {(time.time() - start) / 60:.0f} min"
              + (f"; failed: {', '.join(failed)}" if failed else ""))
    text = table(args.out, args.learners, args.seeds, args.target)
    print(dumps_json(json.loads((args.out / "table.json").read_text())) if args.json else text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
