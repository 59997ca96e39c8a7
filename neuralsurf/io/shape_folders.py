"""Shape collections on disk: a folder of meshes, one class per subfolder, and Occupancy Networks'
preprocessed layout.

Mesh folder (any of `.ply .obj .off .stl .glb`, extension case-insensitive)::

    <root>/<class>/<name>.obj                     a shape is a mesh file in its class folder,
    <root>/<class>/<name>/models/model.obj        or a subfolder holding exactly one mesh (ShapeNet)
    <root>/<class>/train.lst, val.lst, test.lst   optional: one shape name per line

Occupancy Networks' layout (Mescheder et al. 2019, their preprocessed ShapeNet)::

    <root>/<class>/<name>/points.npz       points (n, 3), occupancies (n,) bool or packed bits
    <root>/<class>/<name>/pointcloud.npz   points (m, 3), normals (m, 3): surface samples
    <root>/<class>/{train,val,test}.lst

Both list `ShapeEntry`s (class, name, path, split from the .lst files or None) in sorted order;
`read_occupancy_shape` reads one shape of the second layout. The files' frame is kept: Occupancy
Networks' shapes already lie in the unit cube (longest side 1, centred), their samples in the cube
padded by 0.05 on each side.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import FileFormatError, InputError
from neuralsurf.io.meshes import SUPPORTED as MESH_SUFFIXES
from neuralsurf.io.npz import read_npz
from neuralsurf.io.pointclouds import PathLike

SPLITS = ("train", "val", "test")
"""Split list files `<class>/<split>.lst`."""


@dataclass(frozen=True)
class ShapeEntry:
    """One shape of a folder collection."""

    category: str
    """Its class: the subfolder's name."""
    name: str
    """The mesh file's stem or the shape folder's name (unique within its class)."""
    path: Path
    """The mesh file (mesh folders) or the shape's folder (Occupancy Networks' layout)."""
    split: str | None = None
    """"train", "val" or "test" from the class's .lst files; None when it has none."""


@dataclass(frozen=True)
class OccupancyShape:
    """One shape of Occupancy Networks' layout, in its files' frame."""

    points: Tensor
    """Float[Tensor, "n 3"]: query points (uniform in the padded cube, and near the surface)."""
    occupancies: Tensor
    """Bool[Tensor, "n"]: whether each point is inside."""
    surface: Tensor
    """Float[Tensor, "m 3"]: surface samples."""
    normals: Tensor | None
    """Float[Tensor, "m 3"] | None: their normals."""


def _folder(root: PathLike, what: str) -> Path:
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileFormatError(f"{what} folder {str(root)!r} not found (or not a folder); pass the folder that "
                              f"holds one subfolder per class")
    return root


def _splits(folder: Path) -> dict[str, str]:
    """Shape name -> split from `<folder>/<split>.lst` (empty when there are none). A name in two
    lists is an InputError."""
    found: dict[str, str] = {}
    for split in SPLITS:
        path = folder / f"{split}.lst"
        if not path.is_file():
            continue
        for line in path.read_text().splitlines():
            name = line.strip()
            if not name:
                continue
            if name in found and found[name] != split:
                raise InputError(f"{folder}: shape {name!r} is listed in both {found[name]}.lst and {split}.lst; "
                                 f"keep it in one")
            found[name] = split
    return found


def _mesh_of(folder: Path) -> Path | None:
    """The one mesh file anywhere below `folder`; None when there is none, InputError when several."""
    meshes = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    if len(meshes) > 1:
        raise InputError(f"shape folder {folder} holds {len(meshes)} meshes ({meshes[0].name}, {meshes[1].name}, ...); "
                         f"a shape folder must hold one mesh: move the others out or make each its own shape")
    return meshes[0] if meshes else None


def _classes(root: Path, layout: str) -> list[Path]:
    classes = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not classes:
        raise InputError(f"{layout} {str(root)!r} has no class subfolders; put each class's shapes in "
                         f"<root>/<class>/ (see neuralsurf.io.shape_folders)")
    return classes


def _with_splits(entries: list[ShapeEntry], folder: Path) -> list[ShapeEntry]:
    """Entries with their split from the class's .lst files; names listed there but absent warn."""
    splits = _splits(folder)
    missing = sorted(set(splits) - {e.name for e in entries})
    if missing:
        warnings.warn(f"{folder}: {len(missing)} shapes named in its .lst files are missing (e.g. {missing[0]!r}); "
                      f"they are left out", stacklevel=3)
    if splits:
        unlisted = [e.name for e in entries if e.name not in splits]
        if unlisted:
            warnings.warn(f"{folder}: {len(unlisted)} shapes are in no .lst file (e.g. {unlisted[0]!r}); they are "
                          f"left out", stacklevel=3)
        entries = [e for e in entries if e.name in splits]
    return [ShapeEntry(e.category, e.name, e.path, splits.get(e.name)) for e in entries]


