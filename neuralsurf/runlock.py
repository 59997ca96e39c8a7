"""One run at a time per run directory: an exclusive lock (`neuralsurf.locks`) on a file in it that
names its holder. A second run into a busy directory is refused with the holder's name; the lock dies
with its process, so a run that was killed (kill -9, a lost session) leaves nothing stale and resumes."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

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


@contextmanager
def run_lock(run_dir: str | Path, hold: bool = True) -> Iterator[None]:
    """Hold the lock of `run_dir` (made if missing) for the body, its file naming this process; raises
    ConfigError naming the holder when another run holds it. With `hold` False, do nothing (e.g. the
    ranks of a torchrun job other than rank 0)."""
    if not hold:
        yield
        return
    path = Path(run_dir) / LOCK_NAME
    with lock_or_none(path) as handle:
        if handle is None:
            raise ConfigError(_refusal(path))
        handle.truncate(0)
        handle.write(f"pid {os.getpid()} on {socket.gethostname()} (since {time.strftime('%Y-%m-%d %H:%M:%S')})\n")
        handle.flush()
        try:
            yield
        finally:
            handle.truncate(0)
