"""The method x scene loop: build each scene once, run every method on it, measure, render; each row
stored as soon as it is done (`neuralsurf.evaluation.store`), and reused by a rerun with the same settings.

Plain Python: scenes and methods come in as factories (cli.evaluate builds them from the configs),
so research code can call `run_benchmark` without Hydra.
"""

from __future__ import annotations

import json
import math
import platform
import re
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

import neuralsurf
from neuralsurf.errors import ConfigError
from neuralsurf.evaluation.distances import save_distances, save_held_out_error_map, save_held_out_errors
from neuralsurf.evaluation.methods import NotApplicable
from neuralsurf.evaluation.per_class import shape_class
from neuralsurf.evaluation.photometric import NormalMapResult, normal_map_picture, score_normal_maps
from neuralsurf.evaluation.render import default_view, distance_image, labelled_row, points_image, shade
from neuralsurf.evaluation.rooms import ScoredMesh
from neuralsurf.evaluation.store import reusable_row, row_stem, settings_key, store_row
from neuralsurf.io import write_mesh
from neuralsurf.io.meshes import mesh_format as mesh_format_extension
from neuralsurf.locks import replaced
from neuralsurf.metrics import depth_metrics, evaluate_mesh, held_out_errors, watertight
from neuralsurf.priors import mean_metrics
from neuralsurf.scenes import Scene, SceneUnavailable
from neuralsurf.scenes.recipes import SceneSet
from neuralsurf.structures import Mesh
from neuralsurf.training import seed_everything

SceneFactory = Callable[[], Scene]
MethodFactory = Callable[[], Callable[..., Mesh]]


def environment(include_host: bool = False) -> dict[str, str]:
    """Versions and machine, recorded with every row.

    The machine is described by its platform, processor, CPU threads and GPU, never by its name:
    results are shared, and a hostname says who ran them where. `include_host=True` adds a "host"
    entry (the network name) for one's own records."""
    import open3d

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    env = {"neuralsurf": neuralsurf.__version__, "torch": torch.__version__, "open3d": open3d.__version__,
           "numpy": np.__version__, "python": platform.python_version(),
           "machine": f"{platform.platform()} {platform.processor() or platform.machine()}",
           "cpu_threads": str(torch.get_num_threads()), "gpu": gpu}
    if include_host:
        env["host"] = platform.node()
    return env


def reset_peak_memory() -> None:
    """Reset the process's RSS high-water mark (VmHWM) and CUDA's peak counter."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass  # not Linux, or not allowed: VmHWM then is the process's lifetime peak
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()


def peak_memory_mb() -> tuple[float, float]:
    """(CPU RSS high-water mark, CUDA max allocated) in MiB since `reset_peak_memory`; NaN if unknown."""
    rss = math.nan
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                rss = int(line.split()[1]) / 1024
    except OSError:
        pass
    cuda = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else math.nan
    return rss, cuda


def check_mesh(mesh: Any) -> Mesh:
    """A usable reconstruction, or a ValueError saying why not (the row becomes "failed")."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"the method returned {type(mesh).__name__}, not a neuralsurf Mesh")
    if mesh.is_empty or len(mesh.vertices) == 0:
        raise ValueError("the method returned an empty mesh")
    if not torch.isfinite(mesh.vertices).all():
        raise ValueError("the method returned a mesh with NaN or infinite vertices")
    return mesh


