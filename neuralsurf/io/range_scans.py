"""Range scans with a Stanford/Scanalyze `.conf` alignment (the Stanford 3D Scanning Repository).

A `.conf` file lists one line per scan, `bmesh <file> tx ty tz qi qj qk qr`, plus optional
`camera tx ty tz qi qj qk qr` lines (a viewer's camera, ignored here) and optional
`mesh <file> tx ty tz qi qj qk qr` lines (a reference mesh in the same common frame, often not
shipped with the scans: `read_range_scan_meshes` reads those present, and a warning names those
absent). Conventions, worked out
numerically on the Stanford bunny: only this reading makes the ten scans agree with
`bun_zipper.ply` (median point-to-mesh distance 0.064 mm, 0.52 mm to the nearest mesh vertex);
R(q) instead of R(q)^T, R^T (p - t), R (p + t) or a scalar-first quaternion leave 12-320 mm:

- the quaternion is stored vector part first, scalar last: (qi, qj, qk, qr) = (x, y, z, w);
- the transform maps scan -> common (world) frame as `world = R(q)^T @ scan + t`, where `R(q)` is
  the usual (Hamilton) rotation matrix of q: the rotation applied is that of the conjugate
  quaternion, then the translation.

The scan files are PLY: vertices in the scanner's frame, and either `face` triangles or a
Cyberware `range_grid` (one list per grid cell, `num_rows` x `num_cols` from the `obj_info` lines,
row-major) that is triangulated here. The scanner sits on the +z side of its frame, looking along
-z (again checked against the reconstruction's outward normals: 97 % of each scan's points have
outward normals with n_z > 0), so normals are oriented towards +z.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.cameras import quaternion_to_matrix, render_depth
from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.io.meshes import read_mesh
from neuralsurf.io.pointclouds import (
    PathLike,
    ascii_rows,
    build_cloud,
    named,
    ply_header,
    read_ply_binary,
    read_ply_vertices,
)
from neuralsurf.progress import progress_bar
from neuralsurf.structures import DepthFrames, Mesh, PointCloud

SCANNER_DIRECTION = (0.0, 0.0, 1.0)
"""Direction from a scan's points towards its scanner, in the scan's own frame (+z)."""

_MAX_EDGE_FACTOR = 4.0
"""Range-grid triangles with an edge longer than this many median edges are dropped (they would
bridge depth discontinuities)."""


# ---------------------------------------------------------------------------------------------
# .conf


def conf_transform(translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """The scan -> world 4x4 (float64) of one `.conf` line: `[R(q)^T, t; 0 0 0 1]`, q = (x, y, z, w)."""
    transform = np.eye(4)
    transform[:3, :3] = quaternion_to_matrix(quaternion).T
    transform[:3, 3] = translation
    return transform


_CONF_KEYWORDS = ("bmesh", "mesh", "camera")


def _parse_conf(path: Path) -> tuple[list[tuple[str, Tensor]], list[tuple[int, str, Tensor]]]:
    """The `bmesh` lines `(file, transform)` and the `mesh` lines `(line number, file, transform)`
    of a `.conf` file, in file order (see `read_range_scan_conf`)."""
    scans, meshes = [], []
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        keyword = words[0]
        if keyword not in _CONF_KEYWORDS:
            raise FileFormatError(
                f"{str(path)!r} line {number}: unknown keyword {keyword!r} in {line.strip()!r}; expected "
                f"'bmesh <file> tx ty tz qi qj qk qr', 'mesh <file> tx ty tz qi qj qk qr' or 'camera tx ty tz qi qj qk qr'"
            )
        numbers = words[2:] if keyword != "camera" else words[1:]
        try:
            values = np.array(numbers, dtype=np.float64)
        except ValueError:
            values = np.empty(0)
        if (keyword != "camera" and len(words) < 2) or len(values) != 7 or not np.isfinite(values).all():
            raise FileFormatError(
                f"{str(path)!r} line {number}: cannot parse {line.strip()!r}; expected "
                f"'{keyword}{' <file>' if keyword != 'camera' else ''} tx ty tz qi qj qk qr' (7 numbers)"
            )
        if np.linalg.norm(values[3:]) < 1e-8:
            raise FileFormatError(f"{str(path)!r} line {number}: the quaternion is zero in {line.strip()!r}")
        if keyword == "bmesh":
            scans.append((words[1], torch.from_numpy(conf_transform(values[:3], values[3:]))))
        elif keyword == "mesh":
            meshes.append((number, words[1], torch.from_numpy(conf_transform(values[:3], values[3:]))))
    return scans, meshes


def _warn_absent_meshes(path: Path, meshes: list[tuple[int, str, Tensor]]) -> None:
    """Warn once per `mesh` line of `path` whose file is not in the `.conf`'s folder."""
    for number, name, _ in meshes:
        if not (path.parent / name).is_file():
            warnings.warn(
                f"{str(path)!r} line {number} lists the reference mesh {name!r}, which is not in "
                f"{str(path.parent)!r}; the scans are read without it (put the file there to use it "
                f"through read_range_scan_meshes)",
                stacklevel=3,
            )


