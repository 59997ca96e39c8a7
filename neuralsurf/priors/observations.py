"""Supervision from shape collections (`neuralsurf.priors.cache`) for learned priors.

- `CollectionSDF`: the SDF samples of every shape of a split, for a DeepSDF auto-decoder
  (`models.AutoDecoder`): clamped L1 (`sdf`, DeepSDF's delta 0.1) and the code prior (`code`,
  mean squared norm of the batch's codes: DeepSDF's 1 / sigma^2 ||z||^2 up to the weight).
- `CollectionOccupancy`: occupancy labels of every shape of a split with input clouds drawn from
  its surface samples, for an Occupancy Network (`models.OccupancyNetwork`): binary cross-entropy
  on the logits (`occupancy`).
- `SDFSampleSet`: points with known signed distances of one shape (clamped L1), e.g. a cached
  shape's own samples for a latent-code fit.
- `LatentPrior`: the code prior of a `models.LatentConditioned` (`code`: ||z||^2), which DeepSDF's
  reconstruction adds to whatever observation it fits (a cloud, depth rays, SDF samples).

Both collection observations read each step's shapes from their caches on disk (`cache.SplitArrays`),
so a fit holds one batch, not the collection: its memory does not grow with the number of shapes.

A collection lives in its own unit frame (each shape in [-0.5, 0.5]^3): fit with
`normalization=Normalization()` (the identity); another normalisation maps the samples through it.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from neuralsurf.cameras import backproject_depth
from neuralsurf.distributed import rank_and_world, shard_rows
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.io.npz import ArraySpan, npy_span
from neuralsurf.locks import file_lock
from neuralsurf.losses import clamped_l1
from neuralsurf.observations.base import Observation, Sampler, check_weights
from neuralsurf.priors.cache import SplitArrays, cache_path, load_cache, read_manifest
from neuralsurf.priors.procedural import UNIT_BOUNDS
from neuralsurf.scenes.scanner import ONE_VIEW_IMAGE, one_view_camera, scan_depth
from neuralsurf.structures import Mesh, Normalization


def split_paths(root: str | Path, split: str) -> list[Path]:
    """Cache files of one split of a built collection, in the manifest's (latent-code) order."""
    records, _ = read_manifest(root)
    paths = [cache_path(Path(root), r) for r in records if r.split == split]
    if not paths:
        raise ConfigError(f"the collection in {root} has no {split!r} shapes; build it with --n-{split} > 0")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise InputError(f"{len(missing)} caches of {root} are missing (e.g. {missing[0]}): the build was "
                         f"interrupted; run the same `python -m neuralsurf.priors build` command again to finish it")
    return paths


def _to_unit(points: Tensor, normalization: Normalization) -> Tensor:
    """Float[Tensor, "... 3"] points of the collection's frame in the fit's unit frame (float32)."""
    return normalization.to_unit(points.double()).float()


def global_shapes(shapes_per_batch: int, count: int, world: int, owner: str) -> int:
    """Shapes per step over all processes: `shapes_per_batch`, or all `count` when fewer, which
    must split evenly over `world` processes."""
    shapes = min(shapes_per_batch, count)
    shard_rows(shapes, world, f"{owner} (shapes_per_batch={shapes_per_batch}, {count} shapes)")
    return shapes


# ----------------------------------------------------------------------------- auto-decoder

COLLECTION_SDF_TERMS = ("sdf", "code")


@dataclass(frozen=True)
class ShapeSDFBatch:
    """SDF samples of a few shapes of a collection (unit frame)."""

    shape_index: Tensor
    """Int[Tensor, "b"]: row of each shape's latent code."""
    points: Tensor
    """Float[Tensor, "b s 3"]: sample positions."""
    sdf: Tensor
    """Float[Tensor, "b s"]: their signed distances."""


