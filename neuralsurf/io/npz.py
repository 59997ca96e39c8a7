"""Plain-array .npz files written atomically (read them back with `np.load(path, allow_pickle=False)`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neuralsurf.errors import FileFormatError


def write_npz(path: str | Path, arrays: dict[str, np.ndarray], compressed: bool = False) -> Path:
    """Write `arrays` to `path` through a temporary file in the same folder, flushed to disk, then a
    rename: an interruption leaves the old file or the whole new one, never half of one. Raises
    FileFormatError naming the path when it is a folder or its folder cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise FileFormatError(f"cannot write {str(path)!r}: it is a folder; pass a file name")
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            with open(temporary, "wb") as file:
                (np.savez_compressed if compressed else np.savez)(file, **arrays)
                file.flush()
                os.fsync(file.fileno())
            os.replace(temporary, path)
        finally:
            temporary.unlink(missing_ok=True)
    except OSError as error:
        raise FileFormatError(
            f"cannot write {str(path)!r}: {error.strerror or error}; check that its folder is a writable folder"
        ) from error
    return path
