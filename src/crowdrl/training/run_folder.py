"""Run folders: which folders a process created, which folders crowdrl made, and one writer each.

Nothing in a run folder is written before every refusal check has passed, and only what a run
itself created is ever removed. Hydra creates the run folder before the job starts, so the
:class:`NewFolders` callback (``hydra.callbacks`` in ``conf/``) notes beforehand which of its
folders do not exist yet; :func:`discard_new_folders` removes those, and only while they are empty.
A sweep (``-m``) refused before any of its jobs wrote anything leaves no sweep folder either
(:func:`discard_refused_sweeps`: Hydra writes ``multirun.yaml`` before it checks the jobs).

Every command that writes keeps one rule (:func:`check_folder`): it writes only into a folder it
created or one that carries its own marker, never over a record it did not write in this call.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

RUN_MARKERS = (".lock", "status.json")  # every run folder of crowdrl holds one (the lock comes first)

SWEEP_RECORD = "multirun.yaml"  # what Hydra writes into a sweep folder before it checks the sweep's jobs

_new_folders: set[Path] = set()  # folders this process will create (noted before Hydra creates them)
_new_sweeps: set[Path] = set()  # the sweep folders among them


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


def check_folder(path: Path | str, markers: tuple[str, ...] = (), *, kind: str = "crowdrl run folder",
                 ignore: tuple[str, ...] = ()) -> None:
    """Refuse (:class:`RunFolderRefused`) ``path`` when it is a file, or a folder that holds anything
    (names in ``ignore`` aside) but none of ``markers`` (a ``kind`` of folder that its command made;
    no ``markers``: any file at all). A missing or empty folder is fine."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise RunFolderRefused(f"{path} is a file, not a folder; give a new or empty folder")
    held = sorted(p.name for p in path.iterdir() if p.name not in ignore) if path.is_dir() else []
    if held and not any((path / m).exists() for m in markers):
        names = ", ".join(held[:5]) + (", ..." if len(held) > 5 else "")
        made = f" but is no {kind} (no {' or '.join(markers)})" if markers else ""
        raise RunFolderRefused(f"{path} holds files ({names}){made}; give a new or empty folder")


def check_run_folder(path: Path | str) -> None:
    """Refuse (:class:`RunFolderRefused`) a folder that holds files but was not made by crowdrl
    (it has none of ``.lock`` / ``status.json``); a missing or empty folder is fine (:func:`check_folder`)."""
    check_folder(path, RUN_MARKERS)


class NewFolders(Callback):
    """Hydra callback: before Hydra creates the run (or sweep) folder, note which of its folders
    do not exist yet, so a run refused at start removes only what it created."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        note_new_folders(str(config.hydra.run.dir))

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        sweep = Path(str(config.hydra.sweep.dir)).absolute()
        if not sweep.exists():
            _new_sweeps.add(sweep)
        note_new_folders(sweep)  # every job folder below a new sweep folder is new too


def is_new_folder(path: Path | str) -> bool:
    """Whether this process created ``path`` (directly, or below a sweep folder it created)."""
    path = Path(path).absolute()
    return path in _new_folders or any(p in _new_folders for p in path.parents)


def discard_refused_sweeps() -> None:
    """After a sweep (``-m``) ended in an error: remove each sweep folder this process created in
    which no job wrote anything, i.e. that holds nothing but Hydra's ``multirun.yaml`` (written
    before Hydra composes the jobs, so a bad value such as ``seed=abc,0`` would leave it behind),
    then its new parents while empty (:func:`discard_new_folders`). A sweep any job wrote into is
    left as it is."""
    for sweep in sorted(_new_sweeps):
        try:
            names = [p.name for p in sweep.iterdir()]
        except OSError:  # never made, or already gone
            names = None
        if names == [SWEEP_RECORD]:
            (sweep / SWEEP_RECORD).unlink()
        if names is not None:
            discard_new_folders(sweep)
        _new_sweeps.discard(sweep)
