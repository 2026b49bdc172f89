"""Digests of fixed-seed smoke runs' ``scalars.jsonl``: proof that a refactor changed no output.

Trains ``preset=smoke`` (seed 0, one thread, SARL encoder, no compilation) for each exploration
variant, and for ε-greedy with counterfactual experience and Polyak targets on, and prints one
SHA-256 per run of its ``scalars.jsonl`` rows without the ``time/`` columns (wall-clock) plus its
final test's ``eval.json`` records. Run it before and after a change, on the same machine::

    python experiments/smoke_digest.py --json before.json
    git checkout <new> && python experiments/smoke_digest.py --json after.json
    diff before.json after.json      # no output: every logged scalar is bit-identical

The old commit can run from a ``git worktree`` (``cd <worktree> && python experiments/smoke_digest.py``,
with that worktree's ``src`` first on ``PYTHONPATH``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
VARIANTS: dict[str, list[str]] = {
    "egreedy": ["exploration=egreedy", "learner=plain"],
    "noisy": ["exploration=noisy", "learner=plain"],
    "dropout": ["exploration=dropout", "learner=plain"],
    "icm": ["exploration=icm", "learner=plain"],
    "re3": ["exploration=re3", "learner=plain"],
    "egreedy-counterfactual-polyak": ["exploration=egreedy", "learner=recommended"],
}
COMMON = ["preset=smoke", "seed=0", "threads=1", "encoder=sarl", "env.num_humans=5", "env.orca_backend=eager",
          "logger=csv"]


def digest(run_dir: Path) -> str:
    """SHA-256 of the run's scalar rows (``time/`` columns dropped, keys sorted) and its test records."""
    rows = []
    for line in (run_dir / "scalars.jsonl").read_text(encoding="utf-8").splitlines():
        row = json.loads(line)
        rows.append({k: v for k, v in row.items() if not k.startswith("time/")})
    records = json.loads((run_dir / "eval.json").read_text(encoding="utf-8")) if (run_dir / "eval.json").exists() else None
    text = json.dumps({"rows": rows, "test": records}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def run_variant(name: str, overrides: list[str], root: Path) -> tuple[str, int]:
    run_dir = root / name
    cmd = [sys.executable, str(HERE / "train.py"), *COMMON, *overrides, f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "WANDB_MODE": "offline"})
    if proc.returncode != 0:
        raise SystemExit(f"{name}: train.py failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    rows = len((run_dir / "scalars.jsonl").read_text(encoding="utf-8").splitlines())
    return digest(run_dir), rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--json", type=Path, help="also write {variant: digest} here")
    args = parser.parse_args(argv)
    out: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as tmp:
        print(f"{'variant':<32} {'rows':>5}  digest")
        for name in args.variants:
            out[name], rows = run_variant(name, VARIANTS[name], Path(tmp))
            print(f"{name:<32} {rows:>5}  {out[name]}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
