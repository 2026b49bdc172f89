"""Run folders: which folders a process created, which folders crowdrl made, and one writer each.

Nothing in a run folder is written before every refusal check has passed, and only what a run
itself created is ever removed. Hydra creates the run folder before the job starts, so the
:class:`NewFolders` callback (``hydra.callbacks`` in ``conf/``) notes beforehand which of its
folders do not exist yet; :func:`discard_new_folders` removes those, and only while they are empty.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

RUN_MARKERS = (".lock", "status.json")  # every run folder of crowdrl holds one (the lock comes first)

_new_folders: set[Path] = set()  # folders this process will create (noted before Hydra creates them)


class RunFolderRefused(RuntimeError):
    """A run folder cannot be used by this run; nothing in it was changed."""


class RunFolderBusy(RunFolderRefused):
    """Another process holds the run folder."""


def missing_folders(path: Path | str) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, deepest first."""
    out = []
    for p in [Path(path).absolute(), *Path(path).absolute().parents]:
        if p.exists():
            break
        out.append(p)
    return out


def note_new_folders(path: Path | str) -> None:
    """Record that this process is about to create ``path`` (and any missing ancestors)."""
    _new_folders.update(missing_folders(path))


def discard_new_folders(path: Path | str) -> None:
    """Remove ``path`` and its ancestors, deepest first, as far as this process created them and
    they are empty: a folder that existed before, or that holds anything, is left as it is."""
    for p in [Path(path).absolute(), *Path(path).absolute().parents]:
        if not is_new_folder(p):
            break
        try:
            p.rmdir()  # only an empty folder
        except OSError:
            break
        _new_folders.discard(p)


def check_run_folder(path: Path | str) -> None:
    """Refuse (:class:`RunFolderRefused`) a folder that holds files but was not made by crowdrl
    (it has none of ``.lock`` / ``status.json``); a missing or empty folder is fine."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RunFolderRefused(f"{path} is a file, not a folder; give the run a new or empty folder")
    if path.is_dir() and any(path.iterdir()) and not any((path / m).exists() for m in RUN_MARKERS):
        names = ", ".join(sorted(p.name for p in path.iterdir())[:5])
        raise RunFolderRefused(f"{path} holds files ({names}) but is no crowdrl run folder (no "
                               f"{' or '.join(RUN_MARKERS)}); give the run a new or empty folder")


class NewFolders(Callback):
    """Hydra callback: before Hydra creates the run (or sweep) folder, note which of its folders
    do not exist yet, so a run refused at start removes only what it created."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        note_new_folders(str(config.hydra.run.dir))

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        note_new_folders(str(config.hydra.sweep.dir))  # every job folder below a new sweep folder is new too


def is_new_folder(path: Path | str) -> bool:
    """Whether this process created ``path`` (directly, or below a sweep folder it created)."""
    path = Path(path).absolute()
    return path in _new_folders or any(p in _new_folders for p in path.parents)
