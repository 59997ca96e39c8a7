"""Point samples: a point cloud (with or without normals) as surface, near-surface and free-space
samples with approximate signed distances (DeepSDF, IGR); the maths of `neuralsurf.sampling`."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import estimate_normals, opposed_share, orient_normals, project_to_quadrics
from neuralsurf.losses import clamped_l1, eikonal_loss, normal_loss, off_surface_loss, surface_loss
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.observations.base import Observation, Sampler, check_weights
from neuralsurf.observations.start import voxel_start
from neuralsurf.sampling import SDFBatch, SDFSamples, draw_batch, held_out_split, make_sdf_samples
from neuralsurf.strategies import choose, register
from neuralsurf.structures import Normalization, PointCloud

POINT_TERMS = ("surface", "sdf", "normal", "eikonal", "off_surface")
DEFAULT_POINT_WEIGHTS = {"surface": 3.0, "sdf": 1.0, "normal": 0.1, "eikonal": 0.1, "off_surface": 0.0}


def prepare_cloud(cloud: PointCloud, normals: str | Callable, normal_k: int, denoise: bool = False) -> PointCloud:
    """Check the input and supply its normals by the normal source `normals` (a name of the
    "normal source" family: "given", "estimate", "ignore", or a function of the same signature as
    `given_normals`), which is passed `normal_k` and `denoise`."""
    if not isinstance(cloud, PointCloud):
        raise InputError(f"PointSamples expects a neuralsurf.PointCloud, got {type(cloud).__name__}")
    if len(cloud) < 3:
        raise InputError(f"fitting needs at least 3 points, the cloud has {len(cloud)}")
    points = cloud.points.double()
    spread = torch.linalg.svdvals(points - points.mean(0))
    if spread[1] <= 1e-6 * max(float(spread[0]), 1e-300):
        raise InputError(
            f"the {len(cloud)} points are collinear (or all at one place): a surface cannot be fitted to them; "
            f"check the file or the scan"
        )
    return choose("normal source", normals)(cloud, normal_k, denoise)


@register("normal source", "given")
def given_normals(cloud: PointCloud, normal_k: int, denoise: bool) -> PointCloud:
    """The cloud's own normals, made unit length; InputError when it has none or some have zero length."""
    if cloud.normals is None:
        raise InputError("normals='given' but the cloud has no normals; use normals='estimate' or 'ignore'")
    zero = _zero_normals(cloud)
    if zero.any():
        raise InputError(
            f"{int(zero.sum())} of {len(cloud)} normals have zero length; use normals='estimate' to "
            f"replace them by estimated ones, or remove those points"
        )
    return cloud.with_normals(torch.nn.functional.normalize(cloud.normals, dim=-1))


@register("normal source", "estimate")
def estimated_normals(cloud: PointCloud, normal_k: int, denoise: bool) -> PointCloud:
    """The cloud's own normals where it has them (zero-length ones replaced by estimates oriented like
    their neighbours; unoriented ones given consistent signs: `consistent_normals`), else PCA estimates over
    `normal_k` neighbours oriented by an MST; with `denoise`, a cloud without normals is first projected onto its
    local quadrics (`geometry.project_to_quadrics`, the same k): unoriented scans are the noisy ones."""
    if cloud.normals is not None:
        zero = _zero_normals(cloud)
        if not zero.any():
            return cloud.with_normals(consistent_normals(cloud.points, torch.nn.functional.normalize(cloud.normals,
                                                                                                    dim=-1), normal_k))
        warnings.warn(f"{int(zero.sum())} of {len(cloud)} normals have zero length: replaced by estimated "
                      f"normals oriented like their neighbours", stacklevel=4)
        given = torch.nn.functional.normalize(cloud.normals, dim=-1)
        estimated = orient_normals(cloud.points, estimate_normals(cloud.points, normal_k), normal_k).to(given)
        if (estimated * given)[~zero].sum() < 0:  # orient them like the given normals overall
            estimated = -estimated
        return cloud.with_normals(torch.where(zero[:, None], estimated, given))
    estimated = estimate_normals(cloud.points, normal_k)
    if denoise and len(cloud) >= 6:  # a quadric has 6 unknowns
        k = min(max(normal_k, 6), len(cloud))
        cloud = PointCloud(project_to_quadrics(cloud.points, estimated, k), colors=cloud.colors)
        estimated = estimate_normals(cloud.points, normal_k)
    return cloud.with_normals(orient_normals(cloud.points, estimated, normal_k))


UNORIENTED = 0.02
"""Given normals count as unoriented where this share of the points or more point against most of their neighbours'
(`geometry.opposed_share`)."""


