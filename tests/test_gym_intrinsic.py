"""``experiments/gym_intrinsic.py``: crowdrl.exploration on a plain Gymnasium env (CartPole)."""

from __future__ import annotations

import ast
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "experiments" / "gym_intrinsic.py"
sys.path.insert(0, str(EXAMPLE.parent))

import gym_intrinsic  # noqa: E402

TINY = ["--frames", "400", "--frames-per-batch", "50", "--updates-per-batch", "2", "--warmup-frames", "150",
        "--batch-size", "32", "--seed", "3"]
CROWD_PACKAGES = ("crowdrl.sim", "crowdrl.envs", "crowdrl.models", "crowdrl.training", "crowdrl.evaluation",
                  "crowdrl.policies", "crowdrl.viz")


@pytest.mark.parametrize("bonus", ["icm", "re3"])
def test_example_runs_end_to_end(bonus):
    out = gym_intrinsic.main(["--bonus", bonus, "--beta", "0.5", *TINY])
    assert out["frames"] == 400 and out["updates"] > 0 and out["episodes"] > 0
    assert math.isfinite(out["final_mean_return"])
    sample = out["last_sample"]
    r_ext, r_in, r = sample["next", "reward_ext"], sample["next", "reward_int"], sample["next", "reward"]
    assert r_in.shape == r_ext.shape == r.shape == (32, 1)
    assert torch.isfinite(r_in).all() and (r_in > 0).any()
    assert torch.equal(r, r_ext + 0.5 * r_in)
    stats = out["intrinsic"]
    assert math.isfinite(stats["mean"]) and stats["mean"] > 0 and stats["last"]["beta"] == 0.5


def test_beta_zero_reproduces_the_extrinsic_only_run():
    plain = gym_intrinsic.main(["--bonus", "none", *TINY])
    zero = gym_intrinsic.main(["--bonus", "icm", "--beta", "0", *TINY])
    assert plain["intrinsic"] is None and "reward_int" not in plain["last_sample"]["next"].keys()
    assert zero["returns"] == plain["returns"]
    assert zero["q_checksum"] == plain["q_checksum"]
    assert torch.equal(zero["last_sample"]["next", "reward"], plain["last_sample"]["next", "reward"])


def _crowdrl_imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return {n for n in names if n == "crowdrl" or n.startswith("crowdrl.")}


def test_intrinsic_modules_and_example_import_only_crowdrl_exploration():
    # noisy.py / dropout.py (crowd Q-heads) live in the same package but are not imported by its
    # __init__; the intrinsic-reward modules must stay free of crowd code
    package = ROOT / "src" / "crowdrl" / "exploration"
    files = [EXAMPLE, *(package / f"{name}.py" for name in ("__init__", "intrinsic", "icm", "re3"))]
    for path in files:
        assert all(n.startswith("crowdrl.exploration") for n in _crowdrl_imports(path)), path


# ``import crowdrl`` only registers the Gymnasium ids (crowdrl.registration imports gymnasium
# alone), so the real package is imported: neither it nor the example may pull in crowd code.
_CHILD = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import gym_intrinsic
out = gym_intrinsic.main(["--bonus", "re3", *sys.argv[2:]])
assert out["updates"] > 0
print("MODULES=" + json.dumps(sorted(m for m in sys.modules if m.startswith("crowdrl"))))
"""


def test_no_crowd_module_is_imported_in_a_fresh_process():
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(EXAMPLE.parent), *TINY], capture_output=True,
                          text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("MODULES=")][-1]
    modules = json.loads(line.removeprefix("MODULES="))
    assert "crowdrl.exploration" in modules
    assert not [m for m in modules if m.startswith(CROWD_PACKAGES)], modules
