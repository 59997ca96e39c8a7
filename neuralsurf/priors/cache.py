"""Per-shape caches of training samples (npz), built in parallel, resumable, written atomically.

One file per shape, `<out>/<split>/<name>.npz`, read with `np.load(path, allow_pickle=False)`:

- `sdf_points` Float32[n_sdf, 3], `sdf_values` Float32[n_sdf]: DeepSDF's recipe (Park et al. 2019):
  surface points perturbed by Gaussian noise at two scales (`near_sigmas`, half of the samples at
  each), plus a `volume_fraction` of points uniform in the box; values from the analytic SDF.
- `occ_uniform_points` Float32[n_occ, 3], `occ_uniform_inside` Bool[n_occ]: Occupancy Networks'
  recipe (Mescheder et al. 2019): uniform in the unit cube padded by `padding`, exact labels.
- `occ_near_points`, `occ_near_inside`: surface points plus N(0, `occ_near_sigma`) noise, exact labels.
- `surface_points`, `surface_normals` Float32[n_surface, 3]: area-uniform on the marching-cubes mesh,
  then projected onto the analytic zero set (Newton steps), with the analytic normals.
- `mesh_vertices` Float32[v, 3], `mesh_faces` Int64[f, 3]: the watertight ground-truth mesh (marching
  cubes of the analytic SDF at `mesh_resolution`).
- `recipe`: a JSON string of the record and this recipe; a cache built with another recipe is an
  error, never silently mixed.

All samples of a shape come from its own seed, so a file is the same however the build was split
across processes or interrupted. Files are stored uncompressed, so that training reads the rows of a
step's shapes in place (`SplitArrays`) instead of holding every shape's samples in memory.
"""

from __future__ import annotations

import contextlib
import json
import os
import zipfile
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, FileFormatError
from neuralsurf.geometry import sample_mesh_surface
from neuralsurf.io.npz import ArraySpan, npz_spans, write_npz
from neuralsurf.locks import file_lock
from neuralsurf.priors.procedural import Shape, ShapeRecord, check_shape
from neuralsurf.structures import Mesh

CACHE_KEYS = ("sdf_points", "sdf_values", "occ_uniform_points", "occ_uniform_inside", "occ_near_points",
              "occ_near_inside", "surface_points", "surface_normals", "mesh_vertices", "mesh_faces", "recipe")


@dataclass(frozen=True)
class CacheRecipe:
    """How many samples of each kind, and where (unit frame)."""

    n_sdf: int = 250_000
    """SDF samples (DeepSDF used 500k per shape)."""
    near_sigmas: tuple[float, float] = (0.025, 0.0079)
    """DeepSDF's noise scales (variances 0.0025 and 0.00025 in a unit sphere) halved for the unit cube."""
    volume_fraction: float = 0.1
    """Fraction of SDF samples uniform in [-0.5 - padding, 0.5 + padding]^3."""
    n_occ: int = 100_000
    """Occupancy points of each kind (uniform; near the surface)."""
    occ_near_sigma: float = 0.01
    """Noise of near-surface occupancy points."""
    padding: float = 0.05
    """Half of OccNet's 0.1 padding on each side of the unit cube."""
    n_surface: int = 100_000
    """Surface samples (for input clouds and metrics)."""
    mesh_resolution: int = 128
    """Marching-cubes resolution of the ground-truth mesh over the padded cube."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "near_sigmas", tuple(float(s) for s in self.near_sigmas))
        counts = {k: getattr(self, k) for k in ("n_sdf", "n_occ", "n_surface", "mesh_resolution")}
        if any(not isinstance(v, int) or v < 1 for v in counts.values()):
            raise ConfigError(f"CacheRecipe needs positive integer counts, got {counts}")
        if not (0 <= self.volume_fraction <= 1 and self.padding >= 0 and len(self.near_sigmas) == 2
                and min(self.near_sigmas) > 0 and self.occ_near_sigma > 0):
            raise ConfigError(f"CacheRecipe needs 0 <= volume_fraction <= 1, padding >= 0 and two positive "
                              f"near_sigmas and occ_near_sigma > 0, got {self}")

    @property
    def n_volume(self) -> int:
        """SDF samples uniform in the padded cube (the rest are near the surface)."""
        return round(self.n_sdf * self.volume_fraction)

    @property
    def n_base(self) -> int:
        """Surface points a cache's samples start from (`sample_positions`)."""
        return self.n_surface + self.n_sdf - self.n_volume + self.n_occ


