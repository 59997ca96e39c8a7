"""Plain-array .npz files written atomically (`write_npz`) and read with every member's header checked
against its size first (`read_npz`); the arrays of uncompressed .npz members and .npy files located
(`npz_spans`, `npy_span`) so that a few rows are read at a time (`ArraySpan.rows`)."""

from __future__ import annotations

import math
import os
import struct
import zipfile
from dataclasses import dataclass
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


@dataclass(frozen=True)
class ArraySpan:
    """Where a plain C-ordered array lies in a file (an uncompressed .npz member or a .npy file)."""

    path: Path
    offset: int
    """Byte offset of its first element."""
    dtype: np.dtype
    shape: tuple[int, ...]

    def rows(self, index: np.ndarray) -> np.ndarray:
        """The rows `index` (Int[ndarray, "..."]) of the array: [*index.shape, *shape[1:]]. The file is
        mapped for this call only, so nothing of it stays in the process's memory afterwards."""
        return np.memmap(self.path, self.dtype, "r", self.offset, self.shape)[index]


def _array_header(file, path: Path, name: str, kinds: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of the .npy header at the file's position (left after it); FileFormatError
    for a Fortran-ordered array or one of other kinds."""
    version = np.lib.format.read_magic(file)
    reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = reader(file, max_header_size=10_000)
    if dtype.hasobject or dtype.kind not in kinds or fortran:
        raise FileFormatError(f"{path}: array {name!r} is {dtype}{' (Fortran order)' if fortran else ''}, not plain "
                              f"C-ordered numbers; the file is not one neuralsurf can read")
    return tuple(shape), dtype


def npz_spans(path: str | Path, keys: tuple[str, ...], kinds: str = NUMERIC_KINDS) -> dict[str, ArraySpan]:
    """Where the arrays `keys` of the .npz file `path` lie in it ({key: ArraySpan}), each member's
    header checked as `read_npz` checks it. Raises FileFormatError naming the file for a missing key,
    a compressed member (`write_npz(compressed=True)`: its rows cannot be read in place) or a member
    whose array does not fit in its bytes."""
    path = Path(path)
    spans = {}
    try:
        with zipfile.ZipFile(path) as archive, open(path, "rb") as file:
            names = {info.filename.removesuffix(".npy"): info for info in archive.infolist()}
            for key in keys:
                if key not in names:
                    raise FileFormatError(f"{path} lacks {key!r} (it has {sorted(names)[:10]})")
                info = names[key]
                if info.compress_type != zipfile.ZIP_STORED:
                    raise FileFormatError(f"{path}: member {key!r} is compressed; its rows cannot be read in place: "
                                          f"write the file uncompressed (write_npz(..., compressed=False))")
                file.seek(info.header_offset)
                local = file.read(30)  # the member's local header: signature ... name and extra lengths
                if len(local) < 30 or local[:4] != b"PK\x03\x04":
                    raise FileFormatError(f"{path}: member {key!r} has no local header; the file is damaged")
                name_length, extra_length = struct.unpack("<HH", local[26:30])
                start = info.header_offset + 30 + name_length + extra_length
                file.seek(start)
                shape, dtype = _array_header(file, path, key, kinds)
                offset = file.tell()
                if offset - start + math.prod(shape) * dtype.itemsize > info.file_size:
                    raise FileFormatError(f"{path}: array {key!r} declares shape {shape} ({dtype}), more than its "
                                          f"{info.file_size} bytes hold; the file is damaged or crafted")
                spans[key] = ArraySpan(path, offset, dtype, shape)
    except FileFormatError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise FileFormatError(f"cannot read {path}: {error}; the file is missing, truncated or not an .npz") from None
    return spans


def npy_span(path: str | Path, kinds: str = NUMERIC_KINDS) -> ArraySpan:
    """Where the array of the .npy file `path` lies in it. Raises FileFormatError for a missing or
    truncated file or an array of other kinds."""
    path = Path(path)
    try:
        with open(path, "rb") as file:
            shape, dtype = _array_header(file, path, path.stem, kinds)
            offset = file.tell()
        if offset + math.prod(shape) * dtype.itemsize > path.stat().st_size:
            raise FileFormatError(f"{path}: its array declares shape {shape} ({dtype}), more than the file holds; "
                                  f"it is truncated: delete it")
    except FileFormatError:
        raise
    except (OSError, ValueError, EOFError) as error:
        raise FileFormatError(f"cannot read {path}: {error}; the file is missing, truncated or not an .npy") from None
    return ArraySpan(path, offset, dtype, shape)
