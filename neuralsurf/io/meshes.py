"""Read and write triangle meshes: .ply .obj .off .stl .glb.

Reading goes through trimesh with `process=False`, so vertex order, count and face orientation stay
as stored. Formats that store triangle soups or split vertices at texture/normal seams (.obj, .stl,
.glb) then get bit-identical vertices merged, in order of first use, so that a closed surface comes
back watertight. A .glb scene is concatenated into one mesh with its node transforms applied.

Writing keeps the mesh's own precision in .ply (binary float32/float64), .obj and .off (text with
round-trip digits); .stl and .glb store float32. Vertex colours survive .ply, .obj and .glb (8-bit).
.ply, .obj and .glb also get per-vertex normals (`vertex_normals`: area-weighted, outward for faces
that are counter-clockwise seen from outside, as every neuralsurf mesh is). `write_mesh` is the one
writer; `Mesh.save` calls it.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.geometry import merge_duplicate_vertices, vertex_normals
from neuralsurf.io.pointclouds import (
    PathLike,
    colors_to_uint8,
    named,
    readable_path,
    warn_dropped,
    writable_path,
    write_ply,
)
from neuralsurf.structures import Mesh

SUPPORTED = (".ply", ".obj", ".off", ".stl", ".glb")
"""Mesh file extensions, matched case-insensitively."""

FORMATS = tuple(ext[1:] for ext in SUPPORTED)
"""Mesh format names (a config's `extract.format`, evaluate.py's `mesh_format`)."""

_MERGED = (".obj", ".stl", ".glb")
"""Formats whose loaders may duplicate vertices (soups, seams, scene parts)."""


def _load_trimesh(path: Path, ext: str):
    """trimesh.Trimesh of every triangle mesh in the file, concatenated with transforms applied."""
    import trimesh

    try:
        scene = trimesh.load_scene(str(path), file_type=ext[1:], process=False)
        parts = scene.dump()
    except Exception as error:  # trimesh raises many types on corrupt input
        raise FileFormatError(
            f"trimesh could not read {str(path)!r} as {ext}: {type(error).__name__}: {error}; "
            f"the file is corrupt or not a {ext} file"
        ) from error
    meshes = [p for p in parts if isinstance(p, trimesh.Trimesh) and len(p.faces)]
    others = sorted({type(p).__name__ for p in parts if not isinstance(p, trimesh.Trimesh)})
    if others and meshes:
        warnings.warn(f"{str(path)!r}: non-mesh geometry ({', '.join(others)}) is not kept", stacklevel=3)
    if not meshes:
        hint = (
            "it holds only points: use read_point_cloud"
            if "PointCloud" in others
            else f"check it is a complete, valid {ext} file"
        )
        raise InputError(f"{str(path)!r} contains no triangles that trimesh could read; {hint}")
    return meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)


def _vertex_colors(mesh, path: Path) -> np.ndarray | None:
    """(v, 3) colours in [0, 1] from trimesh's visual; warns about appearance data not kept."""
    visual = mesh.visual
    if visual.kind == "face":
        warnings.warn(f"{str(path)!r}: face colours are not kept (Mesh holds vertex colours)", stacklevel=3)
    if visual.kind == "texture" and getattr(visual, "uv", None) is not None:
        warnings.warn(f"{str(path)!r}: texture coordinates and materials are not kept", stacklevel=3)
    if visual.kind != "vertex":
        return None
    rgba = np.asarray(visual.vertex_colors)
    if (rgba[:, 3] < 255).any():
        warnings.warn(f"{str(path)!r}: vertex alpha is not kept (Mesh holds RGB)", stacklevel=3)
    return rgba[:, :3] / 255.0


def read_mesh(path: PathLike) -> Mesh:
    """Read a triangle mesh from .ply, .obj, .off, .stl or .glb (extension case-insensitive).

    Returns a Mesh: vertices (v, 3) float64, faces (f, 3) int64 in stored order and orientation,
    vertex colours (v, 3) when the file has them. Raises FileFormatError for a missing, unknown or
    corrupt file and InputError for a file without triangles or with NaN/inf vertices.
    """
    path, ext = readable_path(path, SUPPORTED, "mesh")
    loaded = _load_trimesh(path, ext)
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    colors = _vertex_colors(loaded, path)
    if ext in _MERGED:
        vertices, faces, colors = merge_duplicate_vertices(vertices, faces, colors)
    try:
        return Mesh(vertices, faces, colors)
    except InputError as error:
        raise named(path, error) from error


