"""Learned priors from shape collections on disk: a folder of meshes with one class per subfolder, or
Occupancy Networks' preprocessed layout (`neuralsurf.io.shape_folders`).

`FolderCollection` is the folder counterpart of `ShapeCollection`: `build()` writes one cache per
shape with the same arrays as the procedural caches (`priors.cache`), so `CollectionSDF`,
`CollectionOccupancy`, `train_prior` and the `shapes_cloud` / `shapes_one_view` scenes take it as
they are.

Real meshes are rarely watertight, so signs never come from ray parity (`mesh_samples`): the faces
are turned outward patch by patch (`winding.orient_outward`), the surface is the faces between
inside and outside (`winding.boundary_faces`: inner and stray sheets left out), signed distances are
the distance to that surface with the sign of the generalised winding number, and occupancy is the
winding number at least 1/2.

Canonical frame: each mesh is moved into the unit frame of the priors, its bounding box centred and
its longest side 1 (`normalize=True`; `False` for files already in it, as Occupancy Networks' are),
keeping its orientation: the collection's files must share one up axis (y for the procedural
classes and ShapeNet). `build()` records the training shapes' frame statistics (`FrameStats`);
`test_shapes()` warns when a test shape's size in its file or its apparent up axis disagrees with
them (`check_frame`).
"""

from __future__ import annotations

import hashlib
import json
import math
import random
import warnings
from dataclasses import asdict, dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.data import cache_dir
from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.geometry import knn, mesh_contains, point_to_mesh_distance, sample_mesh_surface
from neuralsurf.io.meshes import read_mesh
from neuralsurf.io.npz import write_npz
from neuralsurf.io.shape_folders import (
    OccupancyShape,
    ShapeEntry,
    folder_layout,
    list_mesh_folder,
    list_occupancy_folder,
    read_occupancy_shape,
)
from neuralsurf.locks import file_lock
from neuralsurf.priors.cache import (
    CacheRecipe,
    cache_path,
    cached_recipe,
    load_cache,
    run_jobs,
    sample_positions,
)
from neuralsurf.priors.collection import TestShape
from neuralsurf.priors.procedural import ShapeRecord
from neuralsurf.structures import Mesh, Normalization
from neuralsurf.winding import boundary_faces, inside, orient_outward

# ----------------------------------------------------------------------------- samples of one shape


def mesh_samples(mesh: Mesh, recipe: CacheRecipe, seed: int = 0) -> dict[str, np.ndarray]:
    """The arrays of a shape's cache (`priors.cache`) from a mesh in the unit frame that need not be
    watertight: faces turned outward, the boundary surface (`boundary_faces`) sampled, distances to
    it signed by the winding number. `mesh_vertices` / `mesh_faces` hold that boundary surface."""
    if mesh.is_empty:
        raise InputError("mesh_samples needs a mesh with faces, got an empty mesh")
    mesh = orient_outward(Mesh(mesh.vertices.double(), mesh.faces), seed=seed)
    keep = boundary_faces(mesh)
    if not keep.any():
        raise InputError("the mesh has no faces between inside and outside (no closed or nearly closed part): "
                         "it is a set of open sheets with no volume; a prior needs solid shapes")
    used, faces = torch.unique(mesh.faces[keep], return_inverse=True)
    surface_mesh = Mesh(mesh.vertices[used], faces.reshape(-1, 3))
    generator = torch.Generator().manual_seed(seed)
    surface, normals = sample_mesh_surface(surface_mesh, recipe.n_base, generator)
    sdf_points, occ_uniform, occ_near = sample_positions(surface, recipe, generator)
    points = torch.cat([sdf_points, occ_uniform, occ_near])
    sdf_inside, uniform_inside, near_inside = inside(points, surface_mesh).split(
        [len(sdf_points), len(occ_uniform), len(occ_near)])
    distance = point_to_mesh_distance(sdf_points, surface_mesh)
    return {
        "sdf_points": sdf_points.float().numpy(),
        "sdf_values": torch.where(sdf_inside, -distance, distance).float().numpy(),
        "occ_uniform_points": occ_uniform.float().numpy(),
        "occ_uniform_inside": uniform_inside.numpy(),
        "occ_near_points": occ_near.float().numpy(),
        "occ_near_inside": near_inside.numpy(),
        "surface_points": surface[: recipe.n_surface].float().numpy(),
        "surface_normals": normals[: recipe.n_surface].float().numpy(),
        "mesh_vertices": surface_mesh.vertices.float().numpy(),
        "mesh_faces": surface_mesh.faces.numpy().astype(np.int64),
    }


