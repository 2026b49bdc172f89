"""The ``Examples:`` of the reusable classes run as doctests: each module's examples
pass, and there are examples to run (a module without any fails, so the test is never vacuous)."""

from __future__ import annotations

import doctest
import importlib

import pytest

# module -> the object whose docstring must hold doctested examples
DOCUMENTED = {
    "crowdrl.envs.crowd_nav": "CrowdNavEnv",
    "crowdrl.evaluation.rollout": "evaluate",
    "crowdrl.files": "atomic_write_with",
    "crowdrl.exploration.icm": "ICM",
    "crowdrl.exploration.intrinsic": "IntrinsicRewardTransform",
    "crowdrl.exploration.re3": "RE3",
    "crowdrl.policies.planning": "OnlinePlanner",
    "crowdrl.sim.oracle": "beam_search",
    "crowdrl.schema": "read_typed",
    "crowdrl.sim.lidar": "lidar_scan",
    "crowdrl.tables": "markdown_table",
    "crowdrl.training.config": "RunConfig",
    "crowdrl.training.learner": "D3QNLearner",
    "crowdrl.training.trainer": "Trainer",
}


@pytest.mark.parametrize("name", sorted(DOCUMENTED))
def test_module_examples_pass(name):
    module = importlib.import_module(name)
    doc = getattr(module, DOCUMENTED[name]).__doc__ or ""
    assert "Examples:" in doc and ">>>" in doc, f"{name}.{DOCUMENTED[name]} has no doctested Examples: section"
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, report=True)
    assert result.attempted > 0
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {name} failed (see the output above)"


# modules whose functions carry short examples (without an Examples: section): they pass too
FUNCTION_EXAMPLES = ("crowdrl.envs.episodes", "crowdrl.exploration.rnd", "crowdrl.training.compat", "crowdrl.training.validation")


@pytest.mark.parametrize("name", FUNCTION_EXAMPLES)
def test_function_examples_pass(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
                             report=True)
    assert result.attempted > 0
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {name} failed (see the output above)"
