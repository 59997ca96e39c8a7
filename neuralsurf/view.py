"""neuralsurf-view: look at the meshes of an evaluation run, or at mesh files, in the browser.

    neuralsurf-view outputs/evaluate/quick/<date>      # a run of evaluate.py (or its results_dir)
    neuralsurf-view mesh.ply gt.ply                    # mesh files (.ply .obj .off .stl .glb)

A run shows, per scene (a drop-down picks it): each method's mesh, coloured by each vertex's distance to
the ground truth where the run wrote error-coloured meshes (`neuralsurf.evaluation.distances`; viridis, one
scale per scene), the ground truth, what each method missed (the ground truth coloured by its distance to
the method's mesh, off at first), and the input points, depth cameras and held-out cameras when the run
kept its scenes (`scene_cache`). The meshes stand side by side or overlaid; a check box per mesh shows or hides it.

It serves the page with viser (the `view` extra: ``pip install 'neuralsurf[view]'``), whose wheel carries
its web client: nothing is fetched from the internet. Stop it with Ctrl+C.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from neuralsurf.errors import FileFormatError, InputError, MissingDependencyError, NeuralsurfError
from neuralsurf.evaluation.distances import colours_path, error_meshes, read_distances
from neuralsurf.evaluation.filenames import NPZ, safe_name, stored_file
from neuralsurf.evaluation.store import load_scene, read_rows, row_problem
from neuralsurf.io import read_mesh

log = logging.getLogger("neuralsurf")

MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb")
"""Files read as meshes (`neuralsurf.io.read_mesh`)."""
MAX_POINTS = 200_000
"""Input points shown at most per scene (every k-th point beyond)."""
GREY = (200, 200, 200)
INPUT_COLOUR = (230, 90, 40)
CAMERA_COLOUR = (40, 90, 230)
HELD_OUT_COLOUR = (220, 30, 160)
GROUND_TRUTH = "ground truth"
INPUT = "input points"
CAMERAS = "cameras"
HELD_OUT = "held-out cameras"


@dataclass
class Item:
    """One thing shown in a scene: a mesh (grey, and coloured when known), points, or cameras."""

    label: str
    """Its check box's label: a method's name, "ground truth", "missed by <method>", ..."""
    vertices: np.ndarray
    """Float32[ndarray, "v 3"]: mesh vertices or points (for cameras: their centres)."""
    faces: np.ndarray | None = None
    """Int[ndarray, "f 3"] for a mesh, None for points and cameras."""
    coloured: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """(vertices, faces, Uint8[ndarray, "v 3"] colours): the mesh coloured by its error (or its own
    vertex colours), None when there is none."""
    poses: np.ndarray | None = None
    """Float[ndarray, "n 4 4"] camera-to-world (OpenCV) of cameras, with `fov` (vertical, rad) and `aspect`."""
    fov: float = 0.8
    aspect: float = 4 / 3
    colour: tuple[int, int, int] = INPUT_COLOUR
    """Of points and cameras."""
    visible: bool = True
    """Shown when the viewer opens."""


@dataclass
class Group:
    """One scene of a run (or the mesh files given): what to show and the colour scale's top."""

    name: str
    items: list[Item] = field(default_factory=list)
    scale: float | None = None
    """The top of the error colours (scene units), when the run recorded it."""


# ----------------------------------------------------------------------------------------------
# what to show: a run folder or mesh files -> groups