def occupancy_samples(shape: OccupancyShape, recipe: CacheRecipe, seed: int = 0) -> dict[str, np.ndarray]:
    """The arrays of a shape's cache from Occupancy Networks' files (unit frame): occupancies as
    given (uniform points), surface and normals from the point cloud; near-surface signs from the
    closest cloud point's normal and distances to the cloud (within its spacing of the surface's).
    No mesh: `mesh_vertices` / `mesh_faces` are empty."""
    if shape.normals is None:
        raise InputError("Occupancy Networks' pointcloud.npz has no normals: near-surface signs need them")
    generator = torch.Generator().manual_seed(seed)
    cloud, cloud_normals = shape.surface.double(), shape.normals.double()
    pick = torch.randint(len(cloud), (recipe.n_base,), generator=generator)
    sdf_points, _, occ_near = sample_positions(cloud[pick], recipe, generator)
    n_volume = recipe.n_volume
    order = torch.randperm(len(shape.points), generator=generator)
    uniform, uniform_inside = shape.points.double()[order], shape.occupancies[order]
    near = sdf_points[: recipe.n_sdf - n_volume]

    def signed(points: Tensor) -> Tensor:
        distance, index = knn(points, cloud, 1)
        side = ((points - cloud[index[:, 0]]) * cloud_normals[index[:, 0]]).sum(-1)
        return torch.where(side < 0, -distance[:, 0], distance[:, 0])

    volume, volume_inside = uniform[:n_volume], uniform_inside[:n_volume]
    volume_sdf = knn(volume, cloud, 1)[0][:, 0]
    sdf = torch.cat([signed(near), torch.where(volume_inside, -volume_sdf, volume_sdf)])
    return {
        "sdf_points": torch.cat([near, volume]).float().numpy(),
        "sdf_values": sdf.float().numpy(),
        "occ_uniform_points": uniform[: recipe.n_occ].float().numpy(),
        "occ_uniform_inside": uniform_inside[: recipe.n_occ].numpy(),
        "occ_near_points": occ_near.float().numpy(),
        "occ_near_inside": (signed(occ_near) < 0).numpy(),
        "surface_points": cloud[pick[: recipe.n_surface]].float().numpy(),
        "surface_normals": cloud_normals[pick[: recipe.n_surface]].float().numpy(),
        "mesh_vertices": np.zeros((0, 3), np.float32),
        "mesh_faces": np.zeros((0, 3), np.int64),
    }


def sign_errors(arrays: dict[str, np.ndarray], reference: Mesh, recipe: CacheRecipe) -> dict[str, float]:
    """Shares of a shape cache's samples whose side disagrees with a watertight reference mesh in the
    cache's frame (its exact inside by ray parity, `geometry.mesh_contains`): how wrong the labels
    taken from a damaged mesh are, with the clean mesh as the reference.

    Returns:
        {"sdf_near", "sdf_volume" (the SDF samples near the surface and uniform in the box, by sign),
        "occ_uniform", "occ_near" (the occupancy samples)}: each a share in [0, 1].
    """
    sdf_points = torch.from_numpy(arrays["sdf_points"]).double()
    occ = {key: torch.from_numpy(arrays[f"{key}_points"]).double() for key in ("occ_uniform", "occ_near")}
    points = torch.cat([sdf_points, *occ.values()])
    truth = mesh_contains(points, Mesh(reference.vertices.double(), reference.faces))
    labels = torch.cat([torch.from_numpy(arrays["sdf_values"]) < 0, torch.from_numpy(arrays["occ_uniform_inside"]),
                        torch.from_numpy(arrays["occ_near_inside"])])
    wrong = (labels != truth).split([len(sdf_points) - recipe.n_volume, recipe.n_volume, *map(len, occ.values())])
    return {key: float(part.double().mean()) if len(part) else 0.0
            for key, part in zip(("sdf_near", "sdf_volume", "occ_uniform", "occ_near"), wrong)}


# ----------------------------------------------------------------------------- canonical frame

