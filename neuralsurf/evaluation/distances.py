"""Error-coloured meshes: each reconstruction coloured by its vertices' distance to the ground truth, and
the ground truth by its vertices' distance to the reconstruction (what was missed), on one colour scale
per scene.

A row with a ground truth stores its distances when it is computed (`save_distances`:
`distances/<scene>/<method>.npz`, the two meshes and the two per-vertex distances in the scene's
units). The scale needs every method of the scene, so the colours are made with the report
(`write_error_views`): 0 .. the 95th percentile of all the scene's distances (every method, both
directions), viridis, clipped above. Written then: `renders/<scene>__<method>__error.png` (with
render=true) and `meshes/<scene>__<method>__error.glb`, `meshes/<scene>__<method>__gt_error.glb`
(with save_meshes=true); they are made again only when the scene's scale or the row's distances
change (`distances/<scene>/colours.json` records what they were made with).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralsurf.cameras import render_depth
from neuralsurf.errors import FileFormatError
from neuralsurf.evaluation.filenames import NPZ, row_stem, safe_name, stored_file
from neuralsurf.evaluation.render import default_view, labelled_row, shade, viridis
from neuralsurf.geometry import closest_on_mesh
from neuralsurf.io import write_mesh
from neuralsurf.io.npz import read_npz
from neuralsurf.locks import replaced, write_atomic
from neuralsurf.metrics import common_pixel_errors
from neuralsurf.structures import Mesh

log = logging.getLogger("neuralsurf")

FOLDER = "distances"
"""The folder of the per-row distance files inside a results folder."""
PERCENTILE = 95.0
"""A scene's colour scale ends at this percentile of its distances (every method, both directions)."""