def _mesh_arrays(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices float32 (v, 3), faces int64 (f, 3), colours uint8 (v, 3) or None) of a mesh file."""

    mesh = read_mesh(path)
    colours = None
    if mesh.vertex_colors is not None:
        colours = (np.clip(mesh.vertex_colors.detach().cpu().numpy()[:, :3], 0, 1) * 255).round().astype(np.uint8)
    return mesh.vertices.detach().cpu().numpy().astype(np.float32), mesh.faces.cpu().numpy().astype(np.int64), colours


def _mesh_item(label: str, path: Path, coloured: Path | None = None, visible: bool = True) -> Item:
    """A mesh file as an Item, coloured by the vertex colours of the file `coloured` when given (a run's
    error-coloured mesh), else by its own vertex colours unless they are all one colour (a writer's filler)."""
    vertices, faces, colours = _mesh_arrays(path)
    shaded = None
    if coloured is not None:
        other = _mesh_arrays(coloured) if coloured.is_file() else (None, None, None)
        shaded = other if other[2] is not None else None
    elif colours is not None and (colours != colours[:1]).any():
        shaded = (vertices, faces, colours)
    return Item(label, vertices, faces, shaded, visible=visible)


def is_run(folder: Path) -> bool:
    """Whether `folder` is a results folder of evaluate.py (it holds rows/ or results.json)."""
    return (folder / "rows").is_dir() or (folder / "results.json").is_file()


def run_rows(folder: Path) -> list[dict[str, Any]]:
    """The rows of a results folder: results.json's, else rows/*.json (`neuralsurf.evaluation.store`)."""

    if (folder / "results.json").is_file():  # the suite's order, rewritten after every row
        try:
            results = json.loads((folder / "results.json").read_text())
        except ValueError as error:
            raise InputError(f"{folder / 'results.json'} is not JSON ({error}); rebuild it: python evaluate.py "
                             f"report={folder}") from None
        if not isinstance(results, dict) or not isinstance(results.get("rows", []), list):
            raise InputError(f"{folder / 'results.json'} is not a results file of evaluate.py (an object with a list "
                             f"of rows); rebuild it: python evaluate.py report={folder}")
        return results.get("rows", [])
    return read_rows(folder)


def _scene_input(folder: Path, scene: str) -> list[Item]:
    """The input points and cameras of `scene` from the run's scene cache (`scenes/<scene>-<key>.pt`,
    the newest), or [] when the run kept none or it cannot be read."""
    files = sorted((folder / "scenes").glob(f"{safe_name(scene)}-*.pt"), key=lambda p: p.lstat().st_mtime)
    scene_file = stored_file(folder, str(files[-1].relative_to(folder)), "scene") if files else None
    if scene_file is None:
        return []
    try:
        built = load_scene(scene_file)
    except Exception:  # noqa: BLE001 - the view goes on without the input
        return []
    built = built.scenes[0] if hasattr(built, "scenes") else built  # a set of shapes: its first
    items = []
    points = built.cloud.points.detach().cpu().numpy().astype(np.float32)
    if len(points):
        items.append(Item(INPUT, points[:: max(1, len(points) // MAX_POINTS)], visible=False))
    if built.frames is not None and getattr(built, "depth_input", False) and len(built.frames):
        items.append(_cameras(CAMERAS, built.frames, CAMERA_COLOUR))
    if getattr(built, "held_out", None) is not None and len(built.held_out):
        items.append(_cameras(HELD_OUT, built.held_out, HELD_OUT_COLOUR))
    return items


def _cameras(label: str, frames, colour: tuple[int, int, int]) -> Item:
    """The cameras of DepthFrames as a hidden Item (their centres, poses, vertical field of view, aspect)."""
    K = frames.K.detach().cpu().double().numpy()
    poses = frames.cam_to_world.detach().cpu().double().numpy()
    return Item(label, poses[:, :3, 3].astype(np.float32), poses=poses, colour=colour, visible=False,
                fov=float(2 * np.arctan(frames.height / (2 * K[0, 1, 1]))), aspect=frames.width / frames.height)


def run_groups(folder: Path) -> list[Group]:
    """One Group per scene of the run in `folder` with at least one mesh: each method's mesh (error-coloured
    when the run wrote meshes/<scene>__<method>__error.glb), the ground truth (from the stored distances),
    what each method missed (__gt_error.glb, hidden at first), the input points and cameras (hidden at first)."""

    groups: dict[str, Group] = {}
    for row in run_rows(folder):
        problem = row_problem(row) if isinstance(row, dict) and {"scene", "method", "status"} <= set(row) else \
            "not a row of scene, method and status"
        if problem is not None:
            log.warning("%s: skipping the row %.80s: %s", folder, row, problem)
            continue
        mesh = stored_file(folder, row["mesh"], "mesh") if row["status"] == "ok" and row.get("mesh") else None
        if mesh is None:
            continue
        group = groups.setdefault(row["scene"], Group(row["scene"]))
        coloured = error_meshes(row["scene"], row["method"])
        group.items.append(_mesh_item(row["method"], mesh, _present(folder, coloured["prediction"])))
        missed = _present(folder, coloured["ground truth"])
        if missed is not None:
            vertices, faces, colours = _mesh_arrays(missed)
            group.items.append(Item(f"missed by {row['method']}", vertices, faces,
                                    (vertices, faces, colours) if colours is not None else None, visible=False))
        distances = stored_file(folder, row["distances"], "distances", signature=NPZ) if row.get("distances") else None
        if distances is not None and not any(item.label == GROUND_TRUTH for item in group.items):
            try:
                arrays = read_distances(distances)
                group.items.insert(0, Item(GROUND_TRUTH, arrays["gt_vertices"].astype(np.float32),
                                           arrays["gt_faces"].astype(np.int64)))
            except FileFormatError as error:  # the distances file is damaged: no ground truth shown
                log.warning("%s", error)
    for name, group in groups.items():
        group.items += _scene_input(folder, name)
        group.scale = _scene_scale(folder, name)
    return list(groups.values())


def _present(folder: Path, name: str) -> Path | None:
    """`folder / name` when it exists and is a regular file inside `folder` (`stored_file`), else None."""
    return stored_file(folder, name, "mesh") if (folder / name).exists() else None


def _scene_scale(folder: Path, scene: str) -> float | None:
    """The top of a scene's error colours, as recorded with its error-coloured meshes (colours.json)."""

    try:
        made = json.loads((folder / colours_path(scene)).read_text())
        return float(next(iter(made.values()))["top"])
    except (OSError, ValueError, StopIteration, KeyError, TypeError):
        return None


def collect(paths: Sequence[str | Path]) -> list[Group]:
    """What `neuralsurf-view PATH ...` shows: a run folder's scenes (`run_groups`), a folder's mesh files,
    mesh files; all loose files in one group named "files".

    Raises InputError for a missing path, a file that is not a mesh, or when nothing holds a mesh."""
    if not paths:
        raise InputError("give a run folder of evaluate.py or mesh files: neuralsurf-view <run dir | mesh files>")
    groups: list[Group] = []
    loose = Group("files")
    for given in map(Path, paths):
        if not given.exists():
            raise InputError(f"{given} not found; give a run folder of evaluate.py (outputs/evaluate/<suite>/<date>) "
                             f"or mesh files ({', '.join(MESH_SUFFIXES)})")
        if given.is_dir() and is_run(given):
            found = run_groups(given)
            if not found:
                raise InputError(f"{given} is a run of evaluate.py with no saved meshes (rows ok with a mesh); "
                                 f"run it with save_meshes=true")
            groups += found if len(paths) == 1 else [Group(f"{given.name}/{g.name}", g.items, g.scale) for g in found]
        elif given.is_dir():
            files = sorted(p for p in given.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
            if not files and (given / "meshes").is_dir():
                files = sorted(p for p in (given / "meshes").iterdir() if p.suffix.lower() in MESH_SUFFIXES)
            if not files:
                raise InputError(f"{given} holds no meshes ({', '.join(MESH_SUFFIXES)}) and is not a run of evaluate.py "
                                 f"(no rows/ or results.json)")
            loose.items += [_mesh_item(_label(p, loose), p) for p in files]
        elif given.suffix.lower() in MESH_SUFFIXES:
            loose.items.append(_mesh_item(_label(given, loose), given))
        else:
            raise InputError(f"{given} is not a mesh file ({', '.join(MESH_SUFFIXES)}) nor a folder")
    return groups + ([loose] if loose.items else [])


def _label(path: Path, group: Group) -> str:
    """A file's label: its name, with its folder when the name is taken already."""
    taken = {item.label for item in group.items}
    return path.name if path.name not in taken else f"{path.parent.name}/{path.name}"


# ----------------------------------------------------------------------------------------------
# the page


def _import_viser():
    try:
        import viser
    except ImportError:
        raise MissingDependencyError("neuralsurf-view needs viser, the view extra: pip install -e '.[view]' "
                                     "in a clone of neuralsurf (pip install 'neuralsurf[view]' from a "
                                     "package index)") from None
    return viser


def _extent(items: list[Item]) -> tuple[np.ndarray, float]:
    """(centre (3,), longest side) of the box around the items' vertices."""
    points = np.concatenate([item.vertices for item in items if len(item.vertices)] or [np.zeros((1, 3))])
    lo, hi = points.min(0), points.max(0)
    return (lo + hi) / 2, float((hi - lo).max()) or 1.0


UP_DIRECTIONS = ("+x", "+y", "+z", "-x", "-y", "-z")


def screen_axes(up: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, towards the viewer) unit vectors (3,) of the opening view for a scene whose up is `up`
    ("+y": x right, y up, z towards the viewer; "+z": y right, z up, x towards the viewer; ...): meshes
    stand side by side along "right"."""
    axis, sign = "xyz".index(up[1]), (1.0 if up[0] == "+" else -1.0)
    eye = np.eye(3)
    return sign * eye[(axis + 2) % 3], sign * eye[axis], eye[(axis + 1) % 3]


def _node(group: int, index: int, variant: str) -> str:
    """Scene-tree name of an item's node: /scene_<g>/item_<i>/<variant>."""
    return f"/scene_{group}/item_{index}/{variant}"


def coloured_glb(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> bytes:
    """A GLB of a mesh with vertex colours (uint8 (v, 3)), smooth normals and a matte, double-sided,
    non-metallic material: glTF's default material is metallic, which shows black without an environment map."""
    import trimesh

    material = trimesh.visual.material.PBRMaterial(metallicFactor=0.0, roughnessFactor=0.9, doubleSided=True)
    visual = trimesh.visual.TextureVisuals(material=material)
    visual.vertex_attributes["color"] = np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], 1)
    mesh = trimesh.Trimesh(vertices, faces, visual=visual, process=False)
    return mesh.export(file_type="glb", include_normals=True)


class Viewer:
    """The viser server (`server`) showing `groups`: drop-downs `scene`, `layout` ("side by side" or
    "overlaid") and `colours` ("coloured" or "grey"), a folder per scene (`folders`) with a check box per item
    (`boxes[scene][item]`); `refresh()` applies them (the page's controls call it). `nodes` maps each
    scene-tree name added to its item's label."""

    def __init__(self, groups: list[Group], host: str = "127.0.0.1", port: int = 8080, up: str = "+y"):
        viser = _import_viser()
        if not groups:
            raise InputError("nothing to show: no meshes")
        if up not in UP_DIRECTIONS:
            raise InputError(f"up={up!r} is not an axis; choose one of {', '.join(UP_DIRECTIONS)}")
        self._up, self._focused = up, None
        self.groups = groups
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction(up)
        # plain lights: image-based lighting takes seconds per frame in software WebGL (no GPU)
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.configure_default_lights(cast_shadow=False)
        self.server.scene.add_light_hemisphere("/lights/hemisphere", sky_color=(255, 255, 255),
                                               ground_color=(150, 150, 150), intensity=1.5)
        self.nodes: dict[str, str] = {}
        self._handles: list[list[dict[str, list[tuple[Any, np.ndarray]]]]] = []
        for g, group in enumerate(groups):
            self._handles.append([self._add(g, i, item) for i, item in enumerate(group.items)])
        gui = self.server.gui
        self.scene = gui.add_dropdown("scene", [g.name for g in groups], initial_value=groups[0].name)
        self.layout = gui.add_dropdown("layout", ["side by side", "overlaid"], initial_value="side by side")
        coloured = any(item.coloured is not None for group in groups for item in group.items)
        self.colours = gui.add_dropdown("colours", ["coloured", "grey"] if coloured else ["grey"])
        self.legend = gui.add_markdown("")
        self.boxes: list[list[Any]] = []
        self.folders: list[Any] = []
        for g, group in enumerate(groups):
            folder = gui.add_folder(group.name)
            with folder:
                boxes = [gui.add_checkbox(item.label, item.visible) for item in group.items]
            for box in boxes:
                box.on_update(lambda _: self.refresh())
            self.boxes.append(boxes)
            self.folders.append(folder)
        for control in (self.scene, self.layout, self.colours):
            control.on_update(lambda _: self.refresh())
        self.refresh()

    def _add(self, g: int, i: int, item: Item) -> dict[str, list[tuple[Any, np.ndarray]]]:
        """The viser nodes of one item (all hidden; `refresh` shows the chosen ones): {"grey" | "coloured":
        [(handle, the position it was added at)]}."""
        scene, label = self.server.scene, item.label
        handles = {}
        if item.poses is not None:
            from scipy.spatial.transform import Rotation

            size = 0.05 * _extent(self.groups[g].items)[1]
            for c, pose in enumerate(item.poses):
                x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
                name = _node(g, i, f"camera_{c}")
                handles.setdefault("grey", []).append((scene.add_camera_frustum(
                    name, fov=item.fov, aspect=item.aspect, scale=size, color=item.colour, wxyz=(w, x, y, z),
                    position=tuple(pose[:3, 3]), visible=False, thickness=0.1 * size), pose[:3, 3].copy()))
                self.nodes[name] = label
            return handles
        if item.faces is None:
            size = 0.004 * _extent(self.groups[g].items)[1]
            name = _node(g, i, "points")
            handles["grey"] = [(scene.add_point_cloud(name, item.vertices, item.colour, point_size=size,
                                                      visible=False), np.zeros(3))]
            self.nodes[name] = label
            return handles
        name = _node(g, i, "grey")
        handles["grey"] = [(scene.add_mesh_simple(name, item.vertices, item.faces, color=GREY, side="double",
                                                  visible=False), np.zeros(3))]
        self.nodes[name] = label
        if item.coloured is not None:
            name = _node(g, i, "coloured")
            handles["coloured"] = [(scene.add_glb(name, coloured_glb(*item.coloured), visible=False), np.zeros(3))]
            self.nodes[name] = label
        return handles

    def refresh(self) -> None:
        """Show the chosen scene's checked items, side by side (one slot each along x) or overlaid, grey or
        coloured; hide everything else; point the initial camera at what is shown."""
        chosen = [g.name for g in self.groups].index(self.scene.value)
        side_by_side = self.layout.value == "side by side"
        coloured = self.colours.value != "grey"
        group = self.groups[chosen]
        centre, size = _extent(group.items)
        side, up, depth = screen_axes(self._up)
        slot = 0
        for g, handles in enumerate(self._handles):
            self.folders[g].visible = g == chosen
            for i, (item, nodes) in enumerate(zip(self.groups[g].items, handles)):
                shown = g == chosen and self.boxes[g][i].value
                offset = side * 1.25 * size * slot if side_by_side and item.faces is not None else np.zeros(3)
                variant = "coloured" if coloured and "coloured" in nodes else "grey"
                for key, handles_and_bases in nodes.items():
                    for handle, base in handles_and_bases:
                        handle.position = tuple(base + offset)
                        handle.visible = shown and key == variant
                if shown and side_by_side and item.faces is not None:
                    slot += 1
        count = max(slot, 1) if side_by_side else 1
        middle = centre + side * 1.25 * size * (count - 1) / 2
        eye = middle + (0.3 * up + depth) * size * (0.8 + 0.8 * count)
        self.server.initial_camera.look_at, self.server.initial_camera.position = tuple(middle), tuple(eye)
        if chosen != self._focused:  # another scene: every open page looks at it
            self._focused = chosen
            for client in self.server.get_clients().values():
                client.camera.position, client.camera.look_at = tuple(eye), tuple(middle)
        scale, any_colours = group.scale, any(item.coloured is not None for item in group.items)
        self.legend.content = ("" if not coloured else
                               f"Colours: distance to the ground truth, viridis from 0 (purple) to {scale:.3g} "
                               f"(yellow) scene units." if scale else
                               "Colours: the meshes' own." if any_colours else "No ground truth here: grey.")

    @property
    def port(self) -> int:
        return self.server.get_port()

    def stop(self) -> None:
        self.server.stop()


def port_number(text: str) -> int:
    """A TCP port given on the command line: an integer in 0..65535 (argparse's error otherwise)."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number; give an integer in 0..65535")
    return port


def main(argv: Sequence[str] | None = None) -> int:
    """``neuralsurf-view PATH [PATH ...] [--host H] [--port P] [--up +y]``: serve until Ctrl+C."""

    parser = argparse.ArgumentParser(prog="neuralsurf-view", description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", help="a run folder of evaluate.py, folders of meshes or mesh files")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface)")
    parser.add_argument("--port", type=port_number, default=8080, help="port to serve on, 0..65535 (default 8080)")
    parser.add_argument("--up", default="+y", choices=UP_DIRECTIONS, help="the scenes' up axis (default +y)")
    args = parser.parse_args(argv)
    try:
        _import_viser()
        viewer = Viewer(collect(args.paths), host=args.host, port=args.port, up=args.up)
    except (NeuralsurfError, OSError) as error:
        print(f"neuralsurf-view: {error}", file=sys.stderr)
        return 2
    shown = ", ".join(f"{g.name} ({len(g.items)})" for g in viewer.groups)
    print(f"neuralsurf-view: http://{args.host}:{viewer.port} shows {shown}; Ctrl+C stops it", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
