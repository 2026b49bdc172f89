import os

import pytest
import torch

os.environ.setdefault("WANDB_MODE", "offline")


@pytest.fixture(autouse=True)
def _deterministic_torch():
    """Every test starts from the same torch RNG state and one thread."""
    torch.manual_seed(0)
    torch.set_num_threads(1)
    yield