def consistent_normals(points: Tensor, normals: Tensor, k: int) -> Tensor:
    """Float[Tensor, "n 3"] unit `normals` of Float[Tensor, "n 3"] `points`, their signs made consistent along a
    spanning tree of `k` neighbours (`geometry.orient_normals`: outward for one closed surface; the other way where
    clearly most of the given signs say so) if they are unoriented (`UNORIENTED`), with a warning; else as given."""
    share = opposed_share(points, normals)
    if share < UNORIENTED:
        return normals
    oriented = orient_normals(points, normals, k).to(normals)
    if ((oriented * normals).sum(-1) > 0).double().mean() < 0.4:
        oriented = -oriented
    warnings.warn(f"{share:.0%} of the points' normals point against most of their neighbours': the normals look "
                  f"unoriented, so their signs were made consistent (normals='given' fits them as they are)",
                  stacklevel=5)
    return oriented


@register("normal source", "ignore")
def no_normals(cloud: PointCloud, normal_k: int, denoise: bool) -> PointCloud:
    """The cloud without normals: fit with the surface, eikonal and off-surface terms."""
    return cloud.with_normals(None)


def _zero_normals(cloud: PointCloud) -> Tensor:
    """Bool[Tensor, "n"]: the zero-length normals of a cloud with normals; InputError when all are."""
    zero = cloud.normals.norm(dim=-1) < 1e-12
    if zero.all():
        raise InputError(
            f"all {len(cloud)} normals of the cloud have zero length; drop them (cloud.with_normals(None)) "
            f"or use normals='ignore' or 'estimate' on a cloud without normals"
        )
    return zero


@dataclass(frozen=True)
class SDFOutputs:
    """The model evaluated on a point batch (unit frame)."""

    surface: Tensor
    """Float[Tensor, "n"]: f at surface points."""
    near: Tensor
    """Float[Tensor, "m"]: f at near-surface points."""
    free: Tensor
    """Float[Tensor, "k"]: f at free-space points."""
    surface_gradient: Tensor
    """Float[Tensor, "n 3"]: grad f at surface points."""
    gradient: Tensor
    """Float[Tensor, "n+m+k 3"] or Float[Tensor, "n+k 3"]: grad f at every point, or at the surface and
    free points only (`evaluate_sdf_batch(..., near_gradient=False)`)."""


def evaluate_sdf_batch(model: nn.Module, batch: SDFBatch, near_gradient: bool = True) -> SDFOutputs:
    """The model on all samples of `batch`, with grad f kept for the loss at every point, or (without
    `near_gradient`) at the surface and free points, the near ones evaluated in a second, first-order
    pass: the eikonal term's double backward is the dearest part of a step."""
    with_gradient = [batch.surface_points] + ([batch.near_points] if near_gradient else []) + [batch.free_points]
    points = torch.cat(with_gradient).requires_grad_(True)
    values = model(points)
    (gradient,) = torch.autograd.grad(values.sum(), points, create_graph=True)
    n, m = len(batch.surface_points), len(batch.near_points) if near_gradient else 0
    near = values[n : n + m] if near_gradient else model(batch.near_points)
    return SDFOutputs(values[:n], near, values[n + m :], gradient[:n], gradient)


def point_terms(outputs: SDFOutputs, batch: SDFBatch, weights: Mapping[str, float], clamp: float = 0.1,
                off_surface_alpha: float = 100.0) -> dict[str, Tensor]:
    """Unweighted loss terms whose weight is positive and whose data is there (normals), in
    POINT_TERMS order: surface |f|, clamped-L1 `sdf`, `normal` 1 - cos, `eikonal`, `off_surface`."""
    terms: dict[str, Tensor] = {}
    if weights.get("surface"):
        terms["surface"] = surface_loss(outputs.surface)
    if weights.get("sdf") and batch.near_sdf is not None:
        pred = torch.cat([outputs.near, outputs.free])
        target = torch.cat([batch.near_sdf, batch.free_sdf])
        terms["sdf"] = clamped_l1(pred, target, clamp)
    if weights.get("normal") and batch.surface_normals is not None:
        terms["normal"] = normal_loss(outputs.surface_gradient, batch.surface_normals)
    if weights.get("eikonal"):
        terms["eikonal"] = eikonal_loss(outputs.gradient)
    if weights.get("off_surface"):
        terms["off_surface"] = off_surface_loss(outputs.free, off_surface_alpha)
    if not terms:
        raise ConfigError("every point loss term is switched off or lacks its data (normals); "
                          "give a positive weight to surface, eikonal or off_surface")
    return terms


START_SPACINGS = 1.0
"""The start's cells are at least this many point spacings wide (`observations.start.cells_for_spacing`): clouds
sparser than the bunny's 100k points get a coarser start."""


