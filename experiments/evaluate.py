"""Evaluate a trained checkpoint or a baseline on fixed test cases: ``crowdrl.cli.evaluate``, run from the checkout.

The command itself lives in the package (``src/crowdrl/cli/evaluate.py``, its usage in the docstring
there); installed, it is also ``crowdrl-evaluate`` and ``python -m crowdrl.cli.evaluate``. This file keeps
``python experiments/evaluate.py ...`` working and exposes the module's names.
"""

from crowdrl.cli.evaluate import *  # noqa: F401,F403
from crowdrl.cli.evaluate import main

if __name__ == "__main__":
    main()