def draw_shape_sdf(arrays: SplitArrays, normalization: Normalization, shapes: int, samples: int,
                   generator: torch.Generator, rank: int = 0, world: int = 1) -> ShapeSDFBatch:
    """`shapes` distinct shapes at random (all when fewer), `samples` random SDF samples of each (keys
    `sdf_points`, `sdf_values` of `arrays`), in the unit frame of `normalization`. Under torchrun
    every rank draws the same global batch and reads its rows `rank::world` alone (see
    `neuralsurf.distributed`): each rank reads its own share of the step's shapes."""
    shape_index = torch.randperm(len(arrays), generator=generator)[: min(shapes, len(arrays))]
    sample_index = torch.randint(arrays.rows("sdf_values"), (len(shape_index), samples), generator=generator)
    shape_index, sample_index = shape_index[rank::world], sample_index[rank::world]
    points = arrays.take("sdf_points", shape_index, sample_index)
    values = arrays.take("sdf_values", shape_index, sample_index).float() / normalization.scale
    return ShapeSDFBatch(shape_index, _to_unit(points, normalization), values)


def auto_decoder_terms(model: nn.Module, batch: ShapeSDFBatch, weights: Mapping[str, float],
                       clamp: float) -> dict[str, Tensor]:
    """Unweighted terms of an auto-decoder on `batch`: `sdf` (clamped L1), `code` (mean ||z||^2)."""
    codes = model.codes(batch.shape_index)
    terms: dict[str, Tensor] = {}
    if weights.get("sdf"):
        pred = model.decoder(batch.points, codes[:, None, :].expand(*batch.points.shape[:-1], codes.shape[-1]))
        terms["sdf"] = clamped_l1(pred.reshape(-1), batch.sdf.reshape(-1), clamp)
    if weights.get("code"):
        terms["code"] = codes.square().sum(-1).mean()
    return terms


def _on(batch, device: torch.device):
    """A batch dataclass with every tensor on `device`."""
    return type(batch)(**{f.name: getattr(batch, f.name).to(device) for f in fields(batch)})


@dataclass(frozen=True)
class CollectionSDFSampler(Sampler):
    arrays: SplitArrays
    """The split's caches, read a step's shapes at a time."""
    normalization: Normalization
    device: torch.device
    weights: dict[str, float]
    shapes_per_batch: int
    """Over all processes."""
    samples_per_shape: int
    clamp: float
    rank: int = 0
    world: int = 1

    def sample(self, generator: torch.Generator) -> ShapeSDFBatch:
        batch = draw_shape_sdf(self.arrays, self.normalization, self.shapes_per_batch, self.samples_per_shape,
                               generator, self.rank, self.world)
        return _on(batch, self.device)

    def losses(self, model: nn.Module, batch: ShapeSDFBatch) -> dict[str, Tensor]:
        codes = getattr(model, "codes", None)
        if codes is None or len(codes) != len(self.arrays):
            raise ConfigError(f"CollectionSDF trains an AutoDecoder with one code per shape ({len(self.arrays)}); "
                              f"got a {type(model).__name__} with {len(codes) if codes is not None else 'no'} codes")
        return auto_decoder_terms(model, batch, self.weights, self.clamp)


@dataclass(frozen=True)
class CollectionSDF(Observation):
    """The SDF samples of a collection split, one latent code per shape (DeepSDF's training data),
    read from the shapes' caches a step's shapes at a time."""

    root: str | Path
    """Folder built by `python -m neuralsurf.priors build`."""
    split: str = "train"
    weights: Mapping[str, float] = field(default_factory=lambda: {"sdf": 1.0, "code": 1e-4})
    """Term weights: sdf (clamped L1), code (DeepSDF's code regularisation, 1e-4 there)."""
    shapes_per_batch: int = 16
    """Shapes per step, over all processes under torchrun (DeepSDF: 64 scenes)."""
    samples_per_shape: int = 2048
    """SDF samples per shape per step (DeepSDF: 16384)."""
    clamp: float = 0.1
    """DeepSDF's delta, unit frame."""
    name: str = "shapes"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, COLLECTION_SDF_TERMS, "CollectionSDF"))
        if min(self.shapes_per_batch, self.samples_per_shape) < 1 or not self.clamp > 0:
            raise ConfigError(f"CollectionSDF needs shapes_per_batch, samples_per_shape >= 1 and clamp > 0, got "
                              f"{self.shapes_per_batch}, {self.samples_per_shape}, {self.clamp}")

    @classmethod
    def from_collection(cls, collection, **options) -> CollectionSDF:
        """The training split of a built `ShapeCollection`, with these options."""
        return cls(collection.folder, **options)

    @property
    def paths(self) -> list[Path]:
        """The caches in latent-code order: row i of the codes is shape `paths[i]`."""
        return split_paths(self.root, self.split)

    def bounds(self) -> Tensor:
        return UNIT_BOUNDS.clone()

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> CollectionSDFSampler:
        arrays = SplitArrays(self.paths, ("sdf_points", "sdf_values"))
        rank, world = rank_and_world()
        shapes = global_shapes(self.shapes_per_batch, len(arrays), world, "CollectionSDF")
        return CollectionSDFSampler(arrays, normalization, device, self.weights, shapes, self.samples_per_shape,
                                    self.clamp, rank, world)


