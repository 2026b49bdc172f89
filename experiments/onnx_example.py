"""Checkout shortcut for ``src/crowdrl/onnx_example.py``: runs it by its path, so that, like the file
itself, it needs numpy and onnxruntime only (no torch, no crowdrl). See that file for what it does.

    python experiments/onnx_example.py policy.onnx [--json]
"""

import runpy
from pathlib import Path

if __name__ == "__main__":
    runpy.run_path(str(Path(__file__).resolve().parents[1] / "src" / "crowdrl" / "onnx_example.py"), run_name="__main__")
