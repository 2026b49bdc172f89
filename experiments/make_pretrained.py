"""Publish a trained run as a pretrained agent: ``pretrained/<name>/`` with its ``best.pt``, its
``config.yaml`` and ``eval.json`` (the agent on the 1000 circle and 1000 square test cases of test
seed 0, evaluated from the copied file exactly as ``evaluate.py`` does), then rewrite
``pretrained/README.md``, the index of every agent there.

    python experiments/make_pretrained.py results/episodes-planning/runs/egreedy-s0 sgd3qn-planning-egreedy-episodes-s0
    python experiments/evaluate.py checkpoint=pretrained/sgd3qn-planning-egreedy-episodes-s0 env=square   # checks it
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

os.environ.setdefault("WANDB_MODE", "offline")
ROOT = Path(__file__).resolve().parents[1]
PRETRAINED = ROOT / "pretrained"
SCENARIOS = ("circle", "square")


def publish(run_dir: Path, name: str, episodes: int = 1000) -> list[dict]:
    from crowdrl.evaluation.report import write_records
    from crowdrl.training.checkpoint import checkpoint_path, load_trained_network
    from crowdrl.agents import evaluate_spec

    load_trained_network(run_dir)  # refuses a missing, unsafe, foreign or non-finite checkpoint first
    out = PRETRAINED / name
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(checkpoint_path(run_dir), out / "best.pt")
    shutil.copyfile(run_dir / "config.yaml", out / "config.yaml")
    records = []
    for scenario in SCENARIOS:
        record, _ = evaluate_spec(checkpoint=out, scenario=scenario, episodes=episodes)
        records.append({**record, "checkpoint": f"pretrained/{name}/best.pt", "trained_in": str(run_dir)})
        print(f"{name} on {scenario}: success {record['success_rate']:.3f}", flush=True)
    write_records(out, records)
    (out / "eval.csv").unlink(missing_ok=True)  # eval.json is the record; the index below is the table
    return records


def write_index() -> None:
    from crowdrl.evaluation.report import read_eval_records
    from crowdrl.files import atomic_write_bytes
    from crowdrl.tables import markdown_table

    lines = ["# Pretrained agents", "",
             "Each folder holds `best.pt` (the best validation checkpoint of a training run, loaded with",
             "`weights_only=True`), the run's `config.yaml` and `eval.json`: the agent on the 1000 circle and 1000",
             "square test cases of test seed 0 (trained on circle; square is zero-shot). Check one from a clone:",
             "", "```bash",
             ".venv/bin/python experiments/evaluate.py checkpoint=pretrained/<name> env=square   # reproduces eval.json",
             ".venv/bin/python experiments/check_pretrained.py   # every agent on every recorded scenario, compared",
             "```", "",
             "On the machine that wrote them the records come back to every digit. On another CPU the kernels",
             "round differently, so a path can drift by a step in a few episodes: for",
             "`sgd3qn-planning-egreedy-episodes-s0` on square, one such machine gave the same outcomes (success",
             "0.951) and a navigation time of 11.8817 s against the recorded 11.8825 s.", "",
             "Written by `experiments/make_pretrained.py <run folder> <name>` (2-core CPU).", ""]
    rows = []
    for folder in sorted(p.parent for p in PRETRAINED.glob("*/eval.json")):
        recs = {r["scenario"]: r for r in read_eval_records(folder / "eval.json")}
        c, s = recs["circle"], recs["square"]
        rows.append([f"`{folder.name}`", f"`{c['trained_in']}`", c["checkpoint_frames"], f"{c['success_rate']:.3f}",
                     f"{s['success_rate']:.3f}", f"{c['collision_rate']:.3f}", f"{s['collision_rate']:.3f}"])
    lines.append(markdown_table(["agent", "trained in", "frames of best.pt", "circle success", "square success",
                                 "circle collision", "square collision"], rows))
    atomic_write_bytes(PRETRAINED / "README.md", ("\n".join(lines) + "\n").encode())


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="a finished run folder (its checkpoints/best.pt and config.yaml)")
    p.add_argument("name", help="the agent's folder name under pretrained/")
    p.add_argument("--episodes", type=int, default=1000, help="test cases per scenario")
    args = p.parse_args(argv)
    from crowdrl.training import CheckpointError

    if not (args.run / "config.yaml").exists():
        print(f"make_pretrained.py: run: {args.run} holds no config.yaml (not a run folder)", file=sys.stderr)
        raise SystemExit(2)
    if not args.name or "/" in args.name or args.name.startswith("."):
        print(f"make_pretrained.py: name: {args.name!r} must be a plain folder name", file=sys.stderr)
        raise SystemExit(2)
    try:
        publish(args.run, args.name, args.episodes)
    except CheckpointError as exc:
        print(f"make_pretrained.py: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    write_index()


if __name__ == "__main__":
    main()
