"""File names made from free-text names (scenes, methods): one path component, never a way out of
the folder it is written in."""

from __future__ import annotations

import hashlib
import re

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
