"""`neuralsurf-export RUN_DIR`: mesh a finished run's field again, at another resolution, in another
file format or over a region, without fitting again.

RUN_DIR is the folder of a train.py run, or `<results>/fits/<scene>__<method>` of a neural row of an
evaluate.py run: either holds `checkpoints/last.pt`, read by `neuralsurf.load_field` (weights only).
The extraction settings are the run's own (its config's `extract` section) except those given here. A
scene meshed only near its input (a room: `near_distance`, `extract.observed_voxel`) is built again
from the run's config to know where its input is.
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import sys
import warnings
from pathlib import Path
from typing import Any

import torch

from neuralsurf.checkpoints import CHECKPOINT_NAME, PRIOR_CLASSES, load_checkpoint, load_field, stored_class
from neuralsurf.errors import ConfigError, NeuralsurfError
from neuralsurf.extract import extract_mesh
from neuralsurf.io import write_mesh
from neuralsurf.io.meshes import mesh_format
from neuralsurf.scenes import extract_scene_mesh
from neuralsurf.structures import Mesh

log = logging.getLogger("neuralsurf")

FORMATS = ("ply", "obj", "glb", "off", "stl")


def run_checkpoint(run_dir: Path) -> Path:
    """`run_dir`/checkpoints/last.pt, else a ConfigError saying which folders hold one."""
    path = run_dir / "checkpoints" / CHECKPOINT_NAME
    if path.is_file():
        return path
    fits = sorted(p.parents[1] for p in (run_dir / "fits").glob(f"*/checkpoints/{CHECKPOINT_NAME}"))
    if fits:
        raise ConfigError(f"{run_dir} is an evaluate.py results folder; export one of its fitted rows: "
                          f"{', '.join(map(str, fits[:8]))}{' ...' if len(fits) > 8 else ''}")
    hydra_config = run_dir / ".hydra" / "config.yaml"
    if hydra_config.is_file() and "neuralsurf.rooms.RoomSettings" in hydra_config.read_text():
        raise ConfigError(f"{run_dir} is a room's voxel fit (model=room_voxels), a solve that keeps only its mesh: "
                          f"run train.py again with other model.voxel or model.pixel_stride settings, or with "
                          f"model=sdf_hashgrid for a field that neuralsurf-export can mesh again")
    if (run_dir / "rows").is_dir():
        raise ConfigError(f"{run_dir} is an evaluate.py results folder with no fitted field in fits/: only the "
                          f"neural_sdf, neural_sdf_points, neural_depth and neural_depth_normals rows keep one "
                          f"(neural_voxels, TSDF and Poisson keep only their mesh, in meshes/)")
    raise ConfigError(f"{path} not found: give the folder of a train.py run (it holds checkpoints/{CHECKPOINT_NAME}) "
                      f"or <results>/fits/<scene>__<method> of an evaluate.py run")


def scene_config(run_dir: Path, config: dict[str, Any]) -> dict[str, Any] | None:
    """The config of the scene a run fitted: a train.py run's `data`, or an evaluate.py fit's scene from
    its row file (<results>/rows/<scene>__<method>.json); None when neither is there."""
    if isinstance(config.get("data"), dict):
        return config["data"]
    row = run_dir.parents[1] / "rows" / f"{run_dir.name}.json"
    if run_dir.parent.name == "fits" and row.is_file():
        scene = (json.loads(row.read_text()).get("settings") or {}).get("scene")
        return scene if isinstance(scene, dict) else None
    return None


def shipped_scene_recipes() -> set[str]:
    """The `_target_` of every scene and data config neuralsurf ships: the only functions a stored config may
    name to build a scene again."""
    import yaml

    folder = Path(__file__).parent / "configs"
    targets = set()
    for path in [*(folder / "data").glob("*.yaml"), *(folder / "scene").glob("*.yaml")]:
        config = yaml.safe_load(path.read_text()) or {}
        config = config.get("data", config) if isinstance(config, dict) else {}
        if isinstance(config, dict) and isinstance(config.get("_target_"), str):
            targets.add(config["_target_"])
    return targets


def scene_recipe(scene: dict[str, Any]):
    """The scene recipe a stored scene config names, imported only when it is one neuralsurf ships
    (`shipped_scene_recipes`): nothing read from a run folder chooses other code. ConfigError otherwise."""
    import importlib

    target = scene.get("_target_")
    if target not in shipped_scene_recipes():
        raise ConfigError(f"the run's scene config names {str(target)!r:.120}, which is not one of neuralsurf's scene "
                          f"recipes; a stored config may only rebuild those: export with --box instead of near the "
                          f"input, or run train.py again")
    module, name = target.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


def build_stored_scene(scene: dict[str, Any]):
    """The scene of a stored config: its shipped recipe (`scene_recipe`) called with plain arguments only (no
    nested configs, no Hydra keys), so the stored file supplies data, never code."""
    recipe = scene_recipe(scene)
    arguments = {key: value for key, value in scene.items() if key != "_target_"}
    nested = lambda value: isinstance(value, dict) or (isinstance(value, list) and any(map(nested, value)))
    bad = [key for key, value in arguments.items() if key.startswith("_") or nested(value)]
    if bad:
        raise ConfigError(f"the run's scene config has {bad[0]!r}, not a plain argument of {scene['_target_']}; "
                          f"a stored config may hold only plain values")
    return recipe(**arguments)


def meshed_near_input(scene: dict[str, Any] | None, extract: dict[str, Any]) -> bool:
    """Whether the extraction depends on the scene's input: `near_distance`, `observed_voxel` or `onto_points` set
    in `extract`, or a `near_distance` of the scene's config (given, or its target's default)."""
    if extract.get("onto_points") or any(extract.get(key) is not None for key in ("near_distance", "observed_voxel")):
        return True
    if not scene or "_target_" not in scene:
        return False
    if "near_distance" in scene:
        return scene["near_distance"] is not None
    try:
        parameter = inspect.signature(scene_recipe(scene)).parameters.get("near_distance")
    except Exception:  # noqa: BLE001 - a target that is not a shipped recipe or no longer imports: nothing to rebuild
        return False
    return parameter is not None and parameter.default not in (None, inspect.Parameter.empty)


def export_run(run_dir: str | Path, output: str | Path | None = None, *, resolution: int | None = None,
               file_format: str | None = None, box: list[float] | None = None, level: float | None = None,
               device: str = "cpu", progress: bool = True) -> Path:
    """Mesh the field of a finished run again and write it; returns the file written.

    run_dir: a train.py run folder, or an evaluate.py row's `<results>/fits/<scene>__<method>`.
    output: the mesh file; default `<run_dir>/mesh_<resolution>[_box].<format>`.
    resolution: cells along the longest side of the box (default: the run's `extract.resolution`).
    file_format: ply, obj, glb, off or stl (default: `output`'s suffix, else the run's `extract.format`).
    box: [xmin, ymin, zmin, xmax, ymax, zmax] in the run's world frame: mesh only there, the resolution
        spread over this box. A room meshed on its observed voxels is meshed within its scene's
        `near_distance` of the input inside the box instead.
    level: the level set meshed (default: the run's `extract.level`, else 0).
    Raises ConfigError (no checkpoint, a prior, bad options) or CheckpointError (a damaged checkpoint).
    """
    run_dir = Path(run_dir)
    checkpoint = run_checkpoint(run_dir)
    state = load_checkpoint(checkpoint)
    if stored_class(state) in PRIOR_CLASSES:
        raise ConfigError(f"{checkpoint} holds a learned prior ({stored_class(state)}), not one field: its meshes "
                          f"are completions of shapes (neuralsurf.priors.load_prior, complete_cloud)")
    config = state.get("config") if isinstance(state.get("config"), dict) else {}
    extract = dict(config.get("extract") or {})
    if resolution is not None:
        if resolution < 2:
            raise ConfigError(f"--resolution {resolution}: give at least 2 cells along the longest side")
        extract["resolution"] = resolution
    if level is not None:
        extract["level"] = level
    if file_format is None:
        file_format = Path(output).suffix.lstrip(".") if output is not None and Path(output).suffix else None
    extension = mesh_format(file_format or extract.get("format") or "ply")
    name = f"mesh_{extract.get('resolution', 256)}{'_box' if box is not None else ''}{extension}"
    target = Path(output) if output is not None else run_dir / name
    if target.suffix.lower() != extension:
        raise ConfigError(f"{target}: the file name ends in {target.suffix or 'nothing'} but the format is "
                          f"{extension[1:]}; name the file *{extension} or pass --format {target.suffix[1:] or 'ply'}")
    extract.pop("format", None)
    extract["progress"] = progress
    bounds = None
    if box is not None:
        bounds = torch.tensor(box, dtype=torch.float64).reshape(2, 3)
        if not bool(torch.isfinite(bounds).all() and (bounds[1] > bounds[0]).all()):
            raise ConfigError(f"--box {' '.join(map(str, box))}: give xmin ymin zmin xmax ymax zmax with each max "
                              f"above its min")
    field = load_field(checkpoint, device=device)
    with warnings.catch_warnings():
        if bounds is not None:  # a region is cut open at its faces, as asked
            warnings.filterwarnings("ignore", message="the surface touches the boundary")
        mesh = _extract(field, run_dir, config, extract, bounds)
    target.parent.mkdir(parents=True, exist_ok=True)
    write_mesh(target, mesh)
    return target


def _extract(field, run_dir: Path, config: dict[str, Any], extract: dict[str, Any], bounds) -> Mesh:
    """`export_run`'s mesh: over `bounds` (or the field's box), near the scene's input where the run was."""
    scene = scene_config(run_dir, config)
    if meshed_near_input(scene, extract):
        if scene is None:
            raise ConfigError(f"{run_dir} was meshed near its input only, and its scene's config is not there "
                              f"(a train.py run's checkpoint config, or <results>/rows/ of an evaluate.py run)")
        log.info("building scene %s again to mesh near its input", scene.get("name") or scene["_target_"])
        built = build_stored_scene(scene)
        if bounds is not None and extract.pop("observed_voxel", None) is not None:
            log.info("--box: meshing within the scene's near_distance of the input, not on observed voxels")
        return extract_scene_mesh(field, built, {**extract, **({"bounds": bounds} if bounds is not None else {})},
                                  config.get("seed", 0))
    options = {k: v for k, v in extract.items() if k not in ("near_distance", "observed_voxel", "onto_points")}
    return extract_mesh(field, bounds=bounds, **options)


def main(argv: list[str] | None = None) -> int:
    """`neuralsurf-export RUN_DIR [-o FILE] [--resolution N] [--format F] [--box ...] [--level L] [--device D]`:
    exit status 0, or 1 with the reason."""
    parser = argparse.ArgumentParser(
        prog="neuralsurf-export",
        description="Mesh a finished run's field again (its checkpoints/last.pt) at another resolution, in "
                    "another format or over a region, without fitting again. RUN_DIR: a train.py run folder or "
                    "<results>/fits/<scene>__<method> of an evaluate.py run.")
    parser.add_argument("run_dir", help="the run folder")
    parser.add_argument("-o", "--output", help="the mesh file (default <run_dir>/mesh_<resolution>.<format>)")
    parser.add_argument("--resolution", type=int, help="cells along the longest side (default: the run's)")
    parser.add_argument("--format", dest="file_format", choices=FORMATS,
                        help="file format (default: the output's suffix, else the run's extract.format)")
    parser.add_argument("--box", type=float, nargs=6, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                        help="mesh only this box of the world frame")
    parser.add_argument("--level", type=float, help="the level set to mesh (default: the run's, 0)")
    parser.add_argument("--device", default="cpu", help="where to evaluate the field: cpu (default), cuda, auto")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        path = export_run(args.run_dir, args.output, resolution=args.resolution, file_format=args.file_format,
                          box=args.box, level=args.level, device=args.device, progress=not args.quiet)
    except NeuralsurfError as error:
        print(f"neuralsurf-export: {error}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
