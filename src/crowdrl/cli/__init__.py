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

Every command fails the same way (:func:`one_line_errors` around its ``main``, :func:`hydra_command`
for the Hydra ones): refused input, a
Hydra or OmegaConf error (an unknown option, a value of the wrong type, a missing config), a full
disk, a read-only or forbidden folder, or a file where the run folder should be end it with one line
``<program>: <message>`` on stderr and exit status 2; Ctrl-C / SIGTERM with 130. Only a bug shows a
traceback (exit 1). Each command writes only into a folder it created or one that carries its own
marker, never over a record it did not write in this call (:func:`crowdrl.training.run_folder.check_folder`).

Each Hydra command composes its config onto a typed schema registered in Hydra's ConfigStore (the
first entry of its defaults list: ``train``: :class:`crowdrl.training.config.RunConfig`; ``evaluate``,
``export``: :mod:`crowdrl.cli.schemas`; ``reproduce``: :class:`crowdrl.reproduction.config.ReproduceConfig`),
so Hydra refuses an unknown key or a value of the wrong type, naming it, before anything is written;
a bool key given anything but ``true`` / ``false`` (``2``, which Hydra would store as ``true``) is refused
the same way (:func:`check_overrides`).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import re
import sys
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

# the OS's errors a user fixes (space, a writable folder, permissions), not crowdrl
FOLDER_ERRNOS = {errno.ENOSPC: "free some space or write elsewhere", errno.EDQUOT: "free some space or write elsewhere",
                 errno.EROFS: "the file system is read-only: write elsewhere",
                 errno.EACCES: "no permission: write elsewhere or change the permissions",
                 errno.EPERM: "not permitted: write elsewhere or change the permissions"}


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


def file_in_the_way(exc: OSError) -> str | None:
    """``<path>: <file> is a file, not a folder; ...`` when a folder could not be made (EEXIST, ENOTDIR:
    Hydra making ``hydra.run.dir`` or reproduce.py's ``out=``) because a file stands at its path or
    above it; ``None`` for another ``OSError``."""
    if exc.errno not in (errno.EEXIST, errno.ENOTDIR) or not exc.filename:
        return None
    path = Path(os.fsdecode(exc.filename))
    file = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
    if file is None:
        return None
    where = f"{path}" if file == path else f"{path}: {file}"
    return f"{where} is a file, not a folder; give a new or empty folder"


def folder_error_line(exc: OSError) -> str | None:
    """``<file>: <strerror> (<ERRNO>); <what to do>`` for a full disk, a read-only or forbidden file
    (:data:`FOLDER_ERRNOS`), ``<path>: ... is a file, not a folder; ...`` for a file where a folder
    must be made (:func:`file_in_the_way`); ``None`` for another ``OSError``."""
    if exc.errno not in FOLDER_ERRNOS:
        return file_in_the_way(exc)
    where = f"{exc.filename}: " if exc.filename else ""
    return f"{where}{exc.strerror or os.strerror(exc.errno)} ({errno.errorcode[exc.errno]}); {FOLDER_ERRNOS[exc.errno]}"


def config_error_line(exc: BaseException) -> str | None:
    """One line for a Hydra or OmegaConf error (``seed: Value 'abc' of type 'str' could not be converted
    to Integer``; ``In 'evaluate': Could not find 'env/mars'; available options in 'env': circle, ...``),
    the key first when the error names one (a typed list given one value: how to give a list); ``None``
    for any other exception."""
    try:
        from hydra.errors import HydraException
        from omegaconf.errors import OmegaConfBaseException
    except ImportError:  # pragma: no cover - both come with crowdrl
        return None
    if not isinstance(exc, (HydraException, OmegaConfBaseException)):
        return None
    parts: list[str] = []
    key = None
    for err in (exc, exc.__cause__):
        if err is None:
            continue
        key = key or getattr(err, "full_key", None) or None
        parts += _message_parts(str(err))
    text = "; ".join(dict.fromkeys(p for p in parts if p)) or type(exc).__name__
    if key and "is not a ListConfig, list or tuple" in text:  # a typed list given one value (variants=egreedy)
        text = f"{text.rstrip('.')}; give a list in brackets: {key}=[...]"
    return text if not key or text.startswith(f"{key}:") else f"{key}: {text}"


def unknown_key(exc: BaseException) -> str | None:
    """The dotted key a Hydra/OmegaConf error refuses as absent from the command's typed schema
    (``eval.episods=5``: ``eval.episods``; ``+encoder=sarl``: ``encoder``); ``None`` for another error
    and for a key of Hydra's own config (``hydra.*``)."""
    try:
        from omegaconf.errors import ConfigAttributeError, ConfigKeyError
    except ImportError:  # pragma: no cover - omegaconf comes with crowdrl
        return None
    key = None
    for err in (exc, exc.__cause__):
        if isinstance(err, (ConfigKeyError, ConfigAttributeError)):
            key = getattr(err, "full_key", None) or None
        elif err is not None and "ConfigKeyError raised while composing config" in str(err):  # a group's keys
            found = re.search(r"^\s*full_key: (\S+)$", str(err), re.MULTILINE)
            key = found.group(1) if found else None
        if key:
            break
    return None if not key or key == "hydra" or key.startswith("hydra.") else str(key)


