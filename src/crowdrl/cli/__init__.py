"""The command lines. Each is a module with a ``main()``, installed as a console script
(``pip install ".[train]"``), runnable as ``python -m crowdrl.cli.<name>``, and wrapped in a checkout
by ``experiments/<name>.py``:

- ``crowdrl-train``: :mod:`crowdrl.cli.train` (``experiments/train.py``)
- ``crowdrl-evaluate``: :mod:`crowdrl.cli.evaluate` (``experiments/evaluate.py``)
- ``crowdrl-reproduce``: :mod:`crowdrl.cli.reproduce` (``experiments/reproduce.py``)
- ``crowdrl-demo``: :mod:`crowdrl.cli.demo` (``experiments/demo.py``)
- ``crowdrl-export``: :mod:`crowdrl.cli.export` (``experiments/export.py``; the ``export`` extra)

The configs come from the package (:func:`crowdrl.resources.config_dir`), never from the current
directory; what the commands write (``runs/``, ``multirun/``, ``results/``) is relative to it.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import NoReturn


def command(module: str) -> str:
    """How this command line was started, for its messages: ``python experiments/train.py``,
    ``python -m crowdrl.cli.train`` or ``crowdrl-train`` (``module``: e.g. ``"train"``)."""
    argv0 = Path(sys.argv[0]) if sys.argv and sys.argv[0] else Path()
    if argv0.suffix != ".py":
        return argv0.name or f"crowdrl-{module}"
    if argv0.resolve() == Path(__file__).resolve().parent / f"{module}.py":
        return f"python -m crowdrl.cli.{module}"
    return f"python {sys.argv[0]}"


def program(module: str) -> str:
    """The name this command line goes by in its messages: ``train.py`` (``python experiments/train.py``
    or ``python -m crowdrl.cli.train``) or ``crowdrl-train`` (``module``: e.g. ``"train"``)."""
    return Path(sys.argv[0]).name if sys.argv and sys.argv[0] else f"crowdrl-{module}"


def exit_with_error(module: str, message: str, code: int = 2) -> NoReturn:
    """Print ``<program>: <message>`` on stderr and exit with ``code`` (2: refused input, 1: a failure)."""
    print(f"{program(module)}: {message}", file=sys.stderr)
    raise SystemExit(code)