# ---------------------------------------------------------------------------------------------
# writers


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> None:
    normals = vertex_normals(vertices, faces)
    vertex = {"x": vertices[:, 0], "y": vertices[:, 1], "z": vertices[:, 2],
              "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]}
    if colors is not None:
        rgb = colors_to_uint8(colors, path)
        vertex |= {"red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    write_ply(path, vertex, faces)


def _digits(vertices: np.ndarray) -> str:
    """printf format that round-trips the dtype of `vertices` exactly."""
    return "%.17g" if vertices.dtype == np.float64 else "%.9g"


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> None:
    table, fmt = vertices, ["v " + _digits(vertices)] + [_digits(vertices)] * 2
    if colors is not None:  # the common "v x y z r g b" extension
        table = np.concatenate([vertices.astype(np.float64), np.clip(colors, 0, 1)], axis=1)
        fmt += ["%.6g"] * 3
    with open(path, "w") as file:
        file.write("# written by neuralsurf\n")
        np.savetxt(file, table, fmt=" ".join(fmt))
        np.savetxt(file, vertex_normals(vertices, faces), fmt="vn %.7g %.7g %.7g")
        np.savetxt(file, np.repeat(faces + 1, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")  # vertex k has normal k


def _write_off(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> None:
    if colors is not None:
        warn_dropped(path, "vertex colours", ".off", "use .ply, .obj or .glb to keep them")
    with open(path, "w") as file:
        file.write(f"OFF\n{len(vertices)} {len(faces)} 0\n")
        np.savetxt(file, vertices, fmt=_digits(vertices))
        np.savetxt(file, faces, fmt="3 %d %d %d")


def _write_with_trimesh(ext: str):
    def write(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> None:
        import trimesh

        if colors is not None and ext == ".stl":
            warn_dropped(path, "vertex colours", ".stl", "use .ply, .obj or .glb to keep them")
            colors = None
        if colors is not None:
            colors = colors_to_uint8(colors, path)
        normals = vertex_normals(vertices, faces) if ext == ".glb" else None
        mesh = trimesh.Trimesh(vertices, faces, vertex_normals=normals, vertex_colors=colors, process=False)
        mesh.export(str(path), file_type=ext[1:], **({"include_normals": True} if ext == ".glb" else {}))

    return write


_WRITERS = {
    ".ply": _write_ply,
    ".obj": _write_obj,
    ".off": _write_off,
    ".stl": _write_with_trimesh(".stl"),
    ".glb": _write_with_trimesh(".glb"),
}


def mesh_format(name: str) -> str:
    """A mesh format name ("ply", ".GLB", ...) checked and as the extension to write: ".ply", ".glb", ...

    Raises ConfigError naming the choices (`FORMATS`) for any other value."""
    ext = "." + str(name).lower().lstrip(".")
    if ext not in SUPPORTED:
        raise ConfigError(
            f"unknown mesh format {name!r}; choose one of {', '.join(FORMATS)} (ply, glb and obj keep vertex "
            f"normals and colours)"
        )
    return ext


def write_mesh(path: PathLike, mesh: Mesh) -> None:
    """Write `mesh` (vertices (v, 3), faces (f, 3), optional vertex colours) by the extension of `path`.

    .ply (binary) keeps float32/float64 vertices; .obj and .off are text with round-trip digits;
    .stl and .glb store float32. .ply, .obj and .glb also store outward unit vertex normals
    (`vertex_normals`). Vertex colours go to .ply, .obj, .glb; .off and .stl cannot store them (a
    warning says so). Parent folders are created. FileFormatError when the file cannot be written.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(
            f"write_mesh needs a Mesh, got {type(mesh).__name__}; build one with Mesh(vertices, faces) "
            f"or Mesh.from_trimesh(...)"
        )
    path, ext = writable_path(path, SUPPORTED, "mesh")
    vertices = mesh.vertices.detach().cpu().numpy()
    colors = None if mesh.vertex_colors is None else mesh.vertex_colors.detach().cpu().numpy()
    try:
        _WRITERS[ext](path, vertices, mesh.faces.cpu().numpy(), colors)
    except OSError as error:
        raise FileFormatError(f"cannot write mesh file {str(path)!r}: {error.strerror or error}; check that its "
                              f"folder is writable, or write somewhere else") from None
