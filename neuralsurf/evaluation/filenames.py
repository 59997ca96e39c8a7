"""File names made from free-text names (scenes, methods): one path component, never a way out of
the folder it is written in; and the files a stored row names, read only from inside its results
folder (`stored_file`, `read_stored`)."""

from __future__ import annotations

import hashlib
import logging
import re
import stat
from pathlib import Path
from typing import Any

log = logging.getLogger("neuralsurf")

MAX_LENGTH = 80
"""Characters kept of a name before its hash suffix."""


def safe_name(name: str) -> str:
    """`name` as one safe file-name component: characters other than letters, digits, "_", "-" and
    "." become "_", leading dots are dropped and the length is capped; a name changed so gets the
    first 8 hex digits of its SHA-1, so two names stay two files ("sphere" -> "sphere",
    "../../x" -> "_.._x-9bdbf20b")."""
    name = str(name)
    safe = re.sub(r"[^\w.-]", "_", name, flags=re.ASCII).lstrip(".")[:MAX_LENGTH] or "_"
    if safe != name:
        safe = f"{safe}-{hashlib.sha1(name.encode()).hexdigest()[:8]}"
    return safe


def row_stem(scene: str, method: str) -> str:
    """The file stem of a row's files: "<scene>__<method>", each name made safe (`safe_name`)."""
    return f"{safe_name(scene)}__{safe_name(method)}"


MAX_IMAGE_BYTES = 64 * 2**20
"""The largest render or plot a report embeds."""
MAX_DATA_BYTES = 2 * 2**30
"""The largest mesh or distances file read from a results folder."""
PNG = b"\x89PNG\r\n\x1a\n"
"""The first bytes of every PNG file."""
NPZ = b"PK\x03\x04"
"""The first bytes of an .npz file (a zip archive)."""


def stored_file(folder: str | Path, name: Any, what: str, max_bytes: int = MAX_DATA_BYTES,
                signature: bytes = b"") -> Path | None:
    """The file that `name` (a path relative to `folder`, as read from a stored row) names, resolved, or
    None with a warning when it does not lie inside `folder`, is not a regular file, is larger than
    `max_bytes` or does not start with `signature`. `what` names the entry in the warning."""
    folder = Path(folder)
    reason = None
    if not isinstance(name, str) or not name:
        reason = f"{what} is {name!r:.80}, not a path"
    else:
        try:
            root = folder.resolve()
            path = (folder / name).resolve(strict=True)
            if not path.is_relative_to(root):
                reason = f"{what} {name!r:.200} lies outside {folder}"
            else:
                status = path.stat()
                if not stat.S_ISREG(status.st_mode):
                    reason = f"{what} {name!r:.200} is not a regular file"
                elif status.st_size > max_bytes:
                    reason = f"{what} {name!r:.200} holds {status.st_size} bytes, more than {max_bytes}"
                elif signature:
                    with open(path, "rb") as handle:
                        if handle.read(len(signature)) != signature:
                            reason = f"{what} {name!r:.200} is not a {_KINDS.get(signature, 'file of its kind')}"
        except (OSError, RuntimeError, ValueError) as error:
            reason = f"{what} {name!r:.200} cannot be read ({getattr(error, 'strerror', None) or error})"
    if reason is not None:
        log.warning("%s: %s; skipped (a results folder's rows may name only regular files inside it)", folder, reason)
        return None
    return path


def read_stored(folder: str | Path, name: Any, what: str, max_bytes: int = MAX_IMAGE_BYTES,
                signature: bytes = PNG) -> bytes | None:
    """The bytes of `stored_file(folder, name, ...)` (read no further than `max_bytes`), or None with a
    warning."""
    path = stored_file(folder, name, what, max_bytes, signature)
    if path is None:
        return None
    try:
        with open(path, "rb") as handle:
            data = handle.read(max_bytes + 1)
    except OSError as error:
        log.warning("%s: %s %r cannot be read (%s); skipped", folder, what, name, error.strerror or error)
        return None
    if len(data) > max_bytes or not data.startswith(signature):
        log.warning("%s: %s %r changed while it was read; skipped", folder, what, name)
        return None
    return data


_KINDS = {PNG: "PNG image", NPZ: "npz archive"}
