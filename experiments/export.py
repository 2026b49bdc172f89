"""Export a trained checkpoint's greedy Q policy as an ONNX model: ``crowdrl.cli.export``, run from the checkout.

The command itself lives in the package (``src/crowdrl/cli/export.py``, its usage in the docstring
there); installed, it is also ``crowdrl-export`` and ``python -m crowdrl.cli.export``. This file keeps
``python experiments/export.py ...`` working and exposes the module's names.
"""

from crowdrl.cli.export import *  # noqa: F401,F403
from crowdrl.cli.export import main

if __name__ == "__main__":
    main()
