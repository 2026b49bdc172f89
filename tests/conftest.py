import os

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")
# The SG-D3QN pairwise attention kernels run eager in tests (and in the scripts tests start, which
# inherit this): compiling them costs seconds per process and is what only tests/test_models.py
# checks, by building compiled kernels explicitly and comparing them with eager ones.
os.environ.setdefault("CROWDRL_PAIRWISE", "eager")


@pytest.fixture(autouse=True)
def _deterministic_torch():
    """Every test starts from the same torch RNG state and one thread."""
    torch.manual_seed(0)
    torch.set_num_threads(1)
    yield
