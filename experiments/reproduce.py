"""The paper's table over seeds with one command: ``crowdrl.cli.reproduce``, run from the checkout.

The command itself lives in the package (``src/crowdrl/cli/reproduce.py``, its usage in the docstring
there); installed, it is also ``crowdrl-reproduce`` and ``python -m crowdrl.cli.reproduce``. This file keeps
``python experiments/reproduce.py ...`` working and exposes the module's names.
"""

from crowdrl.cli.reproduce import *  # noqa: F401,F403
from crowdrl.cli.reproduce import main

if __name__ == "__main__":
    main()