def run_benchmark(
    scenes: dict[str, SceneFactory],
    methods: dict[str, MethodFactory],
    run_dir: str | Path,
    *,
    seed: int = 0,
    n_samples: int = 100_000,
    render: bool = True,
    render_size: int = 320,
    save_meshes: bool = True,
    mesh_format: str = "ply",
    configs: dict[str, Any] | None = None,
    log: Callable[[str], None] = print,
    pairs: list[tuple[str, str]] | None = None,
    settings: dict[tuple[str, str], dict[str, Any]] | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Run every method on every scene; one row (a dict) per (method, scene), in scene-major order.

    Each row has method, scene, status ("ok" | "skipped" | "failed"), reason, seconds (the method's
    wall time, scene building excluded), peak_rss_mb, cuda_peak_mb, n_vertices, n_faces, watertight,
    every `evaluate_mesh` metric (gt's normalised frame), file paths of the mesh and render (relative
    to `run_dir`), the method's config (JSON) and the environment (versions, machine).

    Every row is stored the moment it is done, as `run_dir/rows/<scene>__<method>.json` (after its mesh
    and render; see `neuralsurf.evaluation.store`), so a killed run keeps its finished rows.
    Meshes are saved (`save_meshes`) as meshes/<scene>__<method>.<mesh_format> (ply, glb, obj, off, stl).
    `pairs` (list of (scene, method)) restricts the run to those rows. With `settings` ((scene, method)
    -> a JSON-able dict of everything that decides the row), a row already stored with the same
    settings is reused, not computed (logged as "reused"); without, every row is computed. `on_row` is
    called with each computed row once it is stored (evaluate.py rebuilds the report there).
    """
    unsafe = [name for name in [*scenes, *methods] if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", name)]
    if unsafe:
        raise ConfigError(f"scene and method names become file names in the run directory: {unsafe} may hold only "
                          f"letters, digits, '_', '-' and '.', and may not start with '.' (no '/' or '..')")
    wanted = set(pairs) if pairs is not None else {(s, m) for s in scenes for m in methods}
    unknown = sorted(wanted - {(s, m) for s in scenes for m in methods})
    if unknown:
        raise ConfigError(f"rows {unknown} name scenes or methods not given to run_benchmark; choose from "
                          f"scenes {sorted(scenes)} and methods {sorted(methods)}")
    extension = mesh_format_extension(mesh_format)
    run_dir = Path(run_dir)
    configs = configs or {}
    env = environment()
    rows: list[dict[str, Any]] = []
    for scene_name, make_scene in scenes.items():
        built: dict[str, Any] = {}  # the scene, built at its first row that is not reused
        for method_name, make_method in methods.items():
            if (scene_name, method_name) not in wanted:
                continue
            row_settings = settings.get((scene_name, method_name)) if settings is not None else None
            key = settings_key(row_settings) if row_settings is not None else None
            stored = reusable_row(run_dir, scene_name, method_name, key) if key is not None else None
            if stored is not None:
                log(f"  {method_name:>12} on {scene_name}: reused (stored with the same settings, {key})")
                rows.append(stored)
                continue
            if not built:
                built.update(build_scene(scene_name, make_scene, run_dir, log))
            base = {"scene": scene_name, "seed": seed, **env}
            if built["scene"] is not None:
                base["scene_description"] = built["scene"].description
            row = {"method": method_name, **base, "status": "ok", "reason": "",
                   "config": json.dumps(configs.get(method_name, {}), sort_keys=True, default=str)}
            final = run_row(row, built, make_method, run_dir, seed=seed, n_samples=n_samples, render=render,
                            render_size=render_size, save_meshes=save_meshes, log=log, mesh_extension=extension)
            store_row(run_dir, row, key, row_settings, final)
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows


def build_scene(name: str, make_scene: SceneFactory, run_dir: Path,
                log: Callable[[str], None]) -> dict[str, Any]:
    """{"scene": the built scene or None, "error": None or (status, reason), "gt_image": None}: a scene
    that cannot be built (data missing: "skipped"; any other error: "failed") makes its rows that."""
    try:
        scene, error = make_scene(), None
    except SceneUnavailable as unavailable:
        scene, error = None, ("skipped", f"scene unavailable: {unavailable}")
    except Exception as failure:  # noqa: BLE001 - a broken scene must not stop the run
        scene, error = None, ("failed", f"scene failed: {type(failure).__name__}: {failure}")
        _write_traceback(run_dir, f"scene_{name}")
    if scene is not None:
        log(f"scene {name}: {scene.description}")
    return {"scene": scene, "error": error, "gt_image": None}


@dataclass(frozen=True)
class RowJob:
    """What the scorers of a row need besides the method's output and the scene: where files go, how
    metrics are measured and what is rendered."""

    run_dir: Path
    scene_name: str
    method_name: str
    seed: int
    n_samples: int
    render: bool
    render_size: int
    save_meshes: bool
    mesh_extension: str
    built: dict[str, Any]
    """`build_scene`'s dict: the scene's ground-truth render is kept there for its other rows."""
    log: Callable[[str], None]


@dataclass(frozen=True)
class SceneSetMeshes:
    """What a method gives on a scene set (`run_scene_set`): the first scene's mesh, the means of the scenes'
    metrics and the per-scene values."""

    mesh: Mesh
    metrics: dict[str, float]
    per_shape: list[dict[str, Any]]
    by_class: dict[str, tuple[Scene, Mesh]] = field(default_factory=dict)
    """the first scene of each class (`per_class.shape_class`) with its mesh."""


def run_row(row: dict[str, Any], built: dict[str, Any], make_method: MethodFactory, run_dir: Path, *, seed: int,
            n_samples: int, render: bool, render_size: int, save_meshes: bool,
            log: Callable[[str], None], mesh_extension: str = ".ply") -> bool:
    """Run one method on one built scene (`build_scene`'s dict; its ground-truth render is kept there)
    and fill `row` in place: run, then score by the output's type (`SCORERS`: metrics, files), or the
    reason it was skipped or failed. Returns whether the row is final (reusable by a later run with the
    same settings): ok, or skipped because the method does not apply; failed rows and rows of
    unavailable scenes are computed again."""
    scene_name, method_name, scene = row["scene"], row["method"], built["scene"]
    if built["error"] is not None:
        row["status"], row["reason"] = built["error"]
        log(f"  {method_name:>12} on {scene_name}: {row['status']} ({row['reason']})")
        return False
    job = RowJob(run_dir, scene_name, method_name, seed, n_samples, render, render_size, save_meshes,
                 mesh_extension, built, log)
    seed_everything(seed)
    reset_peak_memory()
    started = time.perf_counter()
    try:
        method = make_method()
        fits = run_dir / "fits" / row_stem(scene_name, method_name)
        if isinstance(scene, SceneSet):  # a split of shapes: one row, the means of their metrics
            output = run_scene_set(scene, method, seed, fits, n_samples)
        else:
            output = method(scene, seed=seed, run_dir=fits)
        scorer(output)(output, scene, row, job, started)
    except NotApplicable as error:
        row["status"], row["reason"] = "skipped", str(error)
        log(f"  {method_name:>12} on {scene_name}: skipped ({error})")
        return True
    except Exception as error:  # noqa: BLE001 - a failing method is a row, the run goes on
        row.setdefault("seconds", time.perf_counter() - started)
        row["status"], row["reason"] = "failed", f"{type(error).__name__}: {error}"
        _write_traceback(run_dir, row_stem(scene_name, method_name))
        log(f"  {method_name:>12} on {scene_name}: FAILED ({row['reason']})")
        return False
    return True


def _measured(row: dict[str, Any], started: float) -> None:
    """The method's wall time and peak memory, into `row`."""
    row["seconds"] = time.perf_counter() - started
    row["peak_rss_mb"], row["cuda_peak_mb"] = peak_memory_mb()


def score_normal_map_row(output: NormalMapResult, scene: Scene, row: dict[str, Any], job: RowJob,
                         started: float) -> None:
    """Photometric stereo: scored by angular error (`score_normal_maps`), pictured beside the truth."""
    _measured(row, started)
    row.update(score_normal_maps(output))
    if job.render:
        row["render"] = normal_map_picture(output, job.scene_name, job.method_name, job.run_dir)
    job.log(f"  {job.method_name:>12} on {job.scene_name}: normal error mean {row['normal_error_mean_deg']:.3f} "
            f"deg, median {row['normal_error_median_deg']:.3f} deg  {row['seconds']:.1f} s")


def score_mesh_row(output: Mesh, scene: Scene, row: dict[str, Any], job: RowJob, started: float) -> None:
    """A mesh: scored against the scene's ground truth (`evaluate_mesh`) and held-out views."""
    _score_mesh(output, {}, scene, row, job, started)


def score_scored_mesh_row(output: ScoredMesh, scene: Scene, row: dict[str, Any], job: RowJob,
                          started: float) -> None:
    """A mesh with figures only its method measures (a trajectory's): scored as a mesh, plus those."""
    _score_mesh(output.mesh, output.metrics, scene, row, job, started)


def score_scene_set_row(output: SceneSetMeshes, scene: SceneSet, row: dict[str, Any], job: RowJob,
                        started: float) -> None:
    """A scene set: the means of its scenes' metrics and the per-scene values; files of its first scene."""
    row["per_shape"] = output.per_shape
    _score_mesh(output.mesh, output.metrics, scene, row, job, started)
    if job.render and output.by_class:
        try:
            row["class_render"] = _class_picture(job.scene_name, job.method_name, output.by_class, job.run_dir,
                                                 job.render_size)
        except Exception as error:  # noqa: BLE001 - a render problem must not lose the numbers
            row["render_error"] = f"{type(error).__name__}: {error}"


Scorer = Callable[[Any, Any, dict[str, Any], RowJob, float], None]
SCORERS: dict[type, Scorer] = {
    Mesh: score_mesh_row,
    ScoredMesh: score_scored_mesh_row,
    NormalMapResult: score_normal_map_row,
    SceneSetMeshes: score_scene_set_row,
}
"""A method's output type -> the scorer that fills its row (metrics, files, the log line). A method that
returns a new kind of result adds its type and scorer here."""


def scorer(output: Any) -> Scorer:
    """The scorer of `output`'s type (or of its nearest base class in `SCORERS`); TypeError for any other."""
    for kind in type(output).__mro__:
        if kind in SCORERS:
            return SCORERS[kind]
    raise TypeError(f"the method returned {type(output).__name__}, not a neuralsurf Mesh (or another result "
                    f"with a scorer: {', '.join(kind.__name__ for kind in SCORERS)})")


def _score_mesh(mesh: Mesh, own_metrics: dict[str, float], scene: Scene | SceneSet, row: dict[str, Any],
                job: RowJob, started: float) -> None:
    """Score a mesh (`evaluate_mesh` against the scene's ground truth, when it has one; a scene set has
    none, its scenes' metrics come in `own_metrics`), add `own_metrics` and the held-out views' depth
    metrics, then write its files: the mesh, the distances to the ground truth, the renders."""
    if getattr(scene, "cloud_from_truth", False):
        raise NotApplicable("the scene's only 3D input is made from its ground-truth normals (a photometric "
                            "capture without depth or a true surface): a mesh of it cannot be scored; its "
                            "photometric stereo rows are")
    mesh = check_mesh(mesh)
    _measured(row, started)
    metrics = {}
    if getattr(scene, "ground_truth", None) is not None:
        metrics = evaluate_mesh(mesh, scene.ground_truth, n_samples=job.n_samples, seed=job.seed)
        if not math.isfinite(metrics["chamfer_l1"]):
            raise ValueError(f"the metrics are not finite (chamfer_l1 = {metrics['chamfer_l1']})")
    closed = watertight(mesh, metrics)  # before a scene set's own metrics bring their shapes' mean
    metrics.update(own_metrics)
    if getattr(scene, "held_out", None) is not None:
        errors = held_out_errors(mesh, scene.held_out)
        metrics.update(depth_metrics(mesh, scene.held_out, errors=errors))
        save_held_out_error_map(job.run_dir, job.scene_name, job.method_name, errors)  # the report's common pixels
    row.update(metrics)
    row.update(n_vertices=len(mesh.vertices), n_faces=len(mesh.faces), watertight=closed)
    _mesh_files(mesh, scene, row, job)


def _mesh_files(mesh: Mesh, scene: Scene | SceneSet, row: dict[str, Any], job: RowJob) -> None:
    """The mesh, its distances to the ground truth and its renders, written under `job.run_dir` and named in
    `row`; a render problem is noted in the row, never loses the numbers."""
    run_dir, scene_name, method_name, render_size = job.run_dir, job.scene_name, job.method_name, job.render_size
    if job.save_meshes:
        path = Path("meshes") / f"{row_stem(scene_name, method_name)}{job.mesh_extension}"
        with replaced(run_dir / path) as temporary:
            write_mesh(temporary, mesh)
        row["mesh"] = str(path)
    shown = shown_scene(scene)  # of a scene set: its first scene
    if (job.render or job.save_meshes) and shown.ground_truth is not None:  # coloured with the report
        try:
            row["distances"] = save_distances(run_dir, scene_name, method_name, mesh, shown.ground_truth, render_size)
        except Exception as error:  # noqa: BLE001 - an error view problem must not lose the numbers
            row["distances_error"] = f"{type(error).__name__}: {error}"
    if job.render and shown.ground_truth is not None:
        try:
            if job.built["gt_image"] is None:
                job.built["gt_image"] = _gt_render(shown, run_dir, render_size)
            row["render"] = _render_row(shown, mesh, method_name, job.built["gt_image"], run_dir, render_size)
        except Exception as error:  # noqa: BLE001 - a render problem must not lose the numbers
            row["render_error"] = f"{type(error).__name__}: {error}"
    if job.render and getattr(scene, "held_out", None) is not None:
        try:
            row["held_out_render"] = save_held_out_errors(run_dir, scene_name, method_name, mesh, scene.held_out)
        except Exception as error:  # noqa: BLE001 - a render problem must not lose the numbers
            row["render_error"] = f"{type(error).__name__}: {error}"
    job.log(f"  {method_name:>12} on {scene_name}: chamfer_l1 {row.get('chamfer_l1', math.nan):.5f}  "
            f"F@1% {row.get('fscore_1%', math.nan):.3f}  depth error {row.get('depth_error_mean', math.nan):.4f}  "
            f"completeness {row.get('depth_completeness', math.nan):.3f}  {row['seconds']:.1f} s  "
            f"{row['peak_rss_mb']:.0f} MiB  {row['n_faces']} faces")


def run_scene_set(scenes: SceneSet, method: Callable[..., Mesh], seed: int, run_dir: Path,
                  n_samples: int) -> SceneSetMeshes:
    """`method` on every scene of a set, each mesh scored against its ground truth (`evaluate_mesh`).
    Returns the first scene's mesh, the means of the metrics with "shapes" and "seconds_per_shape"
    (median), the per-scene metrics with their names and seconds, and the first scene of each class with
    its mesh. The first failure fails the row."""
    first, per_scene, by_class = None, [], {}
    for member in scenes.scenes:
        started = time.perf_counter()
        mesh = check_mesh(method(member, seed=seed, run_dir=run_dir))
        seconds = time.perf_counter() - started
        scored = evaluate_mesh(mesh, member.ground_truth, n_samples=n_samples, seed=seed)
        metrics = {k: None if math.isnan(float(v)) else float(v) for k, v in scored.items()}  # JSON: null
        per_scene.append({"shape": member.name, **metrics, "seconds": seconds,
                          "watertight": float(watertight(mesh, scored))})
        first = mesh if first is None else first
        by_class.setdefault(shape_class(member.name), (member, mesh))
    means = mean_metrics(per_scene)
    means["seconds_per_shape"] = float(np.median([row["seconds"] for row in per_scene]))
    return SceneSetMeshes(first, {k: v for k, v in means.items() if k not in ("seconds", "watertight", "failed")},
                          per_scene, by_class)


def shown_scene(scene: Scene | SceneSet) -> Scene:
    """The scene whose render represents a row: the scene, or a set's first (named after the set)."""
    if isinstance(scene, SceneSet):
        import dataclasses

        return dataclasses.replace(scene.scenes[0], name=f"{scene.name}_{scene.scenes[0].name}")
    return scene


def _write_traceback(run_dir: Path, name: str) -> None:
    path = run_dir / "errors" / f"{name}.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(traceback.format_exc())


def _view(scene: Scene) -> dict:
    return default_view(scene.ground_truth.bounds.double().cpu().numpy())


def _gt_render(scene: Scene, run_dir: Path, size: int):
    return shade(scene.ground_truth, _view(scene), size, size, color=(0.80, 0.80, 0.80))


def _render_row(scene: Scene, mesh: Mesh, method: str, gt_image, run_dir: Path, size: int) -> str:
    """ground truth | reconstruction shaded | reconstruction coloured by distance to gt -> one PNG."""
    view = _view(scene)
    lo, hi = scene.ground_truth.bounds.double().cpu().numpy()
    max_distance = 0.01 * float((hi - lo).max())  # the F-score's 1 % threshold: red = beyond it
    images = [gt_image, shade(mesh, view, size, size), distance_image(mesh, scene.ground_truth, view, max_distance,
                                                                     size, size)]
    labels = [f"{scene.name}: ground truth", f"{method}", f"{method}: distance (red >= 1%)"]
    path = Path("renders") / f"{row_stem(scene.name, method)}.png"
    with replaced(run_dir / path) as temporary:
        labelled_row(images, labels).save(temporary)
    return str(path)


def _class_picture(scene_name: str, method: str, by_class: dict[str, tuple[Scene, Mesh]], run_dir: Path,
                   size: int) -> str:
    """One line per class of a scene set, its first shape: the input (the cloud or the view's points) |
    the method's mesh | the ground truth, all from the same side -> renders/<scene>__<method>_classes.png."""
    lines = []
    for member, mesh in by_class.values():
        view = _view(member)
        images = [points_image(member.cloud.points.double().cpu().numpy(), view, size, size), shade(mesh, view, size, size),
                  shade(member.ground_truth, view, size, size, color=(0.80, 0.80, 0.80))]
        lines.append(labelled_row(images, [f"{member.name}: input", method, "ground truth"]))
    canvas = Image.new("RGB", (max(line.width for line in lines), sum(line.height for line in lines)), "white")
    top = 0
    for line in lines:
        canvas.paste(line, (0, top))
        top += line.height
    path = Path("renders") / f"{row_stem(scene_name, method)}_classes.png"
    with replaced(run_dir / path) as temporary:
        canvas.save(temporary)
    return str(path)
