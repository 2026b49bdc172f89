"""Check an exported policy against its checkpoint on the test cases: success of each, and on every step
of the torch policy's own trajectories whether the ONNX model's action is identical (docs/export.md).

    python experiments/onnx_agreement.py pretrained/<agent> --scenarios circle square --episodes 1000
    python experiments/onnx_agreement.py runs/<folder> --model policy.onnx --json agreement.json

Exports the checkpoint's acting policy (its planner, when it has one) to a temporary file unless
``--model`` names one, then per scenario: the checkpoint's torch policy through ``evaluate`` (the
exported model asked the same observation at every step of running episodes: identical, differing by
float rounding, i.e. its scores of the two actions within 1e-4, or otherwise), and the exported model
through ``evaluate.py``'s ONNX path (``checkpoint=<file>.onnx``). Prints a table (or JSON) and exits 1
when a scenario misses the targets (``--max-success-gap`` 0.005, ``--min-identical`` 0.999). One torch
and one onnxruntime thread. A bad argument exits 2 with one line naming it; nothing is written but
``--json``'s file.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import NoReturn

from crowdrl.sim.config import SCENARIOS


def fail(message: str) -> NoReturn:
    print(f"onnx_agreement.py: {message}", file=sys.stderr)
    raise SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a run folder, a .pt file or pretrained/<agent>")
    p.add_argument("--model", help="the exported .onnx model of the checkpoint (default: export one to a temp file)")
    p.add_argument("--scenarios", nargs="+", default=None, help="default: the checkpoint's scenario")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--batch", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0, help="test stream seed")
    p.add_argument("--max-success-gap", type=float, default=0.005)
    p.add_argument("--min-identical", type=float, default=0.999)
    p.add_argument("--json", help="also write the results to this file")
    a = p.parse_args(argv)
    for name, value in (("--episodes", a.episodes), ("--batch", a.batch)):
        if value < 1:
            fail(f"{name}: must be >= 1, got {value}")
    bad = [s for s in a.scenarios or [] if s not in SCENARIOS]
    if bad:
        fail(f"--scenarios: unknown {', '.join(bad)}; allowed: {', '.join(SCENARIOS)}")
    if a.model is not None and not Path(a.model).is_file():
        fail(f"--model: no file at {a.model}")
    if a.json is not None:
        from crowdrl.export import check_writable

        try:
            check_writable(a.json, "--json")
        except ValueError as exc:
            fail(str(exc))

    import torch

    from crowdrl.export import export_onnx, read_exported
    from crowdrl.agents import compare_on_test_cases
    from crowdrl.training import CheckpointError

    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        try:
            model = Path(a.model) if a.model else export_onnx(a.checkpoint, Path(tmp) / "policy.onnx").path
            read_exported(model)
        except CheckpointError as exc:
            fail(f"{'--model' if a.model and str(a.model) in str(exc) else 'checkpoint'}: {exc}")
        except ValueError as exc:
            fail(str(exc))
        for scenario in a.scenarios or [None]:
            began = time.perf_counter()
            try:
                r = compare_on_test_cases(a.checkpoint, model, scenario=scenario, seed=a.seed, episodes=a.episodes,
                                          batch=a.batch)
            except (ValueError, CheckpointError) as exc:
                fail(str(exc))
            r["seconds"] = round(time.perf_counter() - began, 1)
            r["success_gap"] = abs(r["onnx"]["success_rate"] - r["torch"]["success_rate"])
            r["identical_share"] = r["identical"] / max(r["steps"], 1)
            r["ok"] = r["success_gap"] <= a.max_success_gap and r["identical_share"] >= a.min_identical
            rows.append(r)
            print(f"{r['scenario']}: {r['episodes']} cases, success torch {r['torch']['success_rate']:.3f} onnx "
                  f"{r['onnx']['success_rate']:.3f}; steps {r['steps']}: identical {r['identical']} "
                  f"({100 * r['identical_share']:.3f} %), rounding {r['rounding']}, differ {r['differ']} "
                  f"[{r['seconds']} s]{'' if r['ok'] else '  MISSES THE TARGETS'}", flush=True)
    result = {"checkpoint": a.checkpoint, "model": a.model or "exported to a temporary file", "seed": a.seed,
              "targets": {"max_success_gap": a.max_success_gap, "min_identical": a.min_identical}, "rows": rows}
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
