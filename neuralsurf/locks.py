"""Advisory file locks and atomic writes for work shared by processes that may start together (the jobs
of one evaluation sweep on one machine or on a cluster's shared file system).

- `file_lock(path)`: hold an exclusive lock on `path` (created if missing) for a `with` block; a second
  process blocks until the first leaves it. `lock_or_none(path)`: the same without waiting. The lock dies with its process (a killed job never leaves a
  stale lock behind). POSIX `flock`; `msvcrt.locking` on Windows.
- `write_atomic(path, data)` and `replaced(path)`: a file appears whole or not at all (a temporary
  file in the same folder, then `os.replace`), so a reader never sees half of one.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import IO

from neuralsurf.errors import NeuralsurfError


class LockError(NeuralsurfError, OSError):
    """A lock file cannot be created or locked (a read-only or missing folder)."""


@contextmanager
def file_lock(path: str | Path) -> Iterator[Path]:
    """Hold an exclusive advisory lock on `path` (str | Path: a lock file, created with its folders)
    for the `with` block; yields the path. Blocks while another process holds it. Raises LockError
    naming the path when it cannot be created."""
    with _held(path, wait=True):
        yield Path(path)


def lock_or_none(path: str | Path) -> AbstractContextManager[IO[str] | None]:
    """Take the exclusive lock on `path` (str | Path: a lock file, created with its folders) without
    waiting: the `with` block gets the open file (text, read and write) while this process holds it,
    or None when another process holds it. Raises LockError naming the path when it cannot be created."""
    return _held(path, wait=False)


@contextmanager
def _held(path: str | Path, wait: bool) -> Iterator[IO[str] | None]:
    """The lock file `path` opened and locked (waiting for it, or None at once when `wait` is False)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a+")  # noqa: SIM115 - held for the with block, closed below
    except OSError as error:
        raise LockError(f"cannot create the lock file {path}: {error.strerror or error}; make its folder "
                        f"writable or choose another folder") from error
    try:
        held = _lock(handle, wait)
        try:
            yield handle if held else None
        finally:
            if held:
                _unlock(handle)
    finally:
        handle.close()


def _lock(handle, wait: bool = True) -> bool:
    """Lock the open file `handle`; with `wait` False, return False at once when another process holds it."""
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        handle.seek(0)
        while True:
            try:
                msvcrt.locking(handle.fileno(), msvcrt.LK_LOCK if wait else msvcrt.LK_NBLCK, 1)
                return True
            except OSError:  # LK_LOCK gives up after 10 s: try again
                if not wait:
                    return False
                time.sleep(0.1)
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _unlock(handle) -> None:
    try:
        import fcntl
    except ImportError:
        import msvcrt

        handle.seek(0)
        msvcrt.locking(handle.fileno(), msvcrt.LK_UNLCK, 1)
        return
    fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


@contextmanager
def replaced(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path (same folder, same suffix, so writers that choose the format by the
    extension still do) to write `path` (str | Path) through; on a clean exit it is renamed onto
    `path` at once, on an error it is removed and `path` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}-{threading.get_ident()}.tmp{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write `data` (str: UTF-8 text, or bytes) to `path` through a temporary file and a rename."""
    with replaced(path) as temporary:
        if isinstance(data, str):
            temporary.write_text(data, encoding="utf-8")
        else:
            temporary.write_bytes(data)
    return Path(path)