UP_CHOICES = {"+y": (0, 1, 2, 1.0), "-y": (0, 1, 2, -1.0), "+z": (0, 2, 1, 1.0), "-z": (0, 2, 1, -1.0),
              "+x": (1, 0, 2, 1.0), "-x": (1, 0, 2, -1.0)}
"""A file's up axis -> (axes that become x, y, z; sign of the new y)."""


def frame_features(surface: Tensor) -> Tensor:
    """Float64[Tensor, "6"]: the extents of a shape's surface points (Float[Tensor, "n 3"], unit frame)
    along x, y, z and the offset of their mean from the bounding box's centre: what tells a shape's
    up axis from the others (a chair is tallest along y and has more surface below its seat)."""
    points = surface.double()
    low, high = points.min(0).values, points.max(0).values
    return torch.cat([high - low, points.mean(0) - (low + high) / 2])


def _turned(surface: Tensor, up: str) -> Tensor:
    """The points seen with axis `up` of the file as y."""
    a, b, c, sign = UP_CHOICES[up]
    points = surface[:, [a, b, c]].clone()
    points[:, 1] *= sign
    return points


@dataclass(frozen=True)
class FrameStats:
    """Statistics of a collection's training shapes in its canonical frame."""

    mean: tuple[float, ...]
    """The mean of `frame_features` over the training shapes."""
    std: tuple[float, ...]
    log_size_mean: float
    """Mean and standard deviation of log10 of the longest side in the files (before normalising)."""
    log_size_std: float

    @classmethod
    def from_shapes(cls, surfaces: list[Tensor], sizes: list[float]) -> FrameStats:
        """The statistics of the shapes' surface points (Float[Tensor, "n 3"] each, unit frame) and of
        their longest sides in their files."""
        return cls.from_features([frame_features(s) for s in surfaces], sizes)

    @classmethod
    def from_features(cls, features: list[Tensor], sizes: list[float]) -> FrameStats:
        """The statistics of the shapes' `frame_features` and of their longest sides in their files."""
        features = torch.stack(features)
        logs = np.log10(np.maximum(sizes, 1e-30))
        return cls(tuple(features.mean(0).tolist()), tuple(features.std(0, unbiased=False).tolist()),
                   float(logs.mean()), float(logs.std()))

    def distance(self, surface: Tensor) -> float:
        """RMS of the standardised features of a shape (unit frame) from the collection's means."""
        spread = torch.tensor(self.std, dtype=torch.float64).clamp_min(0.02)  # a floor: few or alike shapes
        z = (frame_features(surface) - torch.tensor(self.mean, dtype=torch.float64)) / spread
        return float(z.square().mean().sqrt())


def check_frame(surface: Tensor, stats: FrameStats, where: str, size: float | None = None) -> str | None:
    """Warn when a shape does not sit in the collection's canonical frame; returns the warning or None.

    - bounds: its points (Float[Tensor, "n 3"], unit frame) reach beyond the padded unit cube, or its
      longest side in its file (`size`) is more than 10x off the training shapes' (other units?);
    - up axis: turning another of its axes to y brings its `frame_features` much closer to the
      collection's (RMS z-score below half, and at least 2 better).
    """
    messages = []
    reach = float(surface.abs().max())
    if reach > 0.55 + 1e-6:
        messages.append(f"its points reach {reach:.3g} from the centre, outside the unit frame [-0.5, 0.5]^3 of the "
                        f"collection's shapes: normalise it (bounding box centred, longest side 1)")
    if size is not None and abs(math.log10(max(size, 1e-30)) - stats.log_size_mean) > 1 + 2 * stats.log_size_std:
        messages.append(f"its longest side in its file is {size:.3g}, the training shapes' about "
                        f"{10 ** stats.log_size_mean:.3g}: other units?")
    scores = {up: stats.distance(_turned(surface, up)) for up in UP_CHOICES}
    best = min(scores, key=scores.get)
    if best != "+y" and scores[best] < 0.5 * scores["+y"] and scores["+y"] - scores[best] > 2:
        messages.append(f"its up axis looks like {best} where the collection's is +y (frame distance "
                        f"{scores['+y']:.2f} as it is, {scores[best]:.2f} with {best} up): rotate it into the "
                        f"collection's frame")
    if not messages:
        return None
    message = f"{where}: " + "; ".join(messages)
    warnings.warn(message, stacklevel=2)
    return message


# ----------------------------------------------------------------------------- the collection


