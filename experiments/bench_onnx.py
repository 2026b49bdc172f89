"""Per-step latency of an exported policy: one observation at a time (batch 1), onnxruntime on one thread,
the way a robot runs it (docs/export.md, "Latency").

    taskset -c 0 python experiments/bench_onnx.py pretrained/<agent>             # export it, 10 humans
    taskset -c 0 python experiments/bench_onnx.py runs/<folder> --model policy.onnx --humans 5 20 --json

Exports the checkpoint's acting policy (its planner, when it has one) to a temporary file unless
``--model`` names one, collects the observations of circle test cases (the checkpoint's own policy
acting, ``--steps`` per case) at each crowd size, and times the model on each, one at a time, after
warm-up; reports the median, 99th percentile and worst milliseconds per step. ``taskset -c 0`` pins
it to one core (onnxruntime itself uses one intra-op and one inter-op thread).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from benchkit import Column, add_json_argument, emit, log


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a run folder, a .pt file or pretrained/<agent>")
    p.add_argument("--model", help="its exported .onnx model (default: export one to a temporary file)")
    p.add_argument("--humans", type=int, nargs="+", default=[10], help="crowd sizes (the model's N must be free)")
    p.add_argument("--cases", type=int, default=20, help="circle test cases whose observations are timed")
    p.add_argument("--steps", type=int, default=20, help="steps per case")
    add_json_argument(p)
    a = p.parse_args(argv)
    if a.cases < 1 or a.steps < 1 or min(a.humans) < 1:
        p.error("--cases, --steps and --humans: must be >= 1")
    from crowdrl.export import PLANNER_INPUTS, export_onnx, read_exported
    from crowdrl.onnx_policy import OnnxPolicy
    from crowdrl.training.factories import make_env

    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        model = Path(a.model) if a.model else export_onnx(a.checkpoint, Path(tmp) / "policy.onnx").path
        exported = read_exported(model)
        policy = OnnxPolicy(exported, threads=1)
        for n in a.humans:
            env = make_env(exported.run, split="test", num_envs=a.cases, seed=0, scenario="circle", num_humans=n)
            with torch.no_grad():
                td = env.rollout(a.steps, policy, break_when_any_done=False).reshape(-1)
            feeds = policy.feeds(td)
            singles = [{k: v[i:i + 1] for k, v in feeds.items()} for i in range(len(td))]
            for one in singles[:20]:  # warm-up
                policy.session.run(["action"], one)
            times = []
            for one in singles:
                began = time.perf_counter()
                policy.session.run(["action"], one)
                times.append((time.perf_counter() - began) * 1000)
            t = np.array(times)
            log(f"{n} humans: median {np.median(t):.3f} ms over {len(t)} steps")
            rows.append({"humans": n, "steps": len(t), "median_ms": float(np.median(t)),
                         "p99_ms": float(np.percentile(t, 99)), "max_ms": float(t.max()),
                         "policy": "planner" if exported.plans else "greedy_q"})
    m = exported.metadata
    emit(rows, columns=[Column("humans"), Column("steps"), Column("median_ms", "median ms/step", ".3f"),
                        Column("p99_ms", "p99 ms", ".3f"), Column("max_ms", "max ms", ".3f")],
         title=f"{model.name if a.model else a.checkpoint}: {m.get('crowdrl.policy')} (planning_depth "
               f"{m.get('crowdrl.planning_depth')}, planning_width {m.get('crowdrl.planning_width')}), batch 1, "
               "onnxruntime one thread",
         meta={"checkpoint": a.checkpoint, "inputs": list(exported.inputs), "planner_inputs": list(PLANNER_INPUTS),
               "threads": 1}, as_json=a.json, notes=["Target: <= 20 ms per step at 10 humans on one core (issue #53)."])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
