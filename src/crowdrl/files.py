"""Atomic file writes (readers see the old file or the new one, never half of one) and strict JSON.

A write goes through a temporary ``.<name>.<pid>.<id>.tmp`` beside its target, removed on any error;
one left by a process that was killed mid-write (SIGKILL, power loss) is removed by the next atomic
write of the same target once that process is gone (:func:`remove_stale_temporaries`).

Files written here get the mode a plain ``open(path, "w")`` would give them: an existing file keeps
its mode, a new one gets ``0o666`` less the umask (usually ``0644``), not ``mkstemp``'s ``0600``.
JSON is strict (RFC 8259): an undefined metric (NaN, ±inf) is written as ``null``, never as a bare
``NaN`` that strict parsers reject; ``json.loads`` still reads files written before with ``NaN``.
"""

from __future__ import annotations

import glob
import json
import math
import os
import re
import uuid
from pathlib import Path
from typing import Any, Callable


def finite_or_null(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, ±inf) in nested dicts, lists and tuples as ``None``."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    return obj


def dumps_json(obj: Any, *, indent: int | None = 1, default: Callable[[Any], Any] | None = None,
               sort_keys: bool = False) -> str:
    """Strict JSON text of ``obj``: non-finite floats become ``null`` (:func:`finite_or_null`)."""
    return json.dumps(finite_or_null(obj), indent=indent, default=default, sort_keys=sort_keys, allow_nan=False)


def _temp_beside(path: Path, suffix: str = "") -> Path:
    """A fresh name beside ``path`` (same folder, so the rename is atomic), ending in ``suffix``
    (writers such as matplotlib pick the format from it)."""
    return path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp{suffix}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        return True
    return True


def remove_stale_temporaries(path: Path | str) -> list[Path]:
    """Remove the temporaries of atomic writes of ``path`` (``.<name>.<pid>.<id>.tmp*`` beside it)
    left by processes that no longer run (a writer killed mid-write); return what was removed.
    Those of a live process, this one included, are left alone: it may be writing them now."""
    path = Path(path)
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(\d+)\.[0-9a-f]{{12}}\.tmp")
    removed = []
    try:
        candidates = list(path.parent.glob(f".{glob.escape(path.name)}.*.tmp*"))
    except OSError:
        return removed
    for tmp in candidates:
        found = pattern.match(tmp.name)
        if found is None or int(found.group(1)) == os.getpid() or _pid_alive(int(found.group(1))):
            continue
        try:
            tmp.unlink()
            removed.append(tmp)
        except FileNotFoundError:
            pass
    return removed


def atomic_write_with(path: Path | str, write: Callable[[Path], Any], *, suffix: str = "") -> Path:
    """Write ``path`` through ``write(tmp)``, a function that creates the file ``tmp`` (a figure's
    ``savefig``, a CSV writer), then rename ``tmp`` over ``path``: readers see the old file or the
    new one, never half. ``tmp`` ends in ``suffix``; on any error it is removed and ``path`` is
    untouched.

    Examples:
        >>> import tempfile
        >>> out = Path(tempfile.mkdtemp()) / "notes.txt"
        >>> atomic_write_with(out, lambda tmp: tmp.write_text("hello")).read_text()
        'hello'
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = _temp_beside(path, suffix)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never half
    (flushed to disk before the rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = _temp_beside(path)
    try:
        mode = os.stat(path).st_mode & 0o7777  # an existing file keeps its mode, as open(path, "w") would
    except FileNotFoundError:
        mode = None
    try:
        # created by this process with 0o666 less the umask (mkstemp would give 0o600)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            if mode is not None:
                os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_json(path: Path | str, obj: Any, *, default: Callable[[Any], Any] | None = None) -> None:
    """``obj`` as strict JSON (:func:`dumps_json`), written atomically (:func:`atomic_write_bytes`)."""
    atomic_write_bytes(path, dumps_json(obj, default=default).encode())


def read_json_lines(path: Path | str) -> list[Any]:
    """The records of a JSON-lines file (``scalars.jsonl``), up to a line a kill cut short (everything after it is
    lost anyway); an empty list for a file that does not exist."""
    path = Path(path)
    out = []
    if path.exists():
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return out


__all__ = ["atomic_write_bytes", "atomic_write_json", "atomic_write_with", "dumps_json", "finite_or_null", "read_json_lines",
           "remove_stale_temporaries"]