def read_range_scan_conf(path: PathLike) -> list[tuple[str, Tensor]]:
    """Parse a Scanalyze `.conf` file.

    Returns:
        one `(file name, transform)` per `bmesh` line, in file order; `transform` is a
        Float64[Tensor, "4 4"] mapping the scan's points to the common frame (module docstring).
        `camera` lines, blank lines and `#` comments are skipped; `mesh` lines (reference meshes)
        are checked like the others and left to `read_range_scan_meshes`, with a warning for each
        listed file that is absent.
    Raises:
        FileFormatError for a missing file, a line that does not parse (naming its number), a
        zero quaternion, or a file without any `bmesh` line.
    """
    path = _existing_file(path, "range-scan .conf")
    scans, meshes = _parse_conf(path)
    if not scans:
        raise FileFormatError(
            f"{str(path)!r} has no 'bmesh <file> tx ty tz qi qj qk qr' line; it lists no scans"
        )
    _warn_absent_meshes(path, meshes)
    return scans


def read_range_scan_meshes(conf_path: PathLike) -> list[Mesh]:
    """The reference meshes of a `.conf` file's `mesh <file> tx ty tz qi qj qk qr` lines, in the
    common frame of its scans (same transform convention as `bmesh`, applied in float64).

    Mesh files are looked up relative to the `.conf`'s folder. They are optional: a listed file that
    is absent is skipped with a warning naming it, so the result may be empty.

    Returns:
        one Mesh per `mesh` line whose file exists, in file order (vertices in the file's dtype).
    Raises:
        FileFormatError as `read_range_scan_conf` for the `.conf` itself, or as `read_mesh` for a
        mesh file that exists but cannot be read.
    """
    conf_path = _existing_file(conf_path, "range-scan .conf")
    _, entries = _parse_conf(conf_path)
    _warn_absent_meshes(conf_path, entries)
    meshes = []
    for _, name, transform in entries:
        if (conf_path.parent / name).is_file():
            mesh = read_mesh(conf_path.parent / name)
            rotation, translation = transform[:3, :3], transform[:3, 3]
            vertices = (mesh.vertices.double() @ rotation.T + translation).to(mesh.vertices.dtype)
            meshes.append(Mesh(vertices, mesh.faces, mesh.vertex_colors))
    return meshes


# ---------------------------------------------------------------------------------------------
# scans


def read_range_scans(conf_path: PathLike, with_normals: bool = True, progress: bool = True) -> list[PointCloud]:
    """Read every scan of a `.conf` file, aligned into the `.conf`'s common frame.

    Scan files are looked up relative to the `.conf`'s folder. Normals (when asked for) are those of
    `read_range_scan`, rotated with the points; the transform is applied in float64. `progress`: a
    bar over the scans when reading lasts more than a few seconds (neuralsurf.progress).

    Returns:
        one PointCloud per `bmesh` line, in file order: points (n_i, 3) in the file's dtype,
        normals (n_i, 3) unit, pointing towards the scanner, or None.
    """
    conf_path = Path(conf_path)
    clouds = []
    scans = read_range_scan_conf(conf_path)
    for name, transform in progress_bar(scans, desc=f"range scans {conf_path.name}", unit="scan", enabled=progress):
        path = conf_path.parent / name
        points, normals = _read_scan_arrays(path, with_normals)
        rotation, translation = transform[:3, :3].numpy(), transform[:3, 3].numpy()
        points = (points.astype(np.float64) @ rotation.T + translation).astype(points.dtype)
        normals = None if normals is None else normals @ rotation.T
        clouds.append(build_cloud(path, points, normals))
    return clouds


