"""Read and write point clouds: .ply (ASCII and binary), .xyz, .npy and .pcd.

Every reader returns a `PointCloud` in the file's own frame and keeps float64 where the file stores
float64 (text formats are parsed as float64: they carry no precision of their own). Writers create
missing parent folders and warn, never silently drop, when the format cannot hold normals or colours.

Precision of the writers: .npy is exact; .ply stores the cloud's own float32/float64; .xyz writes
enough digits to round-trip exactly; .pcd (through Open3D) stores float32. Colours are stored as
8-bit in .ply and .pcd.
"""

from __future__ import annotations

import io
import os
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from neuralsurf.errors import FileFormatError, InputError, NeuralsurfError
from neuralsurf.structures import PointCloud

SUPPORTED = (".ply", ".xyz", ".npy", ".pcd")
"""Point-cloud file extensions, matched case-insensitively."""

PathLike = str | os.PathLike


# ---------------------------------------------------------------------------------------------
# paths, shared with meshes.py


def checked_extension(path: PathLike, supported: tuple[str, ...], kind: str) -> str:
    """Lower-case extension of `path`, or FileFormatError listing the `supported` ones."""
    ext = Path(path).suffix.lower()
    if ext not in supported:
        raise FileFormatError(
            f"cannot handle {kind} file {str(path)!r}: unknown extension {ext or '(none)'!r}; "
            f"use one of {', '.join(supported)}"
        )
    return ext


def readable_path(path: PathLike, supported: tuple[str, ...], kind: str) -> tuple[Path, str]:
    """`path` as a Path and its extension, after checking it is a supported, existing file."""
    ext = checked_extension(path, supported, kind)
    path = Path(path)
    if not path.exists():
        raise FileFormatError(f"{kind} file not found: {str(path)!r}; check the path and the working folder")
    if not path.is_file():
        raise FileFormatError(f"{str(path)!r} is not a file (a folder?); pass the path of a {kind} file")
    return path, ext


def writable_path(path: PathLike, supported: tuple[str, ...], kind: str) -> tuple[Path, str]:
    """`path` as a Path and its extension, with its parent folders created.

    Raises FileFormatError when `path` is a folder, when a file stands where a parent folder should
    be, or when the folder cannot be created (permissions)."""
    ext = checked_extension(path, supported, kind)
    path = Path(path)
    if path.is_dir():
        raise FileFormatError(
            f"cannot write {kind} file {str(path)!r}: it is a folder; pass a file name inside it"
        )
    blocking = next((parent for parent in path.parents if parent.exists() and not parent.is_dir()), None)
    if blocking is not None:
        raise FileFormatError(
            f"cannot write {kind} file {str(path)!r}: {str(blocking)!r} is a file, not a folder; "
            f"write somewhere else or move that file away"
        )
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise FileFormatError(
            f"cannot create the folder {str(path.parent)!r} for {kind} file {str(path)!r}: "
            f"{error.strerror or error}; check the path and its permissions"
        ) from error
    return path, ext


def named(path: Path, error: NeuralsurfError) -> NeuralsurfError:
    """The same error class with `path` prepended to its message."""
    return type(error)(f"{str(path)!r}: {error}")


def warn_dropped(path: Path, what: str, fmt: str, hint: str) -> None:
    """Warn that `what` cannot be stored in format `fmt` when writing `path`."""
    warnings.warn(f"{fmt} cannot store {what}; they are not written to {str(path)!r} ({hint})", stacklevel=4)


