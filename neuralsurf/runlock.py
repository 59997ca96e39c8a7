"""One run at a time per run directory: a lock file created with O_EXCL, holding the pid and host of
its holder. A second run into a busy directory is refused with the holder's name; the lock of a run
that died (its pid gone on this host, e.g. after kill -9) is taken over, so such runs resume."""

from __future__ import annotations

import json
import os
import socket
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from neuralsurf.errors import ConfigError

LOCK_NAME = ".neuralsurf.lock"
UNREADABLE_GRACE_S = 60.0
"""An unreadable lock (its holder died between creating and writing it) counts as stale after this."""


def _alive(pid: int) -> bool:
    """Whether process `pid` exists on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def _read(path: Path) -> tuple[str, dict | None]:
    """(the lock file's text, its record or None when it is not a record); ("", None) when absent."""
    try:
        text = path.read_text()
    except (FileNotFoundError, UnicodeDecodeError, OSError):
        return "", None
    try:
        record = json.loads(text)
    except ValueError:
        return text, None
    ok = isinstance(record, dict) and isinstance(record.get("pid"), int) and isinstance(record.get("host"), str)
    return text, record if ok else None


def _stale(path: Path, record: dict | None) -> bool:
    """Whether the lock at `path` belongs to no running process: its pid is gone on this host, or it
    has been unreadable for longer than UNREADABLE_GRACE_S."""
    if record is None:
        try:
            return time.time() - path.stat().st_mtime > UNREADABLE_GRACE_S
        except FileNotFoundError:
            return True
    return record["host"] == socket.gethostname() and not _alive(record["pid"])


def _take_over(path: Path, text: str) -> None:
    """Remove the stale lock whose content was `text`; a lock written meanwhile by another run is put
    back (rename, then compare: two runs taking over one stale lock cannot both win)."""
    aside = path.with_name(f"{path.name}.stale-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return  # another run took it over first
    if aside.read_text() != text:
        try:
            os.link(aside, path)
        except FileExistsError:
            pass
    aside.unlink()


def _refusal(path: Path, holder: dict | None) -> str:
    """Why the run directory of the live lock at `path`, held by `holder`, cannot be used."""
    who = (f"pid {holder['pid']} on {holder['host']} (since {holder.get('started', '?')})"
           if holder else "a run that is starting")
    return (f"run directory {path.parent} is in use by {who}: two runs into one directory would overwrite "
            f"each other's checkpoints and outputs. Wait for it, choose another hydra.run.dir, or delete {path} "
            f"if that run is gone")


def busy_message(run_dir: str | Path) -> str | None:
    """The refusal `acquire` would give when a live run holds `run_dir`'s lock, else None (a check
    before Hydra writes its own files there)."""
    path = Path(run_dir) / LOCK_NAME
    if not path.exists():
        return None
    _, holder = _read(path)
    return None if _stale(path, holder) else _refusal(path, holder)


def acquire(run_dir: str | Path) -> dict:
    """Create `run_dir`/LOCK_NAME for this process (the folder too, if missing) and return its record
    {"pid", "host", "token", "started"}. Raises ConfigError naming the holder when another live run
    holds it."""
    path = Path(run_dir) / LOCK_NAME
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"pid": os.getpid(), "host": socket.gethostname(), "token": uuid.uuid4().hex,
              "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    for _ in range(5):
        try:
            descriptor = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            text, holder = _read(path)
            if not _stale(path, holder):
                raise ConfigError(_refusal(path, holder)) from None
            _take_over(path, text)
            continue
        with os.fdopen(descriptor, "w") as file:
            json.dump(record, file)
        return record
    raise ConfigError(f"could not lock run directory {path.parent}: other runs keep taking it; choose another "
                      f"hydra.run.dir")


def release(run_dir: str | Path, record: dict) -> None:
    """Delete the lock of `run_dir` if it is still `record`'s (never another run's)."""
    path = Path(run_dir) / LOCK_NAME
    _, holder = _read(path)
    if holder is not None and holder.get("token") == record["token"]:
        path.unlink(missing_ok=True)


@contextmanager
def run_lock(run_dir: str | Path, hold: bool = True) -> Iterator[None]:
    """Hold the lock of `run_dir` for the body (`acquire` ... `release`); with `hold` False, do nothing
    (e.g. the ranks of a torchrun job other than rank 0)."""
    if not hold:
        yield
        return
    record = acquire(run_dir)
    try:
        yield
    finally:
        release(run_dir, record)