@dataclass(frozen=True)
class PointSampler(Sampler):
    samples: SDFSamples
    weights: dict[str, float]
    batch_size: int
    free_fraction: float
    clamp: float
    off_surface_alpha: float
    near_gradient: bool
    held_out: Tensor | None = None
    """Float[Tensor, "h 3"]: cloud points kept out of the pools (unit frame), or None."""
    seed: int = 0

    def start_field(self, resolution: int, box: float) -> VoxelSDF | None:
        if self.samples.surface_normals is None:
            return None
        return voxel_start(self.samples.surface_points, self.samples.surface_normals, box, resolution, seed=self.seed,
                           spacings_per_cell=START_SPACINGS, held_out=self.held_out)

    @torch.no_grad()
    def held_out_error(self, model: nn.Module) -> float | None:
        """Mean |f| at the held-out points: their distance to the zero level (unit frame)."""
        if self.held_out is None:
            return None
        return float(torch.cat([model(part).abs() for part in self.held_out.split(65_536)]).mean())

    def sample(self, generator: torch.Generator) -> SDFBatch:
        return draw_batch(self.samples, self.batch_size, self.free_fraction, generator)

    def losses(self, model: nn.Module, batch: SDFBatch) -> dict[str, Tensor]:
        outputs = evaluate_sdf_batch(model, batch, self.near_gradient)
        return point_terms(outputs, batch, self.weights, self.clamp, self.off_surface_alpha)


@dataclass(frozen=True)
class PointSamples(Observation):
    """A point cloud as SDF supervision (surface, normals, near and free samples, eikonal)."""

    cloud: PointCloud
    """The input cloud, world frame, with or without normals."""
    weights: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_POINT_WEIGHTS))
    """Term weights: surface, sdf (clamped L1 of near and free samples), normal, eikonal, off_surface."""
    normals: str | Callable = "estimate"
    """The normal source (`prepare_cloud`): "given" (must be there), "estimate" (PCA + MST orientation
    when absent), "ignore"."""
    normal_k: int = 30
    """Neighbours for normal estimation."""
    denoise: bool = True
    """Project a cloud without normals onto its local quadrics before fitting (see `prepare_cloud`)."""
    batch_size: int = 8192
    """Surface and near-surface samples per step (each)."""
    free_fraction: float = 0.25
    """Free-space samples per step, as a fraction of `batch_size`."""
    n_near: int = 1_000_000
    """Size of the near-surface pool (see `make_sdf_samples`)."""
    n_free: int = 250_000
    """Size of the free-space pool."""
    near_sigmas: tuple[float, ...] = (0.0025, 0.025)
    """Gaussian offsets of near samples, unit frame."""
    winding_points: int = 5000
    """Free-space signs from the winding number of this many points (0: nearest normal)."""
    clamp: float = 0.1
    """DeepSDF's clamp distance of the sdf term, unit frame."""
    off_surface_alpha: float = 100.0
    """exp(-alpha |f|) of the off_surface term."""
    near_gradient: bool = True
    """The eikonal term at near samples too; False: at surface and free samples only, the near ones
    pinned by the sdf term alone (20 % less time a step; bunny_sdf 400 steps: exact Chamfer-L1 8.48e-5
    against 8.36e-5)."""
    held_out: float = 0.0
    """Share of the cloud's points kept out of the pools: `fit` stops when the field's distance to them stops
    falling (its `patience`)."""
    name: str = "points"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, POINT_TERMS, "PointSamples"))
        object.__setattr__(self, "near_sigmas", tuple(self.near_sigmas))
        if not (isinstance(self.batch_size, int) and self.batch_size >= 1 and 0 <= self.free_fraction):
            raise ConfigError(f"PointSamples needs an integer batch_size >= 1 and free_fraction >= 0, got "
                              f"batch_size={self.batch_size!r}, free_fraction={self.free_fraction!r}")
        if not isinstance(self.cloud, PointCloud):
            raise InputError(f"PointSamples expects a neuralsurf.PointCloud, got {type(self.cloud).__name__}")
        if not 0 <= self.held_out < 0.5:
            raise ConfigError(f"PointSamples.held_out is a share of the points in [0, 0.5), got {self.held_out!r}")

    @classmethod
    def from_scene(cls, scene, **options) -> PointSamples:
        """The scene's point cloud (a `neuralsurf.scenes.Scene`) with these options."""
        return cls(scene.cloud, **options)

    def bounds(self) -> Tensor:
        points = self.cloud.points.double()
        return torch.stack([points.min(0).values, points.max(0).values])

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> PointSampler:
        cloud = normalization.cloud_to_unit(prepare_cloud(self.cloud, self.normals, self.normal_k, self.denoise))
        held_out = None
        if self.held_out > 0:
            held, kept = held_out_split(len(cloud), self.held_out, seed)
            held_out = cloud.points[held].float().to(device)
            cloud = PointCloud(cloud.points[kept], None if cloud.normals is None else cloud.normals[kept])
        samples = make_sdf_samples(cloud, n_near=self.n_near, n_free=self.n_free, near_sigmas=self.near_sigmas,
                                   box=box, winding_points=self.winding_points, seed=seed, device=device)
        return PointSampler(samples, self.weights, self.batch_size, self.free_fraction, self.clamp,
                            self.off_surface_alpha, self.near_gradient, held_out, seed)