def list_mesh_folder(root: PathLike) -> list[ShapeEntry]:
    """Every shape of a mesh folder (see the module docstring), classes and names sorted.

    Raises FileFormatError when `root` is not a folder and InputError when it holds no class
    subfolders or no meshes; a class folder without meshes warns and is skipped.
    """
    root = _folder(root, "mesh collection")
    entries = []
    for folder in _classes(root, "mesh collection"):
        shapes = []
        for path in sorted(folder.iterdir()):
            if path.is_file() and path.suffix.lower() in MESH_SUFFIXES:
                shapes.append(ShapeEntry(folder.name, path.stem, path))
            elif path.is_dir() and not path.name.startswith("."):
                mesh = _mesh_of(path)
                if mesh is not None:
                    shapes.append(ShapeEntry(folder.name, path.name, mesh))
        names = [s.name for s in shapes]
        if len(set(names)) != len(names):
            twice = sorted({n for n in names if names.count(n) > 1})
            raise InputError(f"class folder {folder} has two shapes named {twice[0]!r} (e.g. {twice[0]}.obj and "
                             f"{twice[0]}.ply); rename one")
        if not shapes:
            warnings.warn(f"class folder {folder} holds no meshes ({', '.join(MESH_SUFFIXES)}); skipped", stacklevel=2)
            continue
        entries += _with_splits(shapes, folder)
    if not entries:
        raise InputError(f"mesh collection {str(root)!r} holds no meshes ({', '.join(MESH_SUFFIXES)}) in its class "
                         f"subfolders")
    return entries


def list_occupancy_folder(root: PathLike) -> list[ShapeEntry]:
    """Every shape of Occupancy Networks' layout: the folders `<root>/<class>/<name>/` that hold a
    `points.npz`, with their split from `<class>/<split>.lst`. Raises FileFormatError / InputError as
    `list_mesh_folder`."""
    root = _folder(root, "Occupancy Networks")
    entries = []
    for folder in _classes(root, "Occupancy Networks folder"):
        shapes = [ShapeEntry(folder.name, p.name, p) for p in sorted(folder.iterdir())
                  if p.is_dir() and (p / "points.npz").is_file()]
        if not shapes:
            warnings.warn(f"class folder {folder} holds no <shape>/points.npz; skipped", stacklevel=2)
            continue
        entries += _with_splits(shapes, folder)
    if not entries:
        raise InputError(f"{str(root)!r} holds no <class>/<shape>/points.npz: not Occupancy Networks' layout")
    return entries


def folder_layout(root: PathLike) -> str:
    """"occupancy" when some `<root>/<class>/<shape>/points.npz` exists, else "meshes"."""
    root = _folder(root, "shape collection")
    return "occupancy" if next(root.glob("*/*/points.npz"), None) is not None else "meshes"


def _arrays(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise FileFormatError(f"{path} not found; each Occupancy Networks shape folder needs points.npz and "
                              f"pointcloud.npz")
    return read_npz(path, keys)  # headers checked against the file's size, numbers only


def unpack_occupancies(occupancies: np.ndarray, n: int, path: Path | str = "occupancies") -> np.ndarray:
    """Bool (n,) occupancies from an array of n booleans/0-1 values or of ceil(n / 8) bytes of packed
    bits (numpy's packbits, big-endian within each byte: Occupancy Networks' files)."""
    occupancies = np.asarray(occupancies).ravel()
    if len(occupancies) == n:
        return occupancies.astype(bool)
    if occupancies.dtype == np.uint8 and len(occupancies) == (n + 7) // 8:
        return np.unpackbits(occupancies)[:n].astype(bool)
    raise FileFormatError(f"{path}: {len(occupancies)} occupancies ({occupancies.dtype}) for {n} points; expected "
                          f"{n} values or {(n + 7) // 8} bytes of packed bits")


def read_occupancy_shape(folder: PathLike) -> OccupancyShape:
    """One shape of Occupancy Networks' layout: `points.npz` (points, occupancies) and
    `pointcloud.npz` (points, normals when present), as float32 / bool tensors in the files' frame.
    Raises FileFormatError for missing or foreign files, InputError for non-finite points."""
    folder = Path(folder)
    queries = _arrays(folder / "points.npz", ("points", "occupancies"))
    cloud = _arrays(folder / "pointcloud.npz", ("points",))
    points = np.asarray(queries["points"], dtype=np.float32)
    surface = np.asarray(cloud["points"], dtype=np.float32)
    normals = np.asarray(cloud["normals"], dtype=np.float32) if "normals" in cloud else None
    for name, array in (("points.npz points", points), ("pointcloud.npz points", surface), ("normals", normals)):
        if array is None:
            continue
        if array.ndim != 2 or array.shape[1] != 3:
            raise FileFormatError(f"{folder}: {name} have shape {array.shape}; expected (n, 3)")
        if not np.isfinite(array).all():
            raise InputError(f"{folder}: {name} contain NaN or inf; regenerate the shape's files")
    if normals is not None and len(normals) != len(surface):
        raise FileFormatError(f"{folder}: {len(normals)} normals for {len(surface)} surface points")
    occupancies = unpack_occupancies(queries["occupancies"], len(points), folder / "points.npz")
    return OccupancyShape(torch.from_numpy(points), torch.from_numpy(occupancies), torch.from_numpy(surface),
                          None if normals is None else torch.from_numpy(normals))