def vertex_distances(mesh: Mesh, gt: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Exact point-to-mesh distances (`neuralsurf.geometry.closest_on_mesh`), in the meshes' units:
    (each vertex of `mesh` to `gt` (v,), each vertex of `gt` to `mesh` (g,)), float64."""
    to_gt, _ = closest_on_mesh(mesh.vertices.detach().double().cpu(), gt)
    to_mesh, _ = closest_on_mesh(gt.vertices.detach().double().cpu(), mesh)
    return to_gt.numpy(), to_mesh.numpy()


def shared_scale(distances: list[np.ndarray], percentile: float = PERCENTILE) -> float:
    """The top of a scene's colour scale: the `percentile` of all `distances` (arrays of any shape)
    pooled; when that is 0 (perfect reconstructions) their maximum, else 1."""
    pooled = np.concatenate([np.ravel(d) for d in distances]) if distances else np.zeros(0)
    if not len(pooled):
        return 1.0
    top = float(np.percentile(pooled, percentile))
    return top if top > 0 else (float(pooled.max()) or 1.0)


def distance_colors(distances: np.ndarray, top: float) -> np.ndarray:
    """Distances (n,) -> viridis RGB (n, 3) in [0, 1]: 0 dark purple, `top` and beyond yellow."""
    return viridis(np.asarray(distances, dtype=np.float64) / top)


def distances_path(scene: str, method: str) -> Path:
    """distances/<scene>/<method>.npz, relative to the results folder."""
    return Path(FOLDER) / safe_name(scene) / f"{safe_name(method)}.npz"


def error_meshes(scene: str, method: str) -> dict[str, str]:
    """The error-coloured GLBs of a row, relative to the results folder: {"prediction":
    meshes/<scene>__<method>__error.glb, "ground truth": meshes/<scene>__<method>__gt_error.glb}."""
    stem = row_stem(scene, method)
    return {"prediction": f"meshes/{stem}__error.glb", "ground truth": f"meshes/{stem}__gt_error.glb"}


def colours_path(scene: str) -> Path:
    """distances/<scene>/colours.json, relative to the results folder: what the scene's error-coloured
    files were made with ({method: {"top": the scale, "stamp": ..., "files": [...]}})."""
    return Path(FOLDER) / safe_name(scene) / "colours.json"


def save_distances(run_dir: Path, scene: str, method: str, mesh: Mesh, gt: Mesh, render_size: int) -> str:
    """Measure `vertex_distances(mesh, gt)` and store them with both meshes and the render size
    (`distances_path`); returns that path relative to `run_dir`."""
    to_gt, to_mesh = vertex_distances(mesh, gt)
    path = distances_path(scene, method)
    arrays = {"vertices": mesh.vertices.detach().cpu().numpy(), "faces": mesh.faces.cpu().numpy().astype(np.int32),
              "gt_vertices": gt.vertices.detach().cpu().numpy(), "gt_faces": gt.faces.cpu().numpy().astype(np.int32),
              "to_gt": to_gt, "to_mesh": to_mesh, "render_size": np.int64(render_size)}
    with replaced(Path(run_dir) / path) as temporary:
        np.savez(temporary, **arrays)
    return str(path)


DISTANCE_ARRAYS = {"vertices": (-1, 3), "faces": (-1, 3), "gt_vertices": (-1, 3), "gt_faces": (-1, 3),
                   "to_gt": (-1,), "to_mesh": (-1,), "render_size": ()}
"""The arrays of a distances file (`save_distances`) and their shapes (-1: any length)."""


def read_distances(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a distances file (`save_distances`), each of the shape DISTANCE_ARRAYS gives and one
    distance per vertex; FileFormatError naming the file otherwise."""
    arrays = read_npz(path, tuple(DISTANCE_ARRAYS))
    for name, shape in DISTANCE_ARRAYS.items():
        found = arrays[name].shape
        if len(found) != len(shape) or any(want not in (-1, got) for want, got in zip(shape, found)):
            raise FileFormatError(f"{path}: {name} has shape {found}, expected {shape} (-1: any length); "
                                  f"delete the file and evaluate the row again")
    if (not len(arrays["vertices"]) or not len(arrays["gt_vertices"]) or len(arrays["to_gt"]) != len(arrays["vertices"])
            or len(arrays["to_mesh"]) != len(arrays["gt_vertices"])):
        raise FileFormatError(f"{path}: the distances do not match the meshes' vertices (or a mesh is empty); "
                              f"delete the file and evaluate the row again")
    return arrays


def _stamp(path: Path) -> list[int]:
    """What identifies a distances file's content for the colour cache: [size, mtime in ns]."""
    stat = path.stat()
    return [stat.st_size, stat.st_mtime_ns]


def write_error_views(rows: list[dict[str, Any]], run_dir: str | Path) -> dict[tuple[str, str], dict[str, Any]]:
    """The error-coloured files of every ok row with stored distances (`save_distances`), on one scale
    per scene (`shared_scale` of every method's distances, both directions).

    Returns {(scene, method): {"top": the scene's scale, "extent": the ground truth's longest side,
    "render": "renders/<stem>__error.png" or None, "meshes": {"prediction": ..., "ground truth": ...}
    (GLB paths, empty without a saved mesh)}}, paths relative to `run_dir`."""
    run_dir = Path(run_dir)
    by_scene: dict[str, dict[str, Path]] = {}
    for row in rows:
        path = (stored_file(run_dir, row["distances"], "distances", signature=NPZ)
                if row.get("status") == "ok" and row.get("distances") else None)
        if path is not None:
            by_scene.setdefault(row["scene"], {})[row["method"]] = path
    rows_by_key = {(row["scene"], row["method"]): row for row in rows}
    views = {}
    for scene, paths in by_scene.items():
        data = {}
        for method, path in paths.items():
            try:
                data[method] = read_distances(path)
            except FileFormatError as error:
                log.warning("no error-coloured view of %s on %s: %s", method, scene, error)
        if not data:
            continue
        top = shared_scale([d[key] for d in data.values() for key in ("to_gt", "to_mesh")])
        manifest_path = run_dir / colours_path(scene)
        try:
            manifest = json.loads(manifest_path.read_text())
        except (OSError, ValueError):
            manifest = {}
        if not isinstance(manifest, dict):
            manifest = {}
        for method, arrays in data.items():
            row, stem = rows_by_key[(scene, method)], row_stem(scene, method)
            gt_vertices = arrays["gt_vertices"]
            view = {"top": top, "extent": float(np.ptp(gt_vertices, axis=0).max()),
                    "render": f"renders/{stem}__error.png" if row.get("render") else None,
                    "meshes": error_meshes(scene, method) if row.get("mesh") else {}}
            files = [name for name in [view["render"], *view["meshes"].values()] if name]
            made = {"top": top, "stamp": _stamp(paths[method]), "files": files}
            if manifest.get(method) != made or not all((run_dir / name).is_file() for name in files):
                try:
                    _write_view(run_dir, arrays, view, method)
                except Exception as error:  # noqa: BLE001 - the report goes on without this view
                    log.warning("no error-coloured view of %s on %s: %s: %s", method, scene, type(error).__name__,
                                error)
                    manifest.pop(method, None)
                    continue
                manifest[method] = made
            views[(scene, method)] = view
        write_atomic(manifest_path, json.dumps(manifest, indent=1))
    return views


def _write_view(run_dir: Path, arrays, view: dict[str, Any], method: str) -> None:
    """The coloured prediction and ground truth of one row: the render and the GLBs `view` names."""
    top = view["top"]
    prediction = Mesh(arrays["vertices"], arrays["faces"], distance_colors(arrays["to_gt"], top))
    gt = Mesh(arrays["gt_vertices"], arrays["gt_faces"], distance_colors(arrays["to_mesh"], top))
    for mesh, name in ((prediction, "prediction"), (gt, "ground truth")):
        if name in view["meshes"]:
            with replaced(run_dir / view["meshes"][name]) as temporary:
                write_mesh(temporary, mesh)
    if view["render"]:
        size = int(arrays["render_size"])
        camera = default_view(np.stack([arrays["gt_vertices"].min(0), arrays["gt_vertices"].max(0)]))
        images = [shade(mesh, camera, size, size, vertex_colors=True, ambient=0.5) for mesh in (prediction, gt)]
        labels = [f"{method}: distance to ground truth", f"ground truth: distance to {method}"]
        with replaced(run_dir / view["render"]) as temporary:
            labelled_row(images, labels).save(temporary)


def held_out_error_image(rendered: np.ndarray, measured: np.ndarray, top: float = 0.2):
    """Per-pixel error maps of held-out depth views as one PIL image, a row per view: measured depth |
    rendered depth (grey, 0 to 5 m) | signed error rendered - measured (green 0, red where the mesh lies
    behind the reading, blue where it stands in front, saturated at `top` metres; black: the mesh shows
    nothing there; grey: no reading). rendered, measured: Float[ndarray, "n h w"] z-depth, 0 = none."""
    from PIL import Image

    def grey(depth):
        return np.repeat((np.clip(depth / 5.0, 0, 1) * 255).astype(np.uint8)[..., None], 3, -1)

    rows = []
    for r, m in zip(rendered, measured):
        e = np.clip(np.where((m > 0) & (r > 0), r - m, 0) / top, -1, 1)
        colour = (np.stack([np.clip(e, 0, 1), 1 - np.abs(e), np.clip(-e, 0, 1)], -1) * 255).astype(np.uint8)
        colour[(m > 0) & ~(r > 0)] = 0
        colour[m <= 0] = 128
        rows.append(np.concatenate([grey(m), grey(r), colour], 1))
    return Image.fromarray(np.concatenate(rows, 0))


def save_held_out_errors(run_dir: Path, scene: str, method: str, mesh: Mesh, frames, width: int = 960) -> str:
    """`held_out_error_image` of `mesh` ray-cast from the held-out `frames` (DepthFrames), scaled to `width`
    pixels, as renders/<scene>__<method>__held_out.png; returns that path relative to `run_dir`."""

    rendered, _ = render_depth(mesh, frames.K.cpu(), frames.cam_to_world.cpu(), frames.width, frames.height)
    image = held_out_error_image(rendered.numpy(), frames.depth.cpu().numpy())
    image = image.resize((width, round(image.height * width / image.width)))
    path = Path("renders") / f"{row_stem(scene, method)}__held_out.png"
    with replaced(Path(run_dir) / path) as temporary:
        image.save(temporary, format="PNG")
    return str(path)



def held_out_errors_path(scene: str, method: str) -> Path:
    """Where a row's held-out depth errors are stored, relative to the results folder (named by the row, never
    read from a row file)."""
    return Path(FOLDER) / f"{row_stem(scene, method)}__held_out{NPZ}"


def save_held_out_error_map(run_dir: Path, scene: str, method: str, errors) -> None:
    """Store Float[Tensor, "n h w"] held-out depth errors (`metrics.held_out_errors`, NaN where not seen) as
    float16 (compressed) at `held_out_errors_path`, for the common-pixel errors of the report."""
    path = Path(run_dir) / held_out_errors_path(scene, method)
    path.parent.mkdir(parents=True, exist_ok=True)
    with replaced(path) as temporary, open(temporary, "wb") as file:
        np.savez_compressed(file, errors=errors.cpu().numpy().astype(np.float16))


def with_common_pixel_errors(rows: list[dict[str, Any]], run_dir: Path) -> list[dict[str, Any]]:
    """`rows` with `depth_error_common` on each ok row that has held-out depth errors: its mean |error| over
    the held-out pixels that every such row of its scene shows (`metrics.common_pixel_errors`). A map that
    cannot be read is left out with a warning."""
    by_scene: dict[str, dict[str, Any]] = {}
    for row in rows:
        if row.get("status") == "ok" and "depth_error_mean" in row:
            path = Path(run_dir) / held_out_errors_path(row["scene"], row["method"])
            if not path.is_file():
                continue
            try:
                errors = torch.from_numpy(read_npz(path, ("errors",))["errors"].astype(np.float32))
            except FileFormatError as error:
                log.warning("leaving %s out of the common-pixel errors: %s", path, error)
                continue
            by_scene.setdefault(row["scene"], {})[row["method"]] = errors
    common = {}
    for scene, errors in by_scene.items():
        shapes = {tuple(e.shape) for e in errors.values()}
        if len(shapes) == 1:
            common.update({(scene, method): value for method, value in common_pixel_errors(errors).items()})
        else:
            log.warning("scene %s: held-out error maps of different shapes %s; no common-pixel errors", scene, shapes)
    return [{**row, "depth_error_common": common[(row["scene"], row["method"])]}
            if (row["scene"], row["method"]) in common else row for row in rows]