def read_range_scan(path: PathLike, with_normals: bool = True) -> PointCloud:
    """One range scan (PLY) in its scanner's frame.

    Normals, when asked for, are area-weighted vertex normals of the scan's triangles (`face`
    element, or the triangulated `range_grid`), oriented towards the scanner (+z, see the module
    docstring); vertices that no triangle touches (and scans without triangles) get PCA normals
    from 30 neighbours, oriented the same way.

    Returns:
        PointCloud with points (n, 3) in the file's dtype and normals (n, 3) or None.
    """
    path = Path(path)
    return build_cloud(path, *_read_scan_arrays(path, with_normals))


def _read_scan_arrays(path: Path, with_normals: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (n, 3) in the file's dtype and normals (n, 3) float64 or None of a range-scan PLY."""
    points, triangles = _read_scan_geometry(path, with_triangles=with_normals)
    return points, scan_normals(points, triangles) if with_normals else None


def _read_scan_geometry(path: Path, with_triangles: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (n, 3) in the file's dtype and triangles (f, 3) int64 (or None) of a range-scan PLY."""
    path = _existing_file(path, "range scan")
    data = path.read_bytes()
    try:
        columns, _ = read_ply_vertices(path, data)
        if not {"x", "y", "z"} <= columns.keys():
            raise FileFormatError(
                f"no x, y, z vertex properties (found {sorted(columns)}); it is not a range scan"
            )
        points = np.stack([columns[k] for k in "xyz"], axis=1)
        triangles = _ply_triangles(path, data, points) if with_triangles else None
    except FileFormatError as error:
        raise named(path, error) from error
    if len(points) == 0:
        raise InputError(f"{str(path)!r} contains no points; check the file was written completely")
    return points, triangles


def read_range_scan_frames(
    conf_path: PathLike, pixel_size: float = 2.5e-4, distance: float = 1.0, progress: bool = True
) -> DepthFrames:
    """Every scan of a `.conf` file as a depth image from its scanner's side, for TSDF fusion.

    A Cyberware scanner is not a pinhole camera, so each scan's triangles (module docstring) are
    ray cast by a pinhole camera placed `distance` beyond the scan on its scanner's side (+z of the
    scan frame), looking along -z, with a footprint of `pixel_size` per pixel at the scan: the rays
    are nearly parallel to the scanner's, and every depth is a point of the scan's own surface.
    All frames share one image size (the largest scan's, centred on each scan's box). `progress`:
    a bar over reading and ray casting the scans when that lasts more than a few seconds.

    Returns:
        DepthFrames (n_scans, h, w), depth in the scans' units (0 where no triangle is hit),
        cam_to_world = `.conf` transform @ camera-in-scan pose (world = the `.conf`'s common frame).
    Raises:
        FileFormatError for a scan without triangles (no `face` or `range_grid` element);
        ConfigError for a non-positive pixel_size or distance.
    """
    for name, value in (("pixel_size", pixel_size), ("distance", distance)):
        if not (np.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be a positive length in the scans' units, got {value}")
    conf_path = Path(conf_path)
    scans = []
    entries = read_range_scan_conf(conf_path)
    bar = progress_bar(desc=f"range scans {conf_path.name}", total=2 * len(entries), unit="step", enabled=progress)
    for name, transform in entries:
        points, triangles = _read_scan_geometry(conf_path.parent / name)
        bar.update()
        if triangles is None or len(triangles) == 0:
            raise FileFormatError(
                f"{str(conf_path.parent / name)!r} has no triangles (ASCII 'face' or 'range_grid' element); "
                f"a depth image needs the scan's surface, not only its points"
            )
        scans.append((Mesh(torch.from_numpy(points.astype(np.float64)), torch.from_numpy(triangles)), transform))
    lows, highs = zip(*(mesh.bounds for mesh, _ in scans))
    focals = [(distance + float(hi[2] - lo[2])) / pixel_size for lo, hi in zip(lows, highs)]  # footprint at the far side
    half = max(float(((hi - lo)[:2] / 2).max()) * f / distance for lo, hi, f in zip(lows, highs, focals))
    size = 2 * int(np.ceil(half)) + 4  # the nearest points spread widest; a 2-pixel border
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # camera x = x, y = -y, z = -z
    depths, Ks, poses = [], [], []
    for (mesh, transform), lo, hi, focal in zip(scans, lows, highs, focals):
        camera = torch.eye(4, dtype=torch.float64)
        camera[:3, :3] = flip
        camera[:3, 3] = torch.stack([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] + distance])
        K = torch.tensor([[focal, 0, (size - 1) / 2], [0, focal, (size - 1) / 2], [0, 0, 1]], dtype=torch.float64)
        depth, _ = render_depth(mesh, K[None], camera[None], size, size)
        depths.append(depth[0])
        Ks.append(K)
        poses.append(transform @ camera)
        bar.update()
    bar.close()
    return DepthFrames(torch.stack(depths), torch.stack(Ks), torch.stack(poses))


def scan_normals(points: np.ndarray, triangles: np.ndarray | None) -> np.ndarray:
    """Unit normals (n, 3) of a scan's points (n, 3) in its scanner frame, facing the scanner (+z).

    `triangles` (f, 3) int, or None, gives area-weighted vertex normals; a global flip turns them
    towards the scanner (a scan's triangles share one winding). Vertices without a triangle get
    PCA normals of their 30 nearest points, each flipped towards +z.
    """
    view = np.asarray(SCANNER_DIRECTION)
    points = points.astype(np.float64)
    normals = np.zeros((len(points), 3))
    if triangles is not None and len(triangles):
        corners = points[triangles]  # (f, 3, 3)
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # 2 * area * n
        if (cross @ view).sum() < 0:
            cross = -cross
        for i in range(3):
            np.add.at(normals, triangles[:, i], cross)
    length = np.linalg.norm(normals, axis=1)
    lonely = length == 0
    if lonely.any():
        if len(points) < 3:
            raise InputError(
                f"a range scan without triangles needs at least 3 points for normals, got {len(points)}"
            )
        estimated = _pca_normals(points[lonely], points, k=min(30, len(points)))
        normals[lonely] = np.where((estimated @ view)[:, None] < 0, -estimated, estimated)
        length[lonely] = 1.0
    return normals / length[:, None]


def _pca_normals(query: np.ndarray, points: np.ndarray, k: int) -> np.ndarray:
    """Least-variance direction (m, 3) of the k nearest `points` (n, 3) of each query (m, 3)."""
    from scipy.spatial import cKDTree

    _, index = cKDTree(points).query(query, k=k, workers=-1)
    neighbours = points[index] - query[:, None]  # (m, k, 3), offsets keep precision
    centred = neighbours - neighbours.mean(1, keepdims=True)
    return np.linalg.eigh(centred.transpose(0, 2, 1) @ centred)[1][..., 0]


def triangulate_range_grid(
    grid: np.ndarray, points: np.ndarray, max_edge_factor: float = _MAX_EDGE_FACTOR
) -> np.ndarray:
    """Triangles (f, 3) int64 of a range grid, all with the same winding in grid space.

    Args:
        grid: Int[ndarray, "rows cols"] vertex index per cell, -1 where the scanner saw nothing.
        points: Float[ndarray, "n 3"] the vertices.
        max_edge_factor: triangles with an edge longer than this times the median edge are dropped.
    Each 2x2 block of cells gives two triangles when all four cells hold a vertex and one when
    exactly three do.
    """
    a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()  # (r, c), (r, c + 1)
    c, d = grid[1:, :-1].ravel(), grid[1:, 1:].ravel()  # (r + 1, c), (r + 1, c + 1)
    has = [x >= 0 for x in (a, b, c, d)]
    ha, hb, hc, hd = has
    count = ha.astype(int) + hb + hc + hd
    candidates = [  # (triangle, when): windings all clockwise in (column, row) coordinates
        (np.stack([a, c, b], 1), ha & hb & hc),
        (np.stack([b, c, d], 1), hb & hc & hd),
        (np.stack([a, c, d], 1), ~hb & (count == 3)),
        (np.stack([a, d, b], 1), ~hc & (count == 3)),
    ]
    triangles = np.concatenate([tri[when] for tri, when in candidates]).astype(np.int64)
    if len(triangles) == 0:
        return triangles.reshape(0, 3)
    corners = points.astype(np.float64)[triangles]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)  # longest edge
    return triangles[edges <= max_edge_factor * np.median(edges)]


def _ply_triangles(path: Path, data: bytes, points: np.ndarray) -> np.ndarray | None:
    """Triangles of a PLY's `face` element or triangulated `range_grid` (ASCII or binary, in any
    element order), or None when it has neither."""
    header, offset = ply_header(data)
    names = [element.name for element in header.elements]
    wanted = next((name for name in ("face", "range_grid") if name in names), None)
    if wanted is None:
        return None
    count = header[wanted].count
    if header.text:
        counts, flat, starts = _ascii_lists(ascii_rows(data, offset, header, wanted), wanted, len(points))
    else:
        element = read_ply_binary(path)[wanted]
        lists = [prop.name for prop in element.properties if isinstance(prop, _ListProperty())]
        if not lists:
            raise FileFormatError(f"PLY {wanted!r} element has no list of vertex indices")
        counts, flat, starts = _binary_lists(element.data[lists[0]], wanted, len(points))
    if wanted == "face":
        return _fan_triangles(counts, flat, starts)
    rows, cols = _grid_shape(data[:offset])
    if rows * cols != count:
        raise FileFormatError(
            f"range_grid has {count} cells but obj_info declares {rows} rows x {cols} cols; "
            f"the header is inconsistent"
        )
    first = np.where(counts > 0, flat[np.minimum(starts + 1, len(flat) - 1)], -1)  # first vertex per cell
    return triangulate_range_grid(first.reshape(rows, cols), points)


def _ListProperty():
    import plyfile

    return plyfile.PlyListProperty


def _binary_lists(rows: np.ndarray, what: str, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The list rows plyfile read (an object array of index arrays, or an (m, k) array when all
    rows have k entries) in `_ascii_lists`' layout (counts, flat tokens, row starts)."""
    rows = [np.asarray(row, dtype=np.int64).reshape(-1) for row in rows]
    counts = np.array([len(row) for row in rows], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts + 2)[:-1]]).astype(np.int64)
    flat = np.full(int((counts + 2).sum()), -1, dtype=np.int64)
    flat[starts] = counts
    if len(rows):
        indices = np.concatenate(rows)
        if len(indices) and (indices.min() < 0 or indices.max() >= n_vertices):
            raise FileFormatError(f"PLY {what!r} indexes vertices outside [0, {n_vertices}); the file is corrupt")
        positions = np.repeat(starts + 1, counts) + (np.arange(len(indices)) - np.repeat(np.cumsum(counts) - counts, counts))
        flat[positions] = indices
    return counts, flat, starts