# ----------------------------------------------------------------------------- occupancy network

OCCUPANCY_TERMS = ("occupancy",)


@dataclass(frozen=True)
class OccupancyBatch:
    """Input clouds and labelled query points of a few shapes (unit frame)."""

    clouds: Tensor
    """Float[Tensor, "b n 3"]: noisy surface points, the encoder's input."""
    points: Tensor
    """Float[Tensor, "b t 3"]: query points."""
    inside: Tensor
    """Float[Tensor, "b t"]: 1 inside, 0 outside."""


def facing_mask(normals: Tensor, directions: Tensor) -> Tensor:
    """Bool[Tensor, "b m"]: points whose normal faces the row's view direction (n . d < 0): one side of
    each shape, as a camera would see it without self-occlusion. normals: [b, m, 3]; directions: [b, 3]."""
    return (normals * directions.to(normals)[:, None, :]).sum(-1) < 0


def iter_view_clouds(meshes: Iterable[Mesh], views: int, points_per_view: int, seed: int) -> Iterator[Tensor]:
    """`view_clouds` one shape at a time: Float[Tensor, "views points_per_view 3"] per mesh."""
    generator = torch.Generator().manual_seed(seed)
    for i, mesh in enumerate(meshes):
        # camera seeds from 10^6 up: the shapes_one_view scene's cameras take seeds 0, 1, ...
        poses = torch.stack([one_view_camera(1_000_000 * (seed + 1) + views * i + v) for v in range(views)])
        frames = scan_depth(mesh, cam_to_world=poses, **ONE_VIEW_IMAGE)
        points = backproject_depth(frames)
        clouds = torch.empty(views, points_per_view, 3)
        for v in range(views):
            seen = points[v][frames.depth[v] > 0]
            if not len(seen):
                raise InputError(f"shape {i} of the collection is not seen from view {v} (camera {poses[v].tolist()})")
            clouds[v] = seen[torch.randint(len(seen), (points_per_view,), generator=generator)].float()
        yield clouds


def view_clouds(meshes: list, views: int, points_per_view: int, seed: int) -> Tensor:
    """Float[Tensor, "S views points_per_view 3"]: back-projected points of `views` synthetic depth
    views of each mesh (unit frame), cameras and images as the `shapes_one_view` scene's
    (`scenes.scanner.one_view_camera`, `ONE_VIEW_IMAGE`): one-sided clouds with self-occlusion, as one
    depth view sees a shape. Each view's points are drawn at random (with repeats when fewer)."""
    return torch.stack(list(iter_view_clouds(meshes, views, points_per_view, seed)))


def cached_meshes(paths: Iterable[Path]) -> Iterator[Mesh]:
    """The ground-truth mesh of each cache, read one at a time (the two mesh arrays alone)."""
    for path in paths:
        with np.load(path, allow_pickle=False) as data:
            yield Mesh(torch.from_numpy(data["mesh_vertices"]).double(), torch.from_numpy(data["mesh_faces"]))


