"""The main job on a small default (``make demo``), train SG-D3QN and test it against ORCA:
``crowdrl.cli.demo``, run from the checkout.

The command itself lives in the package (``src/crowdrl/cli/demo.py``, its usage in the docstring
there); installed, it is also ``crowdrl-demo`` and ``python -m crowdrl.cli.demo``. This file keeps
``python experiments/demo.py ...`` working and exposes the module's names.
"""

import sys

from crowdrl.cli.demo import *  # noqa: F401,F403
from crowdrl.cli.demo import main

if __name__ == "__main__":
    main(sys.argv[1:])
