"""Train a crowd-navigation agent: ``crowdrl.cli.train``, run from the checkout.

The command itself lives in the package (``src/crowdrl/cli/train.py``, its usage in the docstring
there); installed, it is also ``crowdrl-train`` and ``python -m crowdrl.cli.train``. This file keeps
``python experiments/train.py ...`` working and exposes the module's names.
"""

from crowdrl.cli.train import *  # noqa: F401,F403
from crowdrl.cli.train import main

if __name__ == "__main__":
    main()