def _ascii_lists(lines: list[str], what: str, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse ASCII list rows `k i_1 ... i_k`, one per line, of vertex indices < `n_vertices`.

    Returns (counts (m,), flat tokens with -1 between rows, row starts (m,)) such that row r's
    indices are `flat[starts[r] + 1 : starts[r] + 1 + counts[r]]`.
    """
    try:
        flat = np.array(" -1 ".join(lines).split(), dtype=np.int64)  # -1 separates rows
    except ValueError as error:
        raise FileFormatError(f"PLY {what!r} rows are not integers ({error}); the file is corrupt")
    separators = np.flatnonzero(flat == -1)
    starts = np.concatenate([[0], separators + 1])
    ends = np.concatenate([separators, [len(flat)]])
    counts = flat[np.minimum(starts, len(flat) - 1)] if len(flat) else np.zeros(0, np.int64)
    if len(starts) != len(lines) or (ends - starts != counts + 1).any():
        raise FileFormatError(f"PLY {what!r} rows do not match their counts (one list per line expected)")
    is_index = np.ones(len(flat), dtype=bool)
    is_index[starts[starts < len(flat)]] = False
    is_index[separators] = False
    if is_index.any() and (flat[is_index].min() < 0 or flat[is_index].max() >= n_vertices):
        raise FileFormatError(f"PLY {what!r} indexes vertices outside [0, {n_vertices}); the file is corrupt")
    return counts, flat, starts


def _fan_triangles(counts: np.ndarray, flat: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Triangles (f, 3) of polygons given as ASCII list rows, fan-triangulated."""
    triangles = []
    for k in np.unique(counts[counts >= 3]):
        rows = starts[counts == k]
        for j in range(1, k - 1):
            triangles.append(flat[rows[:, None] + 1 + np.array([0, j, j + 1])])
    return np.concatenate(triangles) if triangles else np.zeros((0, 3), np.int64)


def _grid_shape(header: bytes) -> tuple[int, int]:
    """(num_rows, num_cols) from a Cyberware PLY header's obj_info lines."""
    text = header.decode("ascii", errors="replace")
    found = {key: re.search(rf"obj_info\s+{key}\s+(\d+)", text) for key in ("num_rows", "num_cols")}
    if not all(found.values()):
        raise FileFormatError("PLY range_grid needs 'obj_info num_rows' and 'obj_info num_cols' header lines")
    return int(found["num_rows"].group(1)), int(found["num_cols"].group(1))


def _existing_file(path: PathLike, kind: str) -> Path:
    path = Path(path)
    if not path.is_file():
        why = "is a folder" if path.is_dir() else "not found"
        raise FileFormatError(f"{kind} file {str(path)!r} {why}; check the path (and the .conf's folder)")
    return path
