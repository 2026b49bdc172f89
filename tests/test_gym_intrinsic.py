"""``experiments/gym_intrinsic.py``: crowdrl.exploration on a plain Gymnasium env (CartPole).

The script runs in a subprocess (``--json``); the test does not import ``experiments/``.
"""

from __future__ import annotations

import ast
import functools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "experiments" / "gym_intrinsic.py"

TINY = ("--frames", "400", "--frames-per-batch", "50", "--updates-per-batch", "2", "--warmup-frames", "150",
        "--batch-size", "32", "--seed", "3")
CROWD_PACKAGES = ("crowdrl.sim", "crowdrl.envs", "crowdrl.models", "crowdrl.training", "crowdrl.evaluation",
                  "crowdrl.policies", "crowdrl.viz")


@functools.cache
def _run(*args: str) -> dict:
    """The example's JSON summary for ``args`` (+ ``TINY``), from a fresh process; cached per args."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run([sys.executable, str(EXAMPLE), *args, *TINY, "--json"], capture_output=True, text=True,
                          env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


@pytest.mark.parametrize("bonus", ["icm", "re3"])
def test_example_runs_end_to_end(bonus):
    out = _run("--bonus", bonus, "--beta", "0.5")
    assert out["frames"] == 400 and out["updates"] > 0 and out["episodes"] > 0
    assert math.isfinite(out["final_mean_return"])
    last = out["last_batch"]
    assert last["has_reward_int"]
    assert last["reward_int_shape"] == last["reward_ext_shape"] == last["reward_shape"] == [32, 1]
    assert last["reward_int_finite"] and last["reward_int_positive_somewhere"]
    assert last["max_abs_rewrite_error"] == 0.0  # r == r_ext + 0.5 * r_in exactly
    stats = out["intrinsic"]
    assert math.isfinite(stats["mean"]) and stats["mean"] > 0 and stats["last"]["beta"] == 0.5


def test_beta_zero_reproduces_the_extrinsic_only_run():
    plain = _run("--bonus", "none")
    zero = _run("--bonus", "icm", "--beta", "0")
    assert plain["intrinsic"] is None and not plain["last_batch"]["has_reward_int"]
    assert zero["returns"] == plain["returns"]
    assert zero["q_checksum"] == plain["q_checksum"]
    assert zero["last_batch"]["reward"] == plain["last_batch"]["reward"]


@pytest.mark.parametrize("bonus", ["icm", "re3"])
def test_the_stable_bonus_options_work_on_a_plain_gymnasium_env(bonus):
    out = _run("--bonus", bonus, "--beta", "0.5", "--reward-norm", "batch", "--center", "--clip", "2", "--obs-norm",
               "--terminal-value", *(("--feature-norm", "layernorm") if bonus == "icm" else ()))
    last = out["intrinsic"]["last"]
    # centred, then clipped to ±2 (the clip may move the mean a little off 0)
    assert abs(last["reward_int_mean"]) < 0.05 and last["reward_int_max"] <= 2.0 and last["reward_int_min"] >= -2.0
    assert last["reward_int_raw_mean"] > 0 and 0 < last["reward_int_share"] < 1
    assert "reward_int_terminal_mean" in last  # CartPole's falls are terminal transitions
    if bonus == "icm":
        assert last["icm_feature_norm"] == pytest.approx(128 ** 0.5, rel=1e-2)  # LayerNorm's eps: a hair under
    assert out["options"]["reward_norm"] == "batch" and out["options"]["obs_norm"]


def _crowdrl_imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return {n for n in names if n == "crowdrl" or n.startswith("crowdrl.")}


def test_intrinsic_modules_and_example_import_only_crowdrl_exploration():
    # every exploration module, the noisy and dropout heads included, must stay free of crowd code
    package = ROOT / "src" / "crowdrl" / "exploration"
    names = ("__init__", "intrinsic", "icm", "re3", "noisy", "dropout", "_surgery", "normalize", "schedule")
    files = [EXAMPLE, *(package / f"{name}.py" for name in names)]
    for path in files:
        assert all(n.startswith("crowdrl.exploration") for n in _crowdrl_imports(path)), path


# ``import crowdrl`` only registers the Gymnasium ids (crowdrl.registration imports gymnasium
# alone), so the real package is imported: neither it nor the example may pull in crowd code.
def test_no_crowd_module_is_imported_in_a_fresh_process():
    modules = _run("--bonus", "re3", "--beta", "0.5")["crowdrl_modules"]
    assert "crowdrl.exploration" in modules
    assert not [m for m in modules if m.startswith(CROWD_PACKAGES)], modules
