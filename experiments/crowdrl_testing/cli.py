"""A crowdrl command line run in the test's own process, as ``python experiments/<script> <args>`` would run it.

Tests of refused input (a bad key, a missing checkpoint, a folder in the way) check an exit status, a message and
what is left on disk. A child interpreter would spend ~5 s importing torch, tensordict and torchrl before it
refuses; here the command runs in-process (:func:`run_cli`), with ``sys.argv``, the working directory, stdout,
stderr and the logging setup Hydra changes all restored after. What only a real process shows (one line on the
terminal, no traceback from the interpreter, the shell's exit status) is checked per command with a real process
in ``tests/test_one_line_errors.py`` and ``tests/test_packaging.py``.

Example::

    proc = run_cli("export.py", "checkpoint=nope.pt", cwd=tmp_path)
    assert proc.returncode == 2 and "checkpoint: no checkpoint at" in proc.stderr

Any other script of ``experiments/`` with a ``main(argv=None)`` runs the same way (``run_cli("compare_runs.py",
"--group", ...)``); an ``int`` it returns is its exit status, as ``sys.exit(main())`` makes it.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import logging
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

EXPERIMENTS = Path(__file__).resolve().parent.parent
COMMANDS = {"train.py": "crowdrl.cli.train", "evaluate.py": "crowdrl.cli.evaluate", "export.py": "crowdrl.cli.export",
            "reproduce.py": "crowdrl.cli.reproduce", "demo.py": "crowdrl.cli.demo", "ceiling.py": "crowdrl.cli.ceiling"}


@contextlib.contextmanager
def _logging_restored() -> Iterator[None]:
    """Every logger's handlers, level, propagation and disabled flag as they were (Hydra configures logging)."""
    loggers = [logging.getLogger()] + [lg for lg in logging.Logger.manager.loggerDict.values()
                                       if isinstance(lg, logging.Logger)]
    saved = [(lg, list(lg.handlers), lg.level, lg.propagate, lg.disabled) for lg in loggers]
    try:
        yield
    finally:
        for lg, handlers, level, propagate, disabled in saved:
            lg.handlers[:] = handlers
            lg.setLevel(level)
            lg.propagate, lg.disabled = propagate, disabled
        known = {id(lg) for lg, *_ in saved}
        for lg in list(logging.Logger.manager.loggerDict.values()):
            if isinstance(lg, logging.Logger) and id(lg) not in known:
                lg.handlers[:] = []  # a logger made by the command: no handler into a closed capture


def run_cli(script: str, *args: str, cwd: Path | str | None = None) -> subprocess.CompletedProcess:
    """Run ``experiments/<script>`` with ``args`` in this process from ``cwd``: one of :data:`COMMANDS` (exit status 0
    when its ``main`` returns) or another script's ``main`` (the ``int`` it returns is its exit status); the status,
    stdout and stderr, as :func:`subprocess.run` with ``capture_output`` and ``text`` gives them."""
    from hydra.core.global_hydra import GlobalHydra

    if script in COMMANDS:
        command = importlib.import_module(COMMANDS[script])
    elif (EXPERIMENTS / script).is_file() and script.endswith(".py"):
        spec = importlib.util.spec_from_file_location(f"{script[:-3]}_cli", EXPERIMENTS / script)
        command = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(command)
    else:
        raise ValueError(f"script: no experiments/{script}")
    argv = [str(EXPERIMENTS / script), *args]
    out, err = io.StringIO(), io.StringIO()
    saved_argv, saved_env = sys.argv, dict(os.environ)
    code: int = 0
    try:
        sys.argv = argv
        with (_logging_restored(), contextlib.chdir(cwd or os.getcwd()), contextlib.redirect_stdout(out),
              contextlib.redirect_stderr(err)):
            try:
                returned = command.main()
                if script not in COMMANDS and isinstance(returned, int):
                    code = returned
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                if not isinstance(exc.code, (int, type(None))):
                    print(exc.code, file=sys.stderr)
    finally:
        sys.argv = saved_argv
        os.environ.clear()
        os.environ.update(saved_env)
        GlobalHydra.instance().clear()
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())