def colors_to_uint8(colors: np.ndarray, path: Path) -> np.ndarray:
    """RGB in [0, 1] (n, 3) -> uint8 (n, 3), warning when values outside [0, 1] are clipped."""
    if colors.size and (colors.min() < 0 or colors.max() > 1):
        warnings.warn(
            f"colours outside [0, 1] (range {colors.min():.3g}..{colors.max():.3g}) were clipped "
            f"when writing {str(path)!r}; scale them to [0, 1] first",
            stacklevel=4,
        )
    return np.round(np.clip(colors, 0, 1) * 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# PLY through plyfile
#
# plyfile parses every header and reads binary bodies (memory-mapped, so a body shorter than its
# header declares is caught before anything is allocated). ASCII bodies are read here, vectorised,
# one element row per line as the format requires: plyfile parses ASCII value by value in Python,
# which took 39 s for the ten Stanford bunny scans against 0.8 s here. Writing goes through
# plyfile too, except the rows of the triangle list, which plyfile writes one at a time (1.9 s
# for 400k triangles): they are written as the packed rows of the header plyfile made.


def ply_header(data: bytes):
    """The header of a PLY file's bytes: (plyfile.PlyData with its elements and properties but no
    data, byte offset of the body). FileFormatError when it is not a PLY header."""
    import plyfile

    if not data.startswith(b"ply"):
        raise FileFormatError("not a PLY file: it does not start with 'ply'")
    end = re.search(rb"end_header[ \t]*\r?\n", data)
    if end is None:
        raise FileFormatError("PLY header has no 'end_header' line; the file is truncated or not PLY")
    try:
        header = plyfile.PlyData._parse_header(io.BytesIO(data[: end.end()]))
    except (plyfile.PlyParseError, ValueError, UnicodeDecodeError) as error:
        raise FileFormatError(f"PLY header does not parse: {error}") from error
    return header, end.end()


def ascii_rows(data: bytes, offset: int, header, name: str) -> list[str]:
    """The body lines of element `name` of an ASCII PLY (elements before it skipped, list
    properties included: one row per line); FileFormatError when the file has fewer lines."""
    lines = data[offset:].decode("ascii", errors="replace").splitlines()
    names = [element.name for element in header.elements]
    start = sum(element.count for element in header.elements[: names.index(name)])
    count = header[name].count
    if len(lines) < start + count:
        raise FileFormatError(
            f"ASCII PLY holds fewer lines ({len(lines)}) than its header declares ({start + count} up to the end "
            f"of element {name!r}); the file is truncated"
        )
    return lines[start : start + count]


def read_ply_binary(path: Path):
    """Every element of a binary PLY file as plyfile.PlyData (data copied out of the memory map).
    Triangle lists are memory-mapped too; other list lengths are read row by row."""
    import plyfile

    try:
        try:
            return plyfile.PlyData.read(str(path), mmap="c", known_list_len={"face": {"vertex_indices": 3}})
        except plyfile.PlyElementParseError as error:
            if "unexpected list length" not in str(error):
                raise
            return plyfile.PlyData.read(str(path), mmap="c")
    except plyfile.PlyElementParseError as error:
        element = getattr(error, "element", None)
        declared = f" the {element.count} rows of {element.name!r}" if element is not None else " the rows"
        raise FileFormatError(
            f"binary PLY holds fewer than{declared} its header declares ({error}); the file is truncated"
            if "end-of-file" in str(error) else f"binary PLY body does not parse ({error}); the file is corrupt"
        ) from error
    except (plyfile.PlyParseError, ValueError, OSError, MemoryError) as error:
        raise FileFormatError(f"PLY file does not parse ({type(error).__name__}: {error}); the file is corrupt") from error


def read_ply_vertices(path: Path, data: bytes | None = None) -> tuple[dict[str, np.ndarray], list[str]]:
    """The vertex element of a PLY file as {property name: (n,) array of the file's type}, and the
    names of the other non-empty elements (faces, edges, ...), which are not returned. Elements
    may come in any order, list properties included (e.g. faces before vertices)."""
    data = path.read_bytes() if data is None else data
    header, offset = ply_header(data)
    names = [element.name for element in header.elements]
    if "vertex" not in names:
        raise FileFormatError(f"PLY file has no 'vertex' element (elements: {names})")
    others = [element.name for element in header.elements if element.name != "vertex" and element.count]
    properties = header["vertex"].properties
    if not header.text:
        vertex = read_ply_binary(path)["vertex"].data
        return {prop.name: np.array(vertex[prop.name], dtype=prop.val_dtype) for prop in properties}, others
    if any(isinstance(prop, _list_property()) for prop in properties):
        raise FileFormatError(
            "the PLY vertex element has list properties; a point cloud needs one x, y, z per vertex"
        )
    rows = ascii_rows(data, offset, header, "vertex")
    count = len(rows)
    try:
        table = np.array(" ".join(rows).split(), dtype=np.float64).reshape(count, len(properties))
    except ValueError as error:
        raise FileFormatError(f"ASCII PLY vertex data does not parse ({error}); the file is corrupt") from error
    return {prop.name: table[:, i].astype(prop.val_dtype) for i, prop in enumerate(properties)}, others


def _list_property():
    import plyfile

    return plyfile.PlyListProperty


def write_ply(
    path: Path,
    vertex: dict[str, np.ndarray],
    faces: np.ndarray | None = None,
) -> None:
    """Write a binary little-endian PLY through plyfile.

    `vertex` maps property names to (n,) arrays (float32, float64 or uint8); `faces` is (f, 3) int,
    written as `list uchar int vertex_indices`.
    """
    import plyfile

    table = np.empty(len(next(iter(vertex.values()))), dtype=[(n, "<" + a.dtype.str[1:]) for n, a in vertex.items()])
    for name, array in vertex.items():
        table[name] = array
    elements = [plyfile.PlyElement.describe(table, "vertex")]
    if faces is not None:
        triangles = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
        triangles["vertex_indices"] = faces
        elements.append(
            plyfile.PlyElement.describe(
                triangles, "face", len_types={"vertex_indices": "u1"}, val_types={"vertex_indices": "i4"}
            )
        )
    ply = plyfile.PlyData(elements, text=False, byte_order="<", comments=["written by neuralsurf"])
    with open(path, "wb") as file:
        if faces is None:
            ply.write(file)
            return
        file.write((ply.header + "\n").encode("ascii"))
        file.write(table.tobytes())
        packed = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])  # the rows plyfile would write
        packed["n"], packed["v"] = 3, faces
        file.write(packed.tobytes())