def shard_part(items: list, shard: int, shards: int) -> list:
    """Part `shard` of `shards` consecutive parts of almost equal length (a build split into jobs).
    Raises ConfigError for a shard out of range."""
    if not (isinstance(shards, int) and shards >= 1 and isinstance(shard, int) and 0 <= shard < shards):
        raise ConfigError(f"shard={shard} shards={shards}: need shards >= 1 and 0 <= shard < shards; run "
                          f"shard 0, 1, ..., {shards - 1} to build every shape once")
    return items[shard * len(items) // shards:(shard + 1) * len(items) // shards]


def _cache_key(entry: ShapeEntry, record: ShapeRecord, recipe: CacheRecipe, normalize: bool) -> str:
    """What a shape's cache was built from: its record, the recipe and its file as it is now."""
    stat = entry.path.stat() if entry.path.is_file() else (entry.path / "points.npz").stat()
    source = {"path": str(entry.path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
    return json.dumps({"record": asdict(record), "recipe": asdict(recipe), "source": source, "normalize": normalize},
                      sort_keys=True)


def _shape_cache(entry: ShapeEntry, record: ShapeRecord, out: str, recipe: CacheRecipe, normalize: bool,
                 layout: str, seed: int) -> tuple[str, str]:
    """Write one shape's cache unless it is there with the same source and recipe; returns (name, status)."""
    path = cache_path(Path(out), record)
    key = _cache_key(entry, record, recipe, normalize)
    if path.is_file() and cached_recipe(path) == key:  # unreadable: built again
        return record.name, "cached"
    shape_seed = int(hashlib.sha256(f"{seed}/{entry.category}/{entry.name}".encode()).hexdigest()[:15], 16)
    if layout == "occupancy":
        arrays = occupancy_samples(read_occupancy_shape(entry.path), recipe, shape_seed)
        size = 1.0
    else:
        mesh = read_mesh(entry.path)
        size = float((mesh.vertices.max(0).values - mesh.vertices.min(0).values).max())
        if normalize:
            mesh = Normalization.from_points(mesh.vertices.double()).mesh_to_unit(Mesh(mesh.vertices.double(), mesh.faces))
        arrays = mesh_samples(mesh, recipe, shape_seed)
    arrays["file_size"] = np.array(size)
    arrays["recipe"] = np.array(key)
    write_npz(path, arrays)
    return record.name, "built"


def _build_job(args) -> tuple[str, str]:
    """`_shape_cache(*args)`; its errors name the shape's file."""
    try:
        return _shape_cache(*args)
    except NeuralsurfError as error:
        if str(args[0].path) in str(error):
            raise
        raise type(error)(f"{args[0].path}: {error}") from None


@dataclass(frozen=True)
class FolderCollection:
    """A shape collection read from a folder (train.py's `data` for priors on the user's shapes)."""

    source: str
    """A mesh folder (`<source>/<class>/<shape>.obj|ply|off|stl|glb`) or Occupancy Networks' layout
    (`<source>/<class>/<shape>/points.npz`); see `neuralsurf.io.shape_folders`."""
    classes: tuple[str, ...] | None = None
    """The class subfolders to use (None: all)."""
    n_train: int | None = None
    """At most this many training shapes per class (None: all)."""
    n_test: int | None = None
    """At most this many test shapes per class (None: all)."""
    test_fraction: float = 0.2
    """Share of a class's shapes held out for testing where the class has no .lst files."""
    seed: int = 0
    normalize: bool = True
    """Move each mesh into the unit frame (bounding box centred, longest side 1); False: the files
    already are (Occupancy Networks' are)."""
    n_sdf: int = 100_000
    n_occ: int = 50_000
    n_surface: int = 20_000
    root: str | None = None
    """Folder of the caches; None: `<$NEURALSURF_CACHE or ~/.cache/neuralsurf>/shape_folders/<settings hash>`."""
    workers: int = 0
    """Processes that build missing caches (0: this one)."""
    name: str = "folder"

    def __post_init__(self) -> None:
        if self.classes is not None:
            object.__setattr__(self, "classes", tuple(self.classes))
        if not 0 <= self.test_fraction < 1:
            raise ConfigError(f"FolderCollection: test_fraction must be in [0, 1), got {self.test_fraction}")
        for key in ("n_train", "n_test"):
            value = getattr(self, key)
            if value is not None and value < 0:
                raise ConfigError(f"FolderCollection: {key} must be >= 0 or null (all), got {value}")

    @property
    def recipe(self) -> CacheRecipe:
        return CacheRecipe(n_sdf=self.n_sdf, n_occ=self.n_occ, n_surface=self.n_surface)

    @cached_property
    def layout(self) -> str:
        """"meshes" or "occupancy" (`io.shape_folders.folder_layout`)."""
        return folder_layout(self.source)

    @cached_property
    def _entries(self) -> tuple[tuple[ShapeRecord, ShapeEntry], ...]:
        """(record, entry) of every shape used, by split then class, in latent-code order."""
        entries = list_occupancy_folder(self.source) if self.layout == "occupancy" else list_mesh_folder(self.source)
        by_class: dict[str, list[ShapeEntry]] = {}
        for entry in entries:
            by_class.setdefault(entry.category, []).append(entry)
        if self.classes is not None:
            unknown = sorted(set(self.classes) - set(by_class))
            if unknown:
                raise ConfigError(f"{self.source} has no class {unknown[0]!r}; its classes: {sorted(by_class)}")
            by_class = {c: by_class[c] for c in self.classes}
        split_of: dict[str, list[ShapeEntry]] = {"train": [], "val": [], "test": []}
        for category, shapes in by_class.items():
            unsplit = [s for s in shapes if s.split is None]
            random.Random(f"{self.seed}/{category}").shuffle(unsplit)
            n_test = round(self.test_fraction * len(unsplit)) if len(unsplit) > 1 else 0
            n_test = max(n_test, 1) if self.test_fraction > 0 and len(unsplit) > 1 else n_test
            chosen = {"train": [s for s in shapes if s.split == "train"] + sorted(unsplit[n_test:], key=_key),
                      "val": [s for s in shapes if s.split == "val"],
                      "test": [s for s in shapes if s.split == "test"] + sorted(unsplit[:n_test], key=_key)}
            for split, cap in (("train", self.n_train), ("val", None), ("test", self.n_test)):
                split_of[split] += chosen[split][:cap] if cap is not None else chosen[split]
        pairs = []
        for split, shapes in split_of.items():
            counts: dict[str, int] = {}
            for entry in shapes:
                index = counts.get(entry.category, 0)
                counts[entry.category] = index + 1
                pairs.append((ShapeRecord(entry.category, split, index, self.seed), entry))
        if not any(r.split == "train" for r, _ in pairs):
            raise ConfigError(f"{self.source}: no training shapes (n_train={self.n_train}, test_fraction="
                              f"{self.test_fraction}); a prior needs at least one")
        return tuple(pairs)

    @property
    def description(self) -> str:
        counts = {s: self.count(s) for s in ("train", "val", "test")}
        classes = sorted({r.kind for r in self.records()})
        return (f"{len(classes)} classes from {self.source} ({', '.join(classes)}): {counts['train']} train, "
                f"{counts['val']} val, {counts['test']} test shapes")

    @property
    def folder(self) -> Path:
        if self.root is not None:
            return Path(self.root).expanduser()
        key = {k: v for k, v in asdict(self).items() if k not in ("root", "workers", "name")}
        key["source"] = str(Path(self.source).expanduser().resolve())
        digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
        return cache_dir() / "shape_folders" / digest

    def records(self, split: str | None = None) -> list[ShapeRecord]:
        """The shapes of `split` (all when None), in latent-code order."""
        return [r for r, _ in self._entries if split is None or r.split == split]

    def count(self, split: str) -> int:
        return len(self.records(split))

    def sources(self, split: str | None = None) -> list[ShapeEntry]:
        """The files of `split`'s shapes, in the order of `records`."""
        return [e for r, e in self._entries if split is None or r.split == split]

    def build(self, progress: bool = True, shard: int = 0, shards: int = 1) -> Path:
        """Write every missing cache (resumable; a progress bar with an ETA) and `collection.json` with
        the training shapes' frame statistics; returns the folder. Processes building one folder
        together take turns. With `shards` > 1 only part `shard` of the shapes is built (`shard_part`),
        so that separate jobs build the parts at once; whichever finds every cache there writes
        `collection.json`, and a later build of the whole finds every shape cached."""
        out = self.folder
        part = shard_part(list(self._entries), shard, shards)
        lock = ".build.lock" if shards == 1 else f".build.{shard}-of-{shards}.lock"
        with file_lock(out / lock):
            jobs = [(e, r, str(out), self.recipe, self.normalize, self.layout, self.seed) for r, e in part]
            run_jobs(_build_job, jobs, self.workers, progress)
        if shards > 1 and not all(self.is_cached(record) for record in self.records()):
            return out  # the other parts are still being built
        with file_lock(out / ".build.lock"):
            self._write_manifest(out)
        return out

    def is_cached(self, record: ShapeRecord) -> bool:
        """Whether the shape's cache is there, readable, built from its file as it is now and with
        these settings."""
        entry = dict(self._entries)[record]
        path = cache_path(self.folder, record)
        return path.is_file() and cached_recipe(path) == _cache_key(entry, record, self.recipe, self.normalize)

    def _write_manifest(self, out: Path) -> None:
        features, sizes = [], []
        for record in self.records("train"):  # two arrays of one shape at a time: memory of a shape, not the collection
            with np.load(cache_path(out, record), allow_pickle=False) as data:
                features.append(frame_features(torch.from_numpy(data["surface_points"])))
                sizes.append(float(data["file_size"]))
        stats = FrameStats.from_features(features, sizes)
        manifest = {"recipe": asdict(self.recipe), "shapes": [asdict(r) for r in self.records()],
                    "source": str(self.source), "files": [str(e.path) for e in self.sources()],
                    "frame": asdict(stats)}
        text = json.dumps(manifest, indent=1)
        path = out / "collection.json"
        if not path.is_file() or path.read_text() != text:
            temporary = path.with_name(".collection.json.tmp")
            temporary.write_text(text)
            temporary.replace(path)

    def frame_stats(self) -> FrameStats:
        """The training shapes' frame statistics of the built collection."""
        path = self.folder / "collection.json"
        if not path.is_file():
            raise InputError(f"{path} not found: build the collection first (FolderCollection.build)")
        return FrameStats(**{k: tuple(v) if isinstance(v, list) else v
                             for k, v in json.loads(path.read_text())["frame"].items()})

    def check_prior(self, observations: dict[str, dict]) -> bool:
        """What can be checked before the collection is built for a prior trained on it with `observations`
        (name -> observation config as a plain dict). Occupancy Networks' layout has no meshes: depth views
        of them (`partial_views` with `partial`) are a ConfigError, and its test shapes cannot be scored
        (returns False, with a warning). A mesh folder without test shapes is a ConfigError. Returns
        whether the prior's test shapes can be scored."""
        if self.layout == "occupancy":
            for name, options in observations.items():
                if options.get("partial_views") and options.get("partial"):
                    raise ConfigError(f"{self.source} is in Occupancy Networks' layout, which has no meshes to take "
                                      f"depth views of; set observation.{name}.partial_views=0 (one-sided clouds from "
                                      f"a half-space) or observation.{name}.partial=0")
            warnings.warn(f"{self.source} is in Occupancy Networks' layout, which has no meshes to score test shapes "
                          f"against: the prior is trained and kept (checkpoints/last.pt) but not scored; score it on "
                          f"a mesh folder of the same classes", stacklevel=2)
            return False
        if not self.count("test"):
            raise ConfigError(f"{self.description}: no test shapes to score the prior on; list some in test.lst or "
                              f"set data.test_fraction > 0 (a class needs two shapes for one to be held out)")
        return True

    def test_shapes(self, limit: int | None = None) -> list[TestShape]:
        """The first `limit` test shapes (all when None), read from the built caches, each checked
        against the collection's frame (`check_frame` warns)."""
        if self.layout == "occupancy":
            raise ConfigError(f"{self.source} is in Occupancy Networks' layout, which has no meshes to score test "
                              f"shapes against; evaluate on a mesh folder of the same classes")
        stats = self.frame_stats()
        shapes = []
        for record, entry in [(r, e) for r, e in self._entries if r.split == "test"][:limit]:
            arrays = load_cache(cache_path(self.folder, record))
            shape = TestShape.from_cache(record.name, arrays)
            check_frame(shape.surface, stats, f"test shape {entry.path}", float(arrays["file_size"]))
            shapes.append(shape)
        if not shapes:
            raise ConfigError(f"{self.description}: no test shapes; list some in test.lst or set test_fraction > 0")
        return shapes


def _key(entry: ShapeEntry) -> str:
    return entry.name
