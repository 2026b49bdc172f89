"""The walk of the run config through the code: which crowdrl modules read its fields, in order, during one tiny
``run_training`` (train 64 frames, validate, test 2 cases).

Every read of a ``RunConfig`` section's field from a ``crowdrl`` module is recorded (module, function). Printed:
the reads, the module visits (consecutive reads by one module merged) and how many of them re-enter a module
the walk had left, the same per function, the most visited, and where the crowd config is built
(``crowd_config``) and the obstacle question asked (``sees_obstacles``), per caller. Compare two commits by
running it with each one's ``src`` first on ``PYTHONPATH`` (a ``git worktree``).

    python experiments/config_walk.py            # add --json for the numbers alone
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import sys
import tempfile

import torch

TINY = {"preset": "smoke", "seed": 0, "env": {"num_humans": 4, "orca_backend": "eager"}, "encoder": {"name": "sarl"},
        "logger": {"name": "csv", "progress_bar": False, "render": False},
        "train": {"num_envs": 4, "steps_per_batch": 8, "total_frames": 64, "warmup_frames": 32, "batch_size": 16,
                  "buffer_size": 1000, "val_every_frames": 64, "val_episodes": 2, "checkpoint_every_frames": 64,
                  "test_episodes": 2, "compile_acting": False, "compile_loss": False}}


def visits(seq: list[str]) -> tuple[int, int, collections.Counter]:
    """``(visits, re-entries, visits per name)`` of a sequence with consecutive repeats merged."""
    merged = [k for i, k in enumerate(seq) if i == 0 or seq[i - 1] != k]
    seen: set[str] = set()
    back = 0
    for k in merged:
        back += k in seen
        seen.add(k)
    return len(merged), back, collections.Counter(merged)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print the numbers as JSON")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from crowdrl.training import config as config_module
    from crowdrl.training import validate
    from crowdrl.training.pipeline import run_training

    run = validate(TINY)
    sections = {type(run)} | {type(getattr(run, f.name)) for f in dataclasses.fields(run)
                              if dataclasses.is_dataclass(getattr(run, f.name))}
    names = {f.name for c in sections for f in dataclasses.fields(c)}
    reads: list[tuple[str, str]] = []
    built: collections.Counter = collections.Counter()

    def reading(self, name):  # noqa: ANN001, ANN202
        if name in names:
            frame = sys._getframe(1)
            module = frame.f_globals.get("__name__", "?")
            if module.startswith("crowdrl"):
                reads.append((module, frame.f_code.co_name))
        return object.__getattribute__(self, name)

    def counted(fn, what):  # noqa: ANN001, ANN202
        def wrapper(*a, **k):  # noqa: ANN002, ANN003, ANN202
            frame = sys._getframe(1)
            built[f"{what} <- {frame.f_globals['__name__']}.{frame.f_code.co_name}"] += 1
            return fn(*a, **k)
        return wrapper

    originals = {name: getattr(config_module, name) for name in ("crowd_config", "sees_obstacles")}
    patched = []
    for module in [m for m in list(sys.modules.values()) if getattr(m, "__name__", "").startswith("crowdrl")]:
        for name, fn in originals.items():
            if getattr(module, name, None) is fn:
                setattr(module, name, counted(fn, name))
                patched.append((module, name, fn))
    for cls in sections:
        cls.__getattribute__ = reading
    try:
        with tempfile.TemporaryDirectory() as folder:
            run_training(run, folder)
    finally:
        for cls in sections:
            del cls.__getattribute__
        for module, name, fn in patched:
            setattr(module, name, fn)
    n, back, per_module = visits([m for m, _ in reads])
    nf, backf, per_function = visits([f"{m}.{f}" for m, f in reads])
    out = {"reads": len(reads), "module_visits": n, "modules_reentered": back, "function_visits": nf,
           "functions_reentered": backf, "most_visited_modules": per_module.most_common(6),
           "built_by": dict(sorted(built.items()))}
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"{len(reads)} reads of the run config; {n} module visits, {back} re-entering a module already left; "
          f"{nf} function visits, {backf} re-entering")
    print("most visited modules: " + ", ".join(f"{m} {c}" for m, c in per_module.most_common(6)))
    for key, count in sorted(built.items()):
        print(f"  {count} x {key}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
