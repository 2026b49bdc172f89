"""Where the files crowdrl ships beside its modules live: the Hydra configuration tree and the
torch-free ONNX example.

The configs are kept once, in the repository's top-level ``conf/``; a wheel ships them as the
package data ``crowdrl/conf/`` (``pyproject.toml`` maps ``crowdrl.conf`` to ``conf``). The command
lines (:mod:`crowdrl.cli`) find them with :func:`config_dir`, wherever they are run from.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def config_dir() -> Path:
    """The folder holding ``config.yaml`` and its groups: ``crowdrl/conf`` inside an installed
    package, else the checkout's ``conf/`` when crowdrl is imported from its ``src/`` folder (an
    editable install or ``PYTHONPATH=src``). Never the current directory."""
    packaged = Path(str(files("crowdrl").joinpath("conf")))
    if (packaged / "config.yaml").is_file():
        return packaged
    checkout = Path(__file__).resolve().parents[2] / "conf"  # <checkout>/src/crowdrl/resources.py
    if (checkout / "config.yaml").is_file():
        return checkout
    raise FileNotFoundError(f"crowdrl's Hydra configs are missing: neither {packaged} nor {checkout} holds "
                            f"config.yaml (reinstall crowdrl)")


def onnx_example() -> Path:
    """The standalone script that runs an exported policy with numpy and onnxruntime alone
    (``python <this path> policy.onnx``); it imports nothing of crowdrl, so it can be copied onto a robot."""
    return Path(__file__).resolve().parent / "onnx_example.py"