def cloud_from_ply_columns(columns: dict[str, np.ndarray], path: Path) -> PointCloud:
    """Build a cloud from PLY vertex columns: x y z, optional nx ny nz and red green blue."""
    if not {"x", "y", "z"} <= columns.keys():
        raise FileFormatError(
            f"{str(path)!r} has no x, y, z vertex properties (found {sorted(columns)}); "
            f"it is not a point cloud"
        )
    xyz = [columns[k] for k in "xyz"]
    dtype = np.float64 if any(c.dtype == np.float64 for c in xyz) else np.float32
    points = np.stack(xyz, axis=1).astype(dtype)
    normals = colors = None
    if {"nx", "ny", "nz"} <= columns.keys():
        normals = np.stack([columns[k] for k in ("nx", "ny", "nz")], axis=1)
    if {"red", "green", "blue"} <= columns.keys():
        rgb = np.stack([columns[k] for k in ("red", "green", "blue")], axis=1)
        # integer colours span their type's range; float colours are taken as [0, 1]
        scale = np.iinfo(rgb.dtype).max if rgb.dtype.kind in "iu" else 1.0
        colors = rgb.astype(np.float64) / scale
    ignored = sorted(columns.keys() - {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"})
    if ignored:
        warnings.warn(
            f"{str(path)!r}: vertex properties {ignored} are not kept; a PointCloud holds only "
            f"positions, normals and colours",
            stacklevel=4,
        )
    return build_cloud(path, points, normals, colors)


# ---------------------------------------------------------------------------------------------
# readers: path -> PointCloud


def build_cloud(path: Path, points: np.ndarray, normals=None, colors=None) -> PointCloud:
    """A PointCloud from arrays read from `path`; InputError naming the file when it is invalid."""
    if len(points) == 0:
        raise InputError(f"{str(path)!r} contains no points; check the file was written completely")
    try:
        return PointCloud(points, normals, colors)
    except InputError as error:
        raise named(path, error) from error


def _read_ply(path: Path) -> PointCloud:
    try:
        columns, others = read_ply_vertices(path)
    except FileFormatError as error:
        raise named(path, error) from error
    if others:
        warnings.warn(
            f"{str(path)!r}: PLY elements {others} are not kept; use read_mesh for faces", stacklevel=3
        )
    return cloud_from_ply_columns(columns, path)


def _read_xyz(path: Path) -> PointCloud:
    """Whitespace-separated rows `x y z` or `x y z nx ny nz`; `#` starts a comment."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # numpy's "input contained no data"
        try:
            table = np.loadtxt(path, comments="#", dtype=np.float64, ndmin=2)
        except ValueError as error:
            raise FileFormatError(
                f"{str(path)!r} is not a table of numbers ({error}); each row needs 3 (x y z) or "
                f"6 (x y z nx ny nz) numbers"
            ) from error
    if table.size == 0:
        raise InputError(f"{str(path)!r} contains no points; check the file was written completely")
    if table.shape[1] not in (3, 6):
        raise FileFormatError(
            f"{str(path)!r} has {table.shape[1]} columns; .xyz needs 3 (x y z) or 6 (x y z nx ny nz)"
        )
    return build_cloud(path, table[:, :3], table[:, 3:] if table.shape[1] == 6 else None)


def _read_npy(path: Path) -> PointCloud:
    """An (n, 3) array of points or (n, 6) of points and normals."""
    with open(path, "rb") as file:
        if file.read(6) != b"\x93NUMPY":
            raise FileFormatError(f"{str(path)!r} is not a .npy file (no NUMPY header); save it with np.save")
    try:
        table = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as error:
        raise FileFormatError(f"{str(path)!r} is not a readable .npy array: {error}") from error
    if table.ndim != 2 or table.shape[1] not in (3, 6) or table.dtype.kind not in "fiu":
        raise FileFormatError(
            f"{str(path)!r} holds a {table.dtype} array of shape {table.shape}; "
            f"save a float array of shape (n, 3) (points) or (n, 6) (points and normals)"
        )
    return build_cloud(path, table[:, :3], table[:, 3:] if table.shape[1] == 6 else None)


def parse_pcd_header(data: bytes) -> dict[str, list[str]]:
    """The PCD header as {keyword: values}, up to and including DATA."""
    header = {}
    for raw in data.split(b"\n"):
        line = raw.decode("ascii", errors="replace").strip()
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    missing = [k for k in ("FIELDS", "SIZE", "POINTS", "DATA") if k not in header]
    if missing:
        raise FileFormatError(f"PCD header lacks {', '.join(missing)}; the file is not a valid PCD")
    if not {"x", "y", "z"} <= set(header["FIELDS"]) or len(header["SIZE"]) != len(header["FIELDS"]):
        raise FileFormatError(f"PCD header needs fields x y z with one SIZE each, got {header['FIELDS']}")
    return header


def _read_pcd(path: Path) -> PointCloud:
    """Through Open3D; the header tells float32 from float64 and which fields Open3D drops."""
    import open3d as o3d

    try:
        header = parse_pcd_header(path.read_bytes()[:4096])
    except FileFormatError as error:
        raise named(path, error) from error
    declared = int(header["POINTS"][0]) if header["POINTS"][:1] and header["POINTS"][0].isdigit() else -1
    if declared == 0:
        raise InputError(f"{str(path)!r} contains no points (POINTS 0)")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    if len(cloud.points) != declared:
        raise FileFormatError(
            f"Open3D could not read {str(path)!r}: the header declares {' '.join(header['POINTS'])} points "
            f"but {len(cloud.points)} were read; the data section is truncated, corrupt or uses an "
            f"unsupported layout (DATA {' '.join(header['DATA'])})"
        )
    kept = {"x", "y", "z", "normal_x", "normal_y", "normal_z", "rgb", "rgba"}
    ignored = [f for f in header["FIELDS"] if f not in kept]
    if ignored:
        warnings.warn(f"{str(path)!r}: PCD fields {ignored} are not kept", stacklevel=3)
    size = dict(zip(header["FIELDS"], header["SIZE"]))
    dtype = np.float64 if size["x"] == "8" else np.float32
    points = np.asarray(cloud.points).astype(dtype)
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    colors = np.asarray(cloud.colors) if cloud.has_colors() else None
    return build_cloud(path, points, normals, colors)


_READERS = {".ply": _read_ply, ".xyz": _read_xyz, ".npy": _read_npy, ".pcd": _read_pcd}


def read_point_cloud(path: PathLike) -> PointCloud:
    """Read a point cloud from a .ply, .xyz, .npy or .pcd file (extension case-insensitive).

    Returns a PointCloud: points (n, 3) float32, or float64 where the file stores float64 (and for
    .xyz text); normals (n, 3) and colours (n, 3) in [0, 1] when the file has them.
    Raises FileFormatError for a missing, unknown or corrupt file and InputError for a file with
    no points or with NaN/inf values.
    """
    path, ext = readable_path(path, SUPPORTED, "point cloud")
    return _READERS[ext](path)


# ---------------------------------------------------------------------------------------------
# writers: PointCloud -> path


def _numpy(tensor: torch.Tensor | None) -> np.ndarray | None:
    return None if tensor is None else tensor.detach().cpu().numpy()


def _write_ply(path: Path, cloud: PointCloud) -> None:
    points, normals, colors = _numpy(cloud.points), _numpy(cloud.normals), _numpy(cloud.colors)
    vertex = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    if normals is not None:
        vertex |= {"nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]}
    if colors is not None:
        rgb = colors_to_uint8(colors, path)
        vertex |= {"red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    write_ply(path, vertex)


def _write_xyz(path: Path, cloud: PointCloud) -> None:
    if cloud.colors is not None:
        warn_dropped(path, "colours", ".xyz", "use .ply or .pcd to keep them")
    table = _numpy(cloud.points)
    if cloud.normals is not None:
        table = np.concatenate([table, _numpy(cloud.normals)], axis=1)
    digits = "%.17g" if table.dtype == np.float64 else "%.9g"  # enough to round-trip exactly
    columns = "x y z nx ny nz" if table.shape[1] == 6 else "x y z"
    np.savetxt(path, table, fmt=digits, header=columns)


def _write_npy(path: Path, cloud: PointCloud) -> None:
    if cloud.colors is not None:
        warn_dropped(path, "colours", ".npy", "use .ply or .pcd to keep them")
    table = _numpy(cloud.points)
    if cloud.normals is not None:
        table = np.concatenate([table, _numpy(cloud.normals)], axis=1)
    with open(path, "wb") as file:  # np.save(path) would append ".npy" to a ".NPY" name
        np.save(file, table)


def _write_pcd(path: Path, cloud: PointCloud) -> None:
    import open3d as o3d

    out = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_numpy(cloud.points).astype(np.float64)))
    if cloud.normals is not None:
        out.normals = o3d.utility.Vector3dVector(_numpy(cloud.normals).astype(np.float64))
    if cloud.colors is not None:
        rgb = colors_to_uint8(_numpy(cloud.colors), path)
        out.colors = o3d.utility.Vector3dVector(rgb.astype(np.float64) / 255)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok = o3d.io.write_point_cloud(str(path), out, write_ascii=False)
    if not ok:
        raise FileFormatError(f"Open3D could not write {str(path)!r}; check the folder is writable")


_WRITERS = {".ply": _write_ply, ".xyz": _write_xyz, ".npy": _write_npy, ".pcd": _write_pcd}


def write_point_cloud(path: PathLike, cloud: PointCloud) -> None:
    """Write `cloud` (points (n, 3), optional normals and colours) by the extension of `path`.

    .npy holds (n, 3) or (n, 6) = points and normals in the cloud's dtype (exact); .xyz holds the
    same as text with round-trip digits; .ply (binary) keeps float32/float64 and 8-bit colours;
    .pcd (Open3D) stores float32 and 8-bit colours. Colours are not storable in .xyz and .npy: a
    warning says so. Parent folders are created.
    """
    if not isinstance(cloud, PointCloud):
        raise InputError(f"write_point_cloud needs a PointCloud, got {type(cloud).__name__}; wrap arrays "
                         f"with PointCloud(points, normals, colors)")
    path, ext = writable_path(path, SUPPORTED, "point cloud")
    _WRITERS[ext](path, cloud)
