"""Where the commands write, checked before any work; strict JSON; one writer per folder.

Every command's output path is checked (the folder can be created and a file written there)
before it meshes or simulates anything, and a bad one is a one-line error with exit status 2.
Default outputs go under ``./probegym-out/<command>/`` (the repository ignores it), never
loose in the working directory. JSON is written strictly: a non-finite number becomes
``null`` (``NaN`` is not JSON), and files are readable by all (0644 under the usual umask).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from tissue import ConfigError

#: The folder default outputs go under, in the working directory.
OUTPUT_ROOT = Path("probegym-out")


def default_output(command: str, name: str) -> Path:
    """``probegym-out/<command>/<name>``."""
    return OUTPUT_ROOT / command / name


def check_output_file(path: Path, option: str) -> Path:
    """``path`` if a file can be written there (its folder created if need be); else a
    :class:`ConfigError` naming the option and the problem."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(
            f"{option} {path} is a folder; give a file name, e.g. {path / 'out.json'}"
        )
    _check_folder(path.parent if str(path.parent) else Path("."), f"{option} {path}")
    return path


def check_output_folder(path: Path, option: str) -> Path:
    """``path`` if it is (or can be made) a folder files can be written in."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {path} is a file; give a folder")
    _check_folder(path, f"{option} {path}")
    return path


def _check_folder(folder: Path, what: str) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".probegym-check-"):
            pass
    except OSError as error:
        reason = error.strerror or str(error)
        raise ConfigError(f"cannot write {what}: {reason}; choose a writable place") from None


def finite_or_null(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, recursively (dicts, lists,
    tuples)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(item) for item in value]
    return value


def strict_json(payload: Any, **options: Any) -> str:
    """JSON text with no ``NaN`` or ``Infinity`` literals (non-finite numbers as null)."""
    return json.dumps(finite_or_null(payload), allow_nan=False, **options)


def write_json(payload: Any, path: Path, **options: Any) -> Path:
    """Write ``payload`` as strict JSON to ``path`` (its folder created), atomically: a
    reader never sees half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = strict_json(payload, **options)
    handle, partial = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(handle, "w") as file:
        file.write(text)
    readable(Path(partial))
    os.replace(partial, path)
    return path


def readable(path: Path) -> None:
    """Give a file made by ``tempfile.mkstemp`` (0600) the permissions of any other output:
    0666 less the process's umask."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextlib.contextmanager
def exclusive_folder(folder: Path, what: str) -> Iterator[None]:
    """Hold an OS lock on ``folder`` (``.lock`` inside it) while the block runs; a second
    holder is refused with a clear message. The lock dies with its process (a crashed or
    killed run leaves nothing stale behind)."""
    folder.mkdir(parents=True, exist_ok=True)
    lock_path = folder / ".lock"
    handle = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(handle, 64, 0).decode(errors="replace").strip() or "another"
            raise ConfigError(
                f"another {what} (process {holder}) is writing to {folder}; wait for it to "
                "finish or choose another --out"
            ) from None
        os.ftruncate(handle, 0)
        os.pwrite(handle, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(handle)  # releases the lock