def sample_positions(surface: Tensor, recipe: CacheRecipe, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """Where a cache's samples lie, from Float64[Tensor, "n_base 3"] surface points (`recipe.n_base`:
    the first `n_surface` are the surface samples themselves, the next feed the near-surface SDF
    samples, the last `n_occ` the near-surface occupancy samples).

    Returns:
        sdf points Float64[Tensor, "n_sdf 3"] (near the surface at both `near_sigmas`, then uniform),
        uniform occupancy points and near-surface occupancy points, Float64[Tensor, "n_occ 3"] each.
    """
    n_near = recipe.n_sdf - recipe.n_volume
    half = 0.5 + recipe.padding

    def uniform(n: int) -> Tensor:
        return (2 * torch.rand(n, 3, dtype=torch.float64, generator=generator) - 1) * half

    sigmas = torch.tensor(recipe.near_sigmas, dtype=torch.float64)[torch.arange(n_near) % 2]
    near = surface[recipe.n_surface:recipe.n_surface + n_near]
    near = near + sigmas[:, None] * torch.randn(n_near, 3, dtype=torch.float64, generator=generator)
    sdf_points = torch.cat([near, uniform(recipe.n_volume)])
    occ_near = surface[recipe.n_surface + n_near:recipe.n_base]
    occ_near = occ_near + recipe.occ_near_sigma * torch.randn(len(occ_near), 3, dtype=torch.float64,
                                                              generator=generator)
    return sdf_points, uniform(recipe.n_occ), occ_near


def shape_samples(shape: Shape, recipe: CacheRecipe) -> dict[str, np.ndarray]:
    """Every array of a shape's cache (see the module docstring), from the shape's own seed."""
    mesh = shape.mesh(recipe.mesh_resolution, recipe.padding)
    check_shape(shape, mesh)
    generator = torch.Generator().manual_seed(shape.record.seed % (2**63))
    base, _ = sample_mesh_surface(Mesh(mesh.vertices.double(), mesh.faces), recipe.n_base, generator)
    surface, normals = shape.project(base)
    sdf_points, occ_uniform, occ_near = sample_positions(surface, recipe, generator)
    record = json.dumps({"record": asdict(shape.record), "recipe": asdict(recipe)}, sort_keys=True)
    return {
        "sdf_points": sdf_points.float().numpy(),
        "sdf_values": shape.sdf(sdf_points).float().numpy(),
        "occ_uniform_points": occ_uniform.float().numpy(),
        "occ_uniform_inside": shape.inside(occ_uniform).numpy(),
        "occ_near_points": occ_near.float().numpy(),
        "occ_near_inside": shape.inside(occ_near).numpy(),
        "surface_points": surface[: recipe.n_surface].float().numpy(),
        "surface_normals": normals[: recipe.n_surface].float().numpy(),
        "mesh_vertices": mesh.vertices.float().numpy(),
        "mesh_faces": mesh.faces.numpy().astype(np.int64),
        "recipe": np.array(record),
    }


def cache_path(out: Path, record: ShapeRecord) -> Path:
    return Path(out) / record.split / f"{record.name}.npz"


def load_cache(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of one shape's cache (plain arrays only: `allow_pickle=False`). Raises
    FileFormatError for a missing, truncated or foreign file."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError) as error:
        raise FileFormatError(f"cannot read shape cache {path}: {error}; delete it and build the collection "
                              f"again (python -m neuralsurf.priors build ...)") from None
    missing = [key for key in CACHE_KEYS if key not in arrays]
    if missing:
        raise FileFormatError(f"shape cache {path} lacks {missing}; it was not written by neuralsurf.priors: "
                              f"delete it and build again")
    return arrays


class SplitArrays:
    """Arrays of the caches of a collection's shapes, read from disk a few rows of a few shapes at a time
    (`take`), so that training holds a step's batch, not every shape's samples: memory independent of
    the number of shapes. Each key must have one shape in every cache (one recipe)."""

    def __init__(self, paths: Sequence[Path], keys: tuple[str, ...]):
        self.spans: list[dict[str, ArraySpan]] = [npz_spans(path, keys) for path in paths]
        for key in keys:
            shapes = {spans[key].shape for spans in self.spans}
            if len(shapes) > 1:
                raise FileFormatError(f"the caches of one collection hold {key!r} of shapes {sorted(shapes)[:3]}: they "
                                      f"were built with other recipes; build the collection again into a new folder")

    def __len__(self) -> int:
        return len(self.spans)

    def rows(self, key: str) -> int:
        """Rows of `key` in each shape's cache."""
        return self.spans[0][key].shape[0]

    def take(self, key: str, shapes: Tensor, rows: Tensor) -> Tensor:
        """Rows `rows` (Int[Tensor, "b k"]) of `key` of the shapes `shapes` (Int[Tensor, "b"]):
        [b, k, *rest of key's shape] (`cache[shapes[i]][key][rows[i]]`)."""
        rows = rows.cpu().numpy()
        return torch.from_numpy(np.stack([self.spans[s][key].rows(r) for s, r in zip(shapes.tolist(), rows)]))


def cached_recipe(path: Path) -> str | None:
    """The recipe string of an existing, readable cache, or None."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return str(data["recipe"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):  # unreadable: built again
        return None


def is_cached(record: ShapeRecord, out: str | Path, recipe: CacheRecipe) -> bool:
    """Whether `out` holds a readable cache of `record` built with `recipe`. Raises ConfigError for a
    cache of the same name built with another recipe (never mixed silently)."""
    path = cache_path(Path(out), record)
    if not path.exists():
        return False
    expected = json.dumps({"record": asdict(record), "recipe": asdict(recipe)}, sort_keys=True)
    found = cached_recipe(path)
    if found is not None and found != expected:
        raise ConfigError(f"{path} was built with another recipe or record ({found}); build into another "
                          f"folder or delete it")
    return found == expected


def build_shape(record: ShapeRecord, out: str | Path, recipe: CacheRecipe) -> str:
    """Write one shape's cache (unless already there with this recipe); returns "built" or "cached"."""
    if is_cached(record, out, recipe):
        return "cached"
    write_npz(cache_path(Path(out), record), shape_samples(Shape.from_record(record), recipe))
    return "built"


def _build_job(args) -> tuple[str, str]:
    record, out, recipe = args
    return record.name, build_shape(record, out, recipe)


def _one_thread() -> None:
    torch.set_num_threads(1)


def run_jobs(work: Callable[[tuple], tuple[str, str]], jobs: Sequence[tuple], workers: int, progress: bool,
             counts: dict[str, int] | None = None, on_done: Callable[[str, str], None] | None = None) -> dict[str, int]:
    """Run `work(job) -> (name, status)` on every job, in `workers` spawned processes of one torch
    thread each (0: in this one), with a progress bar; `work` must be a module-level function.
    Returns `counts` (shapes per status, e.g. {"built": ..., "cached": ...}) with these jobs added."""
    from tqdm.auto import tqdm

    counts = dict(counts or {})
    done = sum(counts.values())
    bar = tqdm(total=done + len(jobs), initial=done, desc="shapes", disable=not progress, dynamic_ncols=True)
    with contextlib.ExitStack() as stack:
        stack.callback(bar.close)
        if workers > 0 and jobs:
            pool = stack.enter_context(ProcessPoolExecutor(workers, mp_context=get_context("spawn"),
                                                           initializer=_one_thread))
            results = pool.map(work, jobs)
        else:
            results = map(work, jobs)
        for name, status in results:
            counts[status] = counts.get(status, 0) + 1
            bar.update(1)
            if on_done:
                on_done(name, status)
    return counts


def write_manifest(out: Path, records: Sequence[ShapeRecord], recipe: CacheRecipe) -> Path:
    """`<out>/collection.json`: the recipe and the shapes of each split, in latent-code order."""
    manifest = {"recipe": asdict(recipe), "shapes": [asdict(r) for r in records]}
    path = Path(out) / "collection.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".collection.json.{os.getpid()}.tmp")
    temporary.write_text(json.dumps(manifest, indent=1))
    os.replace(temporary, path)
    return path


def read_manifest(out: str | Path) -> tuple[list[ShapeRecord], CacheRecipe]:
    """The records and recipe of a built collection."""
    path = Path(out) / "collection.json"
    if not path.is_file():
        raise FileFormatError(f"{path} not found: build the collection first "
                              f"(python -m neuralsurf.priors build --out {out})")
    manifest = json.loads(path.read_text())
    return [ShapeRecord(**r) for r in manifest["shapes"]], CacheRecipe(**manifest["recipe"])


def build_collection(out: str | Path, records: Sequence[ShapeRecord], recipe: CacheRecipe = CacheRecipe(),
                     workers: int = 0, progress: bool = True,
                     on_done: Callable[[str, str], None] | None = None) -> dict[str, int]:
    """Write the cache of every record under `out` (and `collection.json`), skipping shapes already
    cached with the same recipe: an interrupted build resumes where it stopped. `workers` > 0 builds
    in that many processes, 0 in this one. Returns counts {"built": ..., "cached": ...}. Processes that
    build the same folder together (the jobs of an evaluation sweep) take turns under the lock
    `<out>/.build.lock`: the first builds, the others then find every shape cached."""
    with file_lock(Path(out) / ".build.lock"):
        return _build_collection(Path(out), records, recipe, workers, progress, on_done)


def _build_collection(out: Path, records: Sequence[ShapeRecord], recipe: CacheRecipe, workers: int,
                      progress: bool, on_done: Callable[[str, str], None] | None) -> dict[str, int]:
    """`build_collection` without its lock."""
    write_manifest(out, records, recipe)
    cached = {record.name for record in records if is_cached(record, out, recipe)}
    jobs = [(record, str(out), recipe) for record in records if record.name not in cached]
    return run_jobs(_build_job, jobs, workers or 0, progress, {"built": 0, "cached": len(cached)}, on_done)