def _message_parts(text: str) -> list[str]:
    """The lines of a Hydra/OmegaConf message worth a user's reading, an options list on one line."""
    parts: list[str] = []
    options: list[str] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("Config search path") or line.startswith("Set the environment variable HYDRA_FULL_ERROR"):
            break
        if not line or line.startswith(("full_key:", "object_type=", "reference_type=")):
            continue
        if line.startswith("Available options in"):
            options = []
            parts.append(line[0].lower() + line[1:] + " {options}")
        elif options is not None and raw.startswith("\t"):
            options.append(line)
        else:
            parts.append(line)
    return [p.replace("{options}", ", ".join(options or [])) if p.endswith("{options}") else p for p in parts]


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While the block runs, SIGTERM (``kill``, ``timeout``, SLURM) raises ``KeyboardInterrupt`` as Ctrl-C
    does, so a command stopped either way cleans up the same (exit 130, the folder it made removed while
    empty); the previous handler is restored after. ``train``'s training loop installs its own handler
    inside (:func:`crowdrl.training.pipeline.stop_signals`: a checkpoint first). Main thread only."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def one_line_errors(module: str, allowed: Callable[[str], str] | None = None) -> Callable[[F], F]:
    """Decorate a command's ``main`` (outside ``@hydra.main``) so that Hydra's and OmegaConf's errors and
    :data:`FOLDER_ERRNOS` end it with one line and exit 2 (:func:`exit_with_error`), and Ctrl-C with
    130. Hydra is told to raise (``HYDRA_FULL_ERROR=1`` while ``main`` runs) instead of printing its
    own report and exiting 1; anything else propagates as it is. SIGTERM is Ctrl-C while ``main`` runs
    (:func:`sigterm_as_interrupt`). With ``allowed`` (the keys the command
    reads that a refused key could have meant, as a text, given that key), a key its typed schema lacks
    is refused as ``<key>: not read by <module>.py (unknown key); allowed: <allowed(key)>``
    (:func:`unknown_key`), without Hydra's advice to add it with ``+``."""
    def decorate(main: F) -> F:
        @functools.wraps(main)
        def run(*args: Any, **kwargs: Any) -> Any:
            previous = os.environ.get("HYDRA_FULL_ERROR")
            os.environ["HYDRA_FULL_ERROR"] = "1"
            try:
                with sigterm_as_interrupt():
                    return main(*args, **kwargs)
            except KeyboardInterrupt:
                exit_with_error(module, "interrupted", code=130)
            except Exception as exc:
                # Hydra's MissingConfigException is an OSError too
                key = unknown_key(exc) if allowed is not None else None
                if key is not None:
                    exit_with_error(module, f"{key}: not read by {module}.py (unknown key); allowed: {allowed(key)}")
                line = (folder_error_line(exc) if isinstance(exc, OSError) else None) or config_error_line(exc)
                if line is None:
                    raise
                exit_with_error(module, line)
            finally:
                if previous is None:
                    os.environ.pop("HYDRA_FULL_ERROR", None)
                else:
                    os.environ["HYDRA_FULL_ERROR"] = previous

        return run  # type: ignore[return-value]

    return decorate


def check_overrides(module: str, cfg: Any) -> None:
    """Refuse, before the job reads its config, a command-line override of a bool key that is not
    ``true`` / ``false`` (``train.q_layer_norm=2``, which Hydra would store as ``true``:
    :func:`crowdrl.schema.check_bool_overrides`): one line naming the key, exit 2, and the run folder
    Hydra made for the job removed while empty."""
    from hydra.core.hydra_config import HydraConfig

    from crowdrl.schema import SchemaError, check_bool_overrides

    hydra_cfg = HydraConfig.get()
    try:
        check_bool_overrides(cfg, list(hydra_cfg.overrides.task))
    except SchemaError as exc:
        from crowdrl.training.run_folder import discard_new_folders

        discard_new_folders(hydra_cfg.runtime.output_dir)
        exit_with_error(module, str(exc))


def plain_library_logs() -> None:
    """torchrl's console lines without its colour codes wherever their stream is not a terminal (a log file, a pipe,
    CI), where the codes would show as raw ``\\033[92m`` text."""
    import logging

    import torchrl  # noqa: F401  (its import installs the coloured console handler)

    for handler in logging.getLogger("torchrl").handlers:
        isatty = getattr(getattr(handler, "stream", None), "isatty", None)
        if not (callable(isatty) and isatty()):
            handler.setFormatter(logging.Formatter("%(asctime)s [%(name)s][%(levelname)s] %(message)s"))


def hydra_command(module: str, config_name: str, allowed: Callable[[str], str] | None = None) -> Callable[[F], F]:
    """``@hydra.main`` on crowdrl's configs (:func:`crowdrl.resources.config_dir`, ``config_name``) with
    :func:`one_line_errors` around both Hydra's composition and the job itself (an error escaping the
    job would make Hydra print "Error executing job ..." first): the one error path of each Hydra command.
    A sweep (``-m``) that fails before any job wrote anything leaves no sweep folder
    (:func:`crowdrl.training.run_folder.discard_refused_sweeps`).
    ``allowed``: the keys the command reads, named when a key its typed schema lacks is refused."""
    def decorate(task: F) -> F:
        import hydra

        from crowdrl.resources import config_dir

        hydra_main = hydra.main(config_path=str(config_dir()), config_name=config_name, version_base="1.3")

        @functools.wraps(task)
        def checked(cfg: Any, *args: Any, **kwargs: Any) -> Any:
            check_overrides(module, cfg)
            plain_library_logs()
            return task(cfg, *args, **kwargs)

        command = one_line_errors(module, allowed)(hydra_main(one_line_errors(module, allowed)(checked)))

        @functools.wraps(task)
        def run(*args: Any, **kwargs: Any) -> Any:
            try:
                return command(*args, **kwargs)
            except BaseException:  # the one line (and exit status) is out already
                from crowdrl.training.run_folder import discard_refused_sweeps

                discard_refused_sweeps()
                raise

        return run  # type: ignore[return-value]

    return decorate
