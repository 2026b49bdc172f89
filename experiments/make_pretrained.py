"""Publish a trained run as a pretrained agent: ``pretrained/<name>/`` with its ``best.pt``, its
``config.yaml`` and ``eval.json`` (the agent on 1000 test cases of test seed 0 per scenario, evaluated
from the copied file exactly as ``evaluate.py`` does), then rewrite ``pretrained/README.md``, the index
of every agent there.

The scenarios (``--scenarios``) default to the ones the run trained on, plus square for an agent
trained on circle (the paper's zero-shot transfer): circle and square for the open-space agents, the
obstacle scenario for a specialist, all five for a generalist (``env.mix``).

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
ORDER = ("circle", "square", "corridor", "doorway", "room")  # the index's columns (others follow, sorted)


def default_scenarios(run) -> list[str]:
    """The scenarios ``run`` (a RunConfig) trained on, plus square after circle (the paper's zero-shot transfer)."""
    from crowdrl.training.config import trained_scenarios

    trained = list(trained_scenarios(run))
    if "circle" in trained and "square" not in trained:
        trained.insert(trained.index("circle") + 1, "square")
    return trained


def publish(run_dir: Path, name: str, episodes: int = 1000, scenarios: list[str] | None = None) -> list[dict]:
    from crowdrl.evaluation.report import write_records
    from crowdrl.training.checkpoint import checkpoint_path, load_trained_network
    from crowdrl.agents import evaluate_spec

    run, _, _ = load_trained_network(run_dir)  # refuses a missing, unsafe, foreign or non-finite checkpoint first
    out = PRETRAINED / name
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(checkpoint_path(run_dir), out / "best.pt")
    shutil.copyfile(run_dir / "config.yaml", out / "config.yaml")
    records = []
    for scenario in scenarios or default_scenarios(run):
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
             "`weights_only=True`), the run's `config.yaml` and `eval.json`: the agent on 1000 test cases of test seed 0",
             "per scenario, those it was trained on (square is zero-shot for the agents trained on circle). A cell is",
             "success (collisions); \"–\": not evaluated there. Check one from a clone:",
             "", "```bash",
             ".venv/bin/python experiments/evaluate.py checkpoint=pretrained/<name> env=square   # reproduces eval.json",
             ".venv/bin/python experiments/check_pretrained.py   # every agent on every recorded scenario, compared",
             "```", "",
             "On the machine that wrote them the records come back to every digit. On another CPU the kernels",
             "round differently, so a path can drift by a step in a few episodes: for",
             "`sgd3qn-planning-egreedy-episodes-s0` on square, one such machine gave the same outcomes (success",
             "0.951) and a navigation time of 11.8817 s against the recorded 11.8825 s.", "",
             "Written by `experiments/make_pretrained.py <run folder> <name>` (2-core CPU).", ""]
    agents = {folder.name: {r["scenario"]: r for r in read_eval_records(folder / "eval.json")}
              for folder in sorted(p.parent for p in PRETRAINED.glob("*/eval.json"))}
    seen = {name for recs in agents.values() for name in recs}
    columns = [name for name in ORDER if name in seen] + sorted(seen - set(ORDER))
    rows = []
    for name, recs in agents.items():
        first = next(iter(recs.values()))
        cells = [f"{recs[c]['success_rate']:.3f} ({recs[c]['collision_rate']:.3f})" if c in recs else "–"
                 for c in columns]
        rows.append([f"`{name}`", f"`{first['trained_in']}`", first["checkpoint_frames"], *cells])
    lines.append(markdown_table(["agent", "trained in", "frames of best.pt", *columns], rows))
    atomic_write_bytes(PRETRAINED / "README.md", ("\n".join(lines) + "\n").encode())


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="a finished run folder (its checkpoints/best.pt and config.yaml)")
    p.add_argument("name", help="the agent's folder name under pretrained/")
    p.add_argument("--episodes", type=int, default=1000, help="test cases per scenario")
    p.add_argument("--scenarios", nargs="+", default=None,
                   help="where to evaluate it (default: the scenarios it trained on, and square after circle)")
    args = p.parse_args(argv)
    from crowdrl.training import CheckpointError

    if not (args.run / "config.yaml").exists():
        print(f"make_pretrained.py: run: {args.run} holds no config.yaml (not a run folder)", file=sys.stderr)
        raise SystemExit(2)
    if not args.name or "/" in args.name or args.name.startswith("."):
        print(f"make_pretrained.py: name: {args.name!r} must be a plain folder name", file=sys.stderr)
        raise SystemExit(2)
    try:
        publish(args.run, args.name, args.episodes, args.scenarios)
    except CheckpointError as exc:
        print(f"make_pretrained.py: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    write_index()


if __name__ == "__main__":
    main()
