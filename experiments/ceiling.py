"""The ceiling of a stream of cases: ``crowdrl.cli.ceiling``, run from the checkout.

The command itself lives in the package (``src/crowdrl/cli/ceiling.py``, its usage in the docstring
there); installed, it is also ``crowdrl-ceiling`` and ``python -m crowdrl.cli.ceiling``. This file keeps
``python experiments/ceiling.py ...`` working and exposes the module's names.
"""

from crowdrl.cli.ceiling import *  # noqa: F401,F403
from crowdrl.cli.ceiling import main

if __name__ == "__main__":
    main()
