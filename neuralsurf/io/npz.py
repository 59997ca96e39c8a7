"""Plain-array .npz files written atomically (`write_npz`) and read with every member's header checked
against its size first (`read_npz`)."""

from __future__ import annotations

import math
import os
import zipfile
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


MAX_RATIO = 1032
"""The most a deflated zip member can grow when it is unpacked (deflate's limit)."""
NUMERIC_KINDS = "biuf"
"""numpy dtype kinds of plain numbers (bool, signed and unsigned integers, floats)."""


def read_npz(path: str | Path, keys: tuple[str, ...] = (), kinds: str = NUMERIC_KINDS) -> dict[str, np.ndarray]:
    """Every array of the .npz file `path` as {name: array}. Each member's header is checked before it is
    read: its dtype must be of `kinds` (no objects, no strings) and the size it declares must fit in the
    member's bytes, which must fit in the file (at most MAX_RATIO times their stored size when deflated),
    so a crafted header cannot make a huge allocation. Raises FileFormatError naming the
    file for a missing, truncated or foreign file, a member of another dtype or size, or a missing `keys`."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                name = info.filename.removesuffix(".npy")
                if info.compress_size > size or info.file_size > max(MAX_RATIO * info.compress_size, 2**20):
                    raise FileFormatError(f"{path}: member {name!r} claims {info.file_size} bytes from "
                                          f"{info.compress_size} stored in a file of {size}; the file is damaged or "
                                          f"crafted")
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    reader = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                              else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = reader(member, max_header_size=10_000)
                if dtype.hasobject or dtype.kind not in kinds:
                    raise FileFormatError(f"{path}: array {name!r} has dtype {dtype}, not plain numbers; the file "
                                          f"is not one neuralsurf can read")
                if math.prod(shape) * dtype.itemsize > info.file_size:
                    raise FileFormatError(f"{path}: array {name!r} declares shape {shape} ({dtype}), more than its "
                                          f"{info.file_size} bytes hold; the file is damaged or crafted")
        with np.load(path, allow_pickle=False) as data:
            missing = [key for key in keys if key not in data.files]
            if missing:
                raise FileFormatError(f"{path} lacks {missing} (it has {sorted(data.files)[:10]})")
            return {name: data[name] for name in data.files}
    except FileFormatError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as error:
        raise FileFormatError(f"cannot read {path}: {error}; the file is missing, truncated or not an .npz") from None