def write_view_clouds(path: Path, paths: list[Path], views: int, points_per_view: int, seed: int) -> Path:
    """`view_clouds` of the caches `paths` written to the .npy file `path` one shape at a time (memory of
    one shape's views), atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float32)), "fortran_order": False,
              "shape": (len(paths), views, points_per_view, 3)}
    try:
        with open(temporary, "wb") as file:
            np.lib.format.write_array_header_1_0(file, header)
            clouds = iter_view_clouds(cached_meshes(paths), views, points_per_view, seed)
            file.writelines(shape.numpy().astype(np.float32).tobytes() for shape in clouds)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def occupancy_pool(arrays: SplitArrays, shapes: Tensor, query: Tensor, n_near: int) -> tuple[Tensor, Tensor]:
    """Rows `query` (Int[Tensor, "b t"]) of each shape's pool of labelled points: its first n - n_near
    uniform occupancy points, then its first `n_near` near-surface ones (n: uniform points a cache).
    Returns points Float[Tensor, "b t 3"] and inside Bool[Tensor, "b t"]."""
    if not n_near:
        return arrays.take("occ_uniform_points", shapes, query), arrays.take("occ_uniform_inside", shapes, query)
    n_uniform = arrays.rows("occ_uniform_points") - n_near
    near = query >= n_uniform
    uniform_rows, near_rows = torch.where(near, 0, query), torch.where(near, query - n_uniform, 0)
    points = torch.where(near[..., None], arrays.take("occ_near_points", shapes, near_rows),
                         arrays.take("occ_uniform_points", shapes, uniform_rows))
    inside = torch.where(near, arrays.take("occ_near_inside", shapes, near_rows),
                         arrays.take("occ_uniform_inside", shapes, uniform_rows))
    return points, inside


def draw_occupancy(arrays: SplitArrays, normalization: Normalization, shapes: int, cloud_points: int,
                   cloud_noise: float, partial: float, query_points: int, n_near: int,
                   generator: torch.Generator, views: ArraySpan | None = None, rank: int = 0,
                   world: int = 1) -> OccupancyBatch:
    """Shapes at random; for each, a cloud of `cloud_points` surface samples plus N(0, cloud_noise^2)
    (unit frame) and `query_points` labelled points (`occupancy_pool`), in the unit frame of
    `normalization`. A `partial` share of clouds is one-sided: drawn from one of the shape's `views`
    (Float[S, V, p, 3], `write_view_clouds`) when given, else the surface samples facing a random
    direction (`facing_mask`). Every rank draws the same global batch and reads its rows `rank::world`
    alone (the other rows' one-sided masks are left all true: each row's multinomial draw takes its
    own stretch of the generator, whatever the other rows' weights)."""
    mine = slice(rank, None, world)
    shape_index = torch.randperm(len(arrays), generator=generator)[: min(shapes, len(arrays))]
    own, b = shape_index[mine], len(shape_index)
    candidates = torch.randint(arrays.rows("surface_points"), (b, 4 * cloud_points), generator=generator)
    keep = torch.ones(b, 4 * cloud_points, dtype=torch.bool)
    one_sided = torch.rand(b, generator=generator) < partial
    if views is None and one_sided.any():
        directions = torch.nn.functional.normalize(torch.randn(b, 3, generator=generator), dim=-1)
        facing = facing_mask(arrays.take("surface_normals", own, candidates[mine]), directions[mine])
        keep[mine] = torch.where(one_sided[mine, None] & facing.any(1, keepdim=True), facing, keep[mine])
    pick = torch.multinomial(keep.double(), cloud_points, replacement=True, generator=generator)
    cloud = arrays.take("surface_points", own, candidates.gather(1, pick)[mine])
    if views is not None and one_sided.any():
        view = torch.randint(views.shape[1], (b, 1), generator=generator)[mine]
        seen = torch.randint(views.shape[2], (b, cloud_points), generator=generator)[mine]
        from_view = torch.from_numpy(views.rows((own[:, None].numpy(), view.numpy(), seen.numpy())))
        cloud = torch.where(one_sided[mine, None, None], from_view, cloud)
    noise = cloud_noise * torch.randn(b, cloud_points, 3, generator=generator)
    query = torch.randint(arrays.rows("occ_uniform_points"), (b, query_points), generator=generator)[mine]
    points, inside = occupancy_pool(arrays, own, query, n_near)
    return OccupancyBatch(_to_unit(cloud, normalization) + noise[mine], _to_unit(points, normalization),
                          inside.float())


@dataclass(frozen=True)
class CollectionOccupancySampler(Sampler):
    arrays: SplitArrays
    """The split's caches, read a step's shapes at a time."""
    normalization: Normalization
    device: torch.device
    weights: dict[str, float]
    shapes_per_batch: int
    cloud_points: int
    cloud_noise: float
    """Unit frame."""
    partial: float
    query_points: int
    n_near: int
    """Near-surface points in each shape's pool of query points (`occupancy_pool`)."""
    views: ArraySpan | None = None
    rank: int = 0
    world: int = 1

    def sample(self, generator: torch.Generator) -> OccupancyBatch:
        batch = draw_occupancy(self.arrays, self.normalization, self.shapes_per_batch, self.cloud_points,
                               self.cloud_noise, self.partial, self.query_points, self.n_near, generator, self.views,
                               self.rank, self.world)
        return _on(batch, self.device)

    def losses(self, model: nn.Module, batch: OccupancyBatch) -> dict[str, Tensor]:
        logits = model.logits(batch.points, model.encode(batch.clouds))
        return {"occupancy": nn.functional.binary_cross_entropy_with_logits(logits, batch.inside)}


@dataclass(frozen=True)
class CollectionOccupancy(Observation):
    """Occupancy labels of a collection split, with input clouds from each shape's surface
    (the training data of an Occupancy Network), read from the shapes' caches a step's shapes at a time."""

    root: str | Path
    """Folder built by `python -m neuralsurf.priors build`."""
    split: str = "train"
    weights: Mapping[str, float] = field(default_factory=lambda: {"occupancy": 1.0})
    shapes_per_batch: int = 32
    """Shapes per step, over all processes under torchrun (OccNet: 64)."""
    query_points: int = 2048
    """Labelled points per shape per step (OccNet: 2048)."""
    cloud_points: int = 300
    """Input points per cloud (OccNet: 300)."""
    cloud_noise: float = 0.005
    """Gaussian noise of the input points, unit frame (OccNet's configs: 0.005)."""
    partial: float = 0.0
    """Share of input clouds seen from one side only (for completion from one view)."""
    partial_views: int = 0
    """One-sided clouds come from this many synthetic depth views of each shape (`view_clouds`, with
    self-occlusion, rendered once into `<root>/views/` and reused); 0: the surface samples facing a
    random direction."""
    near_fraction: float = 0.0
    """Share of query points drawn from the near-surface pool (the rest: uniform in the box). Uniform
    only, as in the paper: test IoU 0.728 against 0.692 with half near (shapes_onet, 5,000 steps)."""
    name: str = "occupancy"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, OCCUPANCY_TERMS, "CollectionOccupancy"))
        counts = (self.shapes_per_batch, self.query_points, self.cloud_points)
        shares = 0 <= self.partial <= 1 and 0 <= self.near_fraction <= 1
        if min(counts) < 1 or self.partial_views < 0 or not shares or self.cloud_noise < 0:
            raise ConfigError(f"CollectionOccupancy needs shapes_per_batch, query_points, cloud_points >= 1, "
                              f"partial_views >= 0, partial and near_fraction in [0, 1] and cloud_noise >= 0, "
                              f"got {self}")

    @classmethod
    def from_collection(cls, collection, **options) -> CollectionOccupancy:
        """The training split of a built `ShapeCollection`, with these options."""
        return cls(collection.folder, **options)

    def bounds(self) -> Tensor:
        return UNIT_BOUNDS.clone()

    def prepare(self, normalization: Normalization, box: float, device: torch.device,
                seed: int) -> CollectionOccupancySampler:
        paths = split_paths(self.root, self.split)
        keys = ("surface_points", "surface_normals", "occ_uniform_points", "occ_uniform_inside", "occ_near_points",
                "occ_near_inside")
        arrays = SplitArrays(paths, keys)
        rank, world = rank_and_world()
        shapes = global_shapes(self.shapes_per_batch, len(arrays), world, "CollectionOccupancy")
        n_near = round(arrays.rows("occ_uniform_points") * self.near_fraction)
        return CollectionOccupancySampler(arrays, normalization, device, self.weights, shapes, self.cloud_points,
                                          self.cloud_noise / normalization.scale, self.partial, self.query_points,
                                          n_near, self._views(paths, seed), rank, world)

    def _views(self, paths: list[Path], seed: int) -> ArraySpan | None:
        """Where the `view_clouds` of every shape (4 x cloud_points points a view, the collection's frame)
        lie on disk, or None. Rendered once per caches, views and seed into `<root>/views/<split>-<hash>.npy`
        (under a lock: the ranks of a run and the jobs of a sweep render it once) and reused."""
        if not (self.partial_views and self.partial):
            return None
        points = 4 * self.cloud_points
        sources = [(p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in paths]
        digest = hashlib.sha256(json.dumps([sources, self.partial_views, points, seed]).encode()).hexdigest()[:16]
        path = Path(self.root) / "views" / f"{self.split}-{digest}.npy"
        with file_lock(path.with_suffix(".lock")):
            if not path.is_file():
                write_view_clouds(path, paths, self.partial_views, points, seed)
        return npy_span(path)


# ----------------------------------------------------------------------------- one shape

SDF_SAMPLE_TERMS = ("sdf",)


@dataclass(frozen=True)
class SDFSampleBatch:
    """Points with known signed distances (unit frame)."""

    points: Tensor
    """Float[Tensor, "n 3"]."""
    sdf: Tensor
    """Float[Tensor, "n"]."""


@dataclass(frozen=True)
class SDFSampleSampler(Sampler):
    points: Tensor
    values: Tensor
    weights: dict[str, float]
    batch_size: int
    clamp: float

    def sample(self, generator: torch.Generator) -> SDFSampleBatch:
        index = torch.randint(len(self.values), (self.batch_size,), generator=generator).to(self.values.device)
        return SDFSampleBatch(self.points[index], self.values[index])

    def losses(self, model: nn.Module, batch: SDFSampleBatch) -> dict[str, Tensor]:
        return {"sdf": clamped_l1(model(batch.points), batch.sdf, self.clamp)}


@dataclass(frozen=True)
class SDFSampleSet(Observation):
    """Points of one shape with their signed distances (world frame), fitted by clamped L1."""

    points: Tensor
    """Float[Tensor, "n 3"]."""
    sdf: Tensor
    """Float[Tensor, "n"]: signed distances, negative inside."""
    weights: Mapping[str, float] = field(default_factory=lambda: {"sdf": 1.0})
    batch_size: int = 8192
    clamp: float = 0.1
    """DeepSDF's delta, unit frame."""
    name: str = "sdf_samples"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, SDF_SAMPLE_TERMS, "SDFSampleSet"))
        points, sdf = torch.as_tensor(self.points), torch.as_tensor(self.sdf)
        if points.ndim != 2 or points.shape[1] != 3 or sdf.shape != points.shape[:1] or not len(sdf):
            raise InputError(f"SDFSampleSet needs points (n, 3) and sdf (n,) with n >= 1, got "
                             f"{tuple(points.shape)} and {tuple(sdf.shape)}")
        if not (torch.isfinite(points).all() and torch.isfinite(sdf).all()):
            raise InputError("SDFSampleSet: points or sdf hold NaN or inf; drop those samples")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "sdf", sdf)

    @classmethod
    def from_cache(cls, path: str | Path, **options) -> SDFSampleSet:
        """The SDF samples of one cached shape (`neuralsurf.priors.cache` npz)."""
        arrays = load_cache(path)
        return cls(torch.from_numpy(arrays["sdf_points"]), torch.from_numpy(arrays["sdf_values"]), **options)

    def bounds(self) -> Tensor:
        points = self.points.double()
        return torch.stack([points.min(0).values, points.max(0).values])

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> SDFSampleSampler:
        points = normalization.to_unit(self.points.double()).float().to(device)
        values = (self.sdf.double() / normalization.scale).float().to(device)
        return SDFSampleSampler(points, values, self.weights, self.batch_size, self.clamp)


@dataclass(frozen=True)
class NoBatch:
    """The latent prior draws nothing."""


@dataclass(frozen=True)
class LatentPriorSampler(Sampler):
    weights: dict[str, float]

    def sample(self, generator: torch.Generator) -> NoBatch:
        return NoBatch()

    def losses(self, model: nn.Module, batch: NoBatch) -> dict[str, Tensor]:
        code = getattr(model, "code", None)
        if not isinstance(code, Tensor):
            raise ConfigError(f"LatentPrior regularises the code of a LatentConditioned model, got a "
                              f"{type(model).__name__} without one")
        return {"code": code.square().sum()}


@dataclass(frozen=True)
class LatentPrior(Observation):
    """DeepSDF's prior on a reconstructed shape's code: ||z||^2 (a zero-mean Gaussian, up to the weight).
    It observes no data: its bounds are the prior's unit cube."""

    weights: Mapping[str, float] = field(default_factory=lambda: {"code": 1e-4})
    name: str = "prior"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, ("code",), "LatentPrior"))

    def bounds(self) -> Tensor:
        return UNIT_BOUNDS.clone()

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> LatentPriorSampler:
        return LatentPriorSampler(self.weights)
