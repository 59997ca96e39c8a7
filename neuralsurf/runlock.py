"""One run at a time per run directory: an exclusive lock (`neuralsurf.locks`) on a file in it that
names its holder. A second run into a busy directory is refused with the holder's name; the lock dies
with its process, so a run that was killed (kill -9, a lost session) leaves nothing stale and resumes."""

from __future__ import annotations

import atexit
import os
import socket
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import IO

from neuralsurf.errors import ConfigError
from neuralsurf.locks import lock_or_none

LOCK_NAME = ".neuralsurf.lock"


def _refusal(path: Path) -> str:
    """Why the run directory of the held lock at `path` cannot be used."""
    holder = path.read_text().strip() or "a run that is starting"
    return (f"run directory {path.parent} is in use by {holder}: two runs into one directory would overwrite "
            f"each other's checkpoints and outputs. Wait for it or choose another hydra.run.dir")


def busy_message(run_dir: str | Path) -> str | None:
    """The refusal `run_lock` would give when a live run holds `run_dir`'s lock, else None (a check
    before Hydra writes its own files there)."""
    path = Path(run_dir) / LOCK_NAME
    if not path.exists():
        return None
    with lock_or_none(path) as handle:
        return None if handle is not None else _refusal(path)


_CLAIMED: dict[Path, tuple[AbstractContextManager, IO[str]]] = {}
"""Lock files this process took ahead of its run (`claim`), by resolved path: `run_lock` holds them on."""


def _name_holder(handle: IO[str]) -> None:
    handle.truncate(0)
    handle.write(f"pid {os.getpid()} on {socket.gethostname()} (since {time.strftime('%Y-%m-%d %H:%M:%S')})\n")
    handle.flush()


def claim(run_dir: str | Path) -> str | None:
    """Take the lock of `run_dir` (made if missing) now, before anything is written there, and keep it
    until this process's `run_lock` on the same folder ends (or the process does): two runs started
    together into one folder cannot both pass. Returns the refusal naming the holder when another
    live run holds it, else None. Raises LockError when the lock file cannot be created."""
    path = Path(run_dir) / LOCK_NAME
    manager = lock_or_none(path)
    handle = manager.__enter__()
    if handle is None:
        manager.__exit__(None, None, None)
        return _refusal(path)
    _name_holder(handle)
    if not _CLAIMED:
        atexit.register(_release_claims)
    _CLAIMED[path.resolve()] = (manager, handle)
    return None


def _release_claims() -> None:
    """Give up the locks `claim` took that no run used (the run stopped before it began)."""
    while _CLAIMED:
        manager, handle = _CLAIMED.popitem()[1]
        handle.truncate(0)
        manager.__exit__(None, None, None)


@contextmanager
def run_lock(run_dir: str | Path, hold: bool = True) -> Iterator[None]:
    """Hold the lock of `run_dir` (made if missing) for the body, its file naming this process; raises
    ConfigError naming the holder when another run holds it. With `hold` False, do nothing (e.g. the
    ranks of a torchrun job other than rank 0). A lock this process took with `claim` is used as it is
    and given up at the end."""
    if not hold:
        yield
        return
    path = Path(run_dir) / LOCK_NAME
    claimed = _CLAIMED.pop(path.resolve(), None) if path.exists() else None
    manager = claimed[0] if claimed is not None else lock_or_none(path)
    handle = claimed[1] if claimed is not None else manager.__enter__()
    try:
        if handle is None:
            raise ConfigError(_refusal(path))
        _name_holder(handle)
        try:
            yield
        finally:
            handle.truncate(0)
    finally:
        manager.__exit__(None, None, None)
