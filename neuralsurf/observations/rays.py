"""Depth rays: every valid pixel of depth images is a ray from its camera to the surface it saw.

Per step, a batch of rays with samples along each (iSDF, Ortiz et al. 2022; Azinovic et al. 2022):
- `surface`: f = 0 at the measured hit;
- `band`: in a truncation band around the hit, f equals the signed distance to the hit along the
  ray, projected on the normal of the depth map there (exact for a plane), weighted by the inverse
  of the sensor noise sigma at that depth;
- `free`: stratified between the box and the band, where the ray saw free space: 0 <= f <= the
  distance to the hit along the ray (the hit is a surface point, so it bounds the distance);
- `carve`: on uniform points of the box labelled by all views at once (space carving): a point in
  front of a reading in some view is free (f >= 0); a point behind the readings of every view that
  sees it (at least two, no missing pixel among them) is inside (f <= 0); others are unknown.
  Without it the field is free inside the object and in corners no ray crosses, and grows pockets;
- `normal`: grad f at the hit along the depth map's normal there (1 - cos), weighted by the normal's
  confidence (depth noise against pixel spacing: finite differences of far Kinect depth are noise);
- `eikonal`: |grad f| = 1 on every sample and on the uniform points.
Missing pixels (depth 0) are skipped, never fitted as surface.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import _depth_normals, backproject_depth_to_camera, kinect_sigma
from neuralsurf.losses import eikonal_loss
from neuralsurf.observations.base import NotObserved, Observation, Sampler, check_weights
from neuralsurf.structures import DepthFrames, Normalization

RAY_TERMS = ("surface", "band", "free", "carve", "normal", "eikonal")
DEFAULT_RAY_WEIGHTS = {"surface": 3.0, "band": 1.0, "free": 100.0, "carve": 1.0, "normal": 0.5, "eikonal": 0.03}


@dataclass(frozen=True)
class Rays:
    """Rays of valid pixels in one frame of reference (world or unit)."""

    origins: Tensor
    """Float[Tensor, "r 3"]: camera centres."""
    directions: Tensor
    """Float[Tensor, "r 3"]: unit directions."""
    hit: Tensor
    """Float[Tensor, "r"]: distance along the ray to the measured surface."""
    sigma: Tensor
    """Float[Tensor, "r"]: sensor noise standard deviation along the ray at the hit."""
    cosine: Tensor
    """Float[Tensor, "r"]: |cos| between the ray and the depth map's normal at the hit (1 where unknown)."""
    normals: Tensor
    """Float[Tensor, "r 3"]: the depth map's normal at the hit, facing the camera, of length its confidence
    1 / (1 + (sigma / pixel spacing)^2)^2, pixel spacing = depth / fx (0 where unknown)."""


def depth_rays(frames: DepthFrames, sigma_of_depth=kinect_sigma, max_depth_jump: float = 0.05,
               chunk: int = 8) -> Rays:
    """World-frame rays of the valid pixels of `frames`, ordered by frame, row, column.

    The measured z-depth becomes a distance along the ray (z |d| for the camera-frame direction
    d = K^-1 (u, v, 1)); `sigma_of_depth` maps z-depth to the axial noise sigma (metres), scaled
    the same way. `chunk` frames are processed at once (bounds memory, same result). Raises
    InputError when no pixel is valid.
    """
    if not (frames.depth > 0).any():
        raise InputError(f"all {frames.depth.numel()} depth pixels of the {len(frames)} frames are missing (0); "
                         f"nothing to fit: check the depth scale (metres) and the invalid-value code")
    parts = []
    for start in range(0, len(frames), chunk):
        depth, K = frames.depth[start : start + chunk], frames.K[start : start + chunk]
        valid = depth > 0
        normals, has_normal = _depth_normals(backproject_depth_to_camera(depth, K), max_depth_jump)
        unit_depth = backproject_depth_to_camera(torch.ones_like(depth), K)  # camera-frame rays at z = 1
        length = unit_depth.norm(dim=-1)  # ray length per unit z-depth
        directions = unit_depth / length[..., None]
        cosine = torch.where(has_normal, (normals * directions).sum(-1).abs(), torch.ones_like(length))
        pose = frames.cam_to_world[start : start + chunk].to(depth)
        world = torch.einsum("nij,nhwj->nhwi", pose[:, :3, :3], directions)
        # a finite-difference normal is as good as the depth noise is small against the pixel spacing
        sigma, spacing = sigma_of_depth(depth), depth / K[:, 0, 0, None, None]
        confidence = has_normal / (1 + (sigma / spacing.clamp_min(1e-12)) ** 2) ** 2
        world_normals = torch.einsum("nij,nhwj->nhwi", pose[:, :3, :3], normals) * confidence[..., None]
        origins = pose[:, None, None, :3, 3].expand_as(world)
        parts.append(Rays(origins[valid], world[valid], (depth * length)[valid],
                          (sigma * length)[valid], cosine[valid], world_normals[valid]))
    return Rays(*(torch.cat([getattr(p, name) for p in parts]) for name in Rays.__dataclass_fields__))


def box_entry(origins: Tensor, directions: Tensor, box: float) -> Tensor:
    """Float[Tensor, "r"]: distance along each ray where it enters the cube [-box, box]^3 (0 when the
    origin lies inside; rays that miss the cube get their exit, which is smaller than their entry).
    origins, directions: Float[Tensor, "r 3"]."""
    inverse = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0, t1 = (-box - origins) * inverse, (box - origins) * inverse
    return torch.minimum(t0, t1).amax(-1).clamp_min(0.0)


def carve_labels(points: Tensor, frames: DepthFrames, band: float, sigma_of_depth=kinect_sigma,
                 bounds: Tensor | None = None, missing_fraction: float = 0.1) -> Tensor:
    """Space carving of world points by all depth frames at once.

    A view votes "free" where the point lies in front of its pixel's reading by more than the band
    (`band`, or 3 noise sigmas of the reading if larger), "behind" where it lies farther than the band
    behind it. "Inside" needs at least two "behind" votes, no vote within the band, and missing
    readings (dropouts, or background in the silhouette) in at most `missing_fraction` of the views
    the point projects into (on the 24 Kinect bunny views: 84 % of the interior labelled, none wrong;
    with no missing reading allowed, 43 %). Views whose image a point misses say nothing of it, so
    "inside" is also limited to `bounds` (the box of the observed surface).
    Args:
        points: Float[Tensor, "n 3"] world; frames: DepthFrames; band: metres;
        bounds: Float[Tensor, "2 3"] world box, or None for no limit.
    Returns:
        Int8[Tensor, "n"]: +1 free (some view saw through it), -1 inside, 0 unknown.
    """
    from neuralsurf.geometry import project_points

    free = torch.zeros(len(points), dtype=torch.bool)
    near = torch.zeros(len(points), dtype=torch.bool)
    behind, missing, seen_by = (torch.zeros(len(points), dtype=torch.int32) for _ in range(3))
    for depth, K, pose in zip(frames.depth.cpu(), frames.K.cpu(), frames.cam_to_world.cpu()):
        uv, z = project_points(points.double(), K.double(), pose.double())
        pixel = uv.round().long()
        seen = (z > 0) & (pixel[:, 0] >= 0) & (pixel[:, 0] < depth.shape[1]) & (pixel[:, 1] >= 0) & (
            pixel[:, 1] < depth.shape[0])
        reading = torch.zeros(len(points), dtype=torch.float64)
        reading[seen] = depth[pixel[seen, 1], pixel[seen, 0]].double()
        valid = seen & (reading > 0)
        margin = torch.clamp(3 * sigma_of_depth(reading), min=band)
        in_front, is_behind = valid & (z < reading - margin), valid & (z > reading + margin)
        free |= in_front
        near |= valid & ~in_front & ~is_behind
        behind += is_behind.int()
        missing += (seen & ~valid).int()
        seen_by += seen.int()
    inside = ~free & ~near & (behind >= 2) & (missing <= missing_fraction * seen_by)
    if bounds is not None:
        bounds = torch.as_tensor(bounds, dtype=torch.float64)
        inside &= ((points >= bounds[0]) & (points <= bounds[1])).all(-1)
    return torch.where(free, 1, torch.where(inside, -1, 0)).to(torch.int8)


@dataclass(frozen=True)
class RayBatch:
    """Rays drawn for one step, with the distances of their samples (unit frame)."""

    origins: Tensor
    """Float[Tensor, "r 3"]: camera centres."""
    directions: Tensor
    """Float[Tensor, "r 3"]: unit directions."""
    hit: Tensor
    """Float[Tensor, "r"]: measured distance to the surface along the ray."""
    sigma: Tensor
    """Float[Tensor, "r"]: sensor noise sigma along the ray."""
    cosine: Tensor
    """Float[Tensor, "r"]: |cos| between ray and surface normal (projects ray distances on the normal)."""
    normals: Tensor
    """Float[Tensor, "r 3"]: depth-map normal at the hit, of length its confidence (0 where unknown)."""
    free_t: Tensor
    """Float[Tensor, "r f"]: distances of free-space samples, between box entry and band."""
    free_valid: Tensor
    """Bool[Tensor, "r f"]: free samples that lie in front of the band (rays entering close to the hit have none)."""
    band_t: Tensor
    """Float[Tensor, "r b"]: distances of samples in the band [hit - band, hit + band]."""
    uniform: Tensor
    """Float[Tensor, "u 3"]: uniform points of the box (carve and eikonal terms)."""
    uniform_label: Tensor
    """Int8[Tensor, "u"]: their `carve_labels` (+1 free, -1 inside, 0 unknown)."""


def draw_rays(rays: Rays, entry: Tensor, n_rays: int, n_free: int, n_band: int, band: Tensor, n_uniform: int,
              carved: tuple[Tensor, Tensor], generator: torch.Generator) -> RayBatch:
    """`n_rays` rays at random with `n_free` stratified free samples in [entry, hit - band] and `n_band`
    uniform samples in [hit - band, hit + band] each, and `n_uniform` points of the `carved` pool
    (points Float[Tensor, "p 3"], labels Int8[Tensor, "p"]). Random numbers are drawn on the CPU with
    `generator` (a resumed fit draws the same batches) and moved to the rays' device.
    band: Float[Tensor, "r"], half-width of each ray's band."""
    device = rays.hit.device
    pick = torch.randint(len(rays.hit), (n_rays,), generator=generator).to(device)
    u_free = torch.rand(n_rays, n_free, generator=generator).to(device)
    u_band = torch.rand(n_rays, n_band, generator=generator).to(device)
    chosen = torch.randint(len(carved[0]), (n_uniform,), generator=generator).to(device)
    hit, half = rays.hit[pick], band[pick]
    start, stop = entry[pick], hit - half
    strata = (torch.arange(n_free, device=device) + u_free) / max(n_free, 1)
    free_t = start[:, None] + strata * (stop - start).clamp_min(0)[:, None]
    band_t = hit[:, None] + half[:, None] * (2 * u_band - 1)
    return RayBatch(rays.origins[pick], rays.directions[pick], hit, rays.sigma[pick], rays.cosine[pick],
                    rays.normals[pick], free_t,
                    (stop > start)[:, None].expand_as(free_t), band_t, carved[0][chosen], carved[1][chosen])


def ray_terms(model: nn.Module, batch: RayBatch, weights: Mapping[str, float]) -> dict[str, Tensor]:
    """Unweighted ray loss terms (surface, band, free, carve, normal, eikonal; those with a positive weight) of the
    unit-frame `model` on `batch`, from one forward pass over all samples."""
    r, f = batch.free_t.shape
    b = batch.band_t.shape[1]
    t = torch.cat([batch.hit[:, None], batch.band_t, batch.free_t], dim=1)  # (r, 1 + b + f)
    points = batch.origins[:, None] + t[..., None] * batch.directions[:, None]
    need_gradient = bool(weights.get("eikonal") or weights.get("normal"))
    points = torch.cat([points.reshape(-1, 3), batch.uniform]).requires_grad_(need_gradient)
    values = model(points)
    along = values[: r * (1 + b + f)].reshape(r, 1 + b + f)
    noise_weight = 1.0 / batch.sigma
    noise_weight = noise_weight / noise_weight.mean()
    terms: dict[str, Tensor] = {}
    if weights.get("surface"):
        terms["surface"] = (noise_weight * along[:, 0].abs()).mean()
    if weights.get("band"):
        target = (batch.hit[:, None] - batch.band_t) * batch.cosine[:, None]
        terms["band"] = (noise_weight[:, None] * (along[:, 1 : 1 + b] - target).abs()).mean()
    if weights.get("free") and f:
        bound = batch.hit[:, None] - batch.free_t
        free = along[:, 1 + b :]
        violation = torch.relu(free - bound) + torch.relu(-free)
        terms["free"] = (violation * batch.free_valid).sum() / batch.free_valid.sum().clamp_min(1)
    if weights.get("carve"):
        label = batch.uniform_label.to(values.dtype)
        violation = torch.relu(-label * values[r * (1 + b + f) :])
        terms["carve"] = violation.sum() / (label != 0).sum().clamp_min(1)
    if need_gradient:
        (gradient,) = torch.autograd.grad(values.sum(), points, create_graph=True)
    if weights.get("normal"):
        confidence = batch.normals.norm(dim=-1)
        at_hit = gradient[: r * (1 + b + f)].reshape(r, 1 + b + f, 3)[:, 0]
        cosine = torch.nn.functional.cosine_similarity(at_hit, batch.normals, dim=-1)
        terms["normal"] = (confidence * (1 - cosine)).mean()
    if weights.get("eikonal"):
        terms["eikonal"] = eikonal_loss(gradient)
    if not terms:
        raise ConfigError("every ray loss term is switched off; give a positive weight to surface, band, free, carve or normal")
    return terms


@dataclass(frozen=True)
class RaySampler(Sampler):
    rays: Rays
    entry: Tensor
    band: Tensor
    weights: dict[str, float]
    n_rays: int
    n_free: int
    n_band: int
    n_uniform: int
    carved: tuple[Tensor, Tensor]

    def sample(self, generator: torch.Generator) -> RayBatch:
        return draw_rays(self.rays, self.entry, self.n_rays, self.n_free, self.n_band, self.band, self.n_uniform,
                         self.carved, generator)

    def losses(self, model: nn.Module, batch: RayBatch) -> dict[str, Tensor]:
        return ray_terms(model, batch, self.weights)


@dataclass(frozen=True)
class DepthRays(Observation):
    """Depth images with cameras as ray supervision (surface, truncation band, free space, eikonal)."""

    frames: DepthFrames
    """Depth maps (metres, 0 = missing) with intrinsics and camera-to-world poses, world frame."""
    weights: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_RAY_WEIGHTS))
    """Term weights: surface, band, free, carve, normal, eikonal."""
    n_rays: int = 1024
    """Rays per step."""
    n_free: int = 6
    """Stratified free-space samples per ray."""
    n_band: int = 6
    """Samples per ray in the truncation band."""
    n_uniform: int = 1024
    """Uniform points of the box per step (carve and eikonal terms)."""
    n_carve: int = 200_000
    """Size of the pool of uniform points labelled by space carving (drawn once, seeded)."""
    truncation: float = 0.01
    """Half-width of the band around each hit, unit frame (at least 3 noise sigmas)."""
    max_rays: int = 4_000_000
    """Keep at most this many rays (a random subset, fixed by the seed) to bound memory."""
    noise_model: str = "kinect"
    """Noise sigma of a depth reading: "kinect" (Nguyen et al. 2012: 1.2 mm at 0.4 m, growing with
    the square of the depth) or "constant" (`sigma` metres)."""
    sigma: float = 0.001
    """Noise sigma of the "constant" model, metres."""
    name: str = "rays"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, RAY_TERMS, "DepthRays"))
        if not isinstance(self.frames, DepthFrames):
            raise InputError(f"DepthRays expects neuralsurf.DepthFrames, got {type(self.frames).__name__}")
        counts = {k: getattr(self, k) for k in ("n_rays", "n_free", "n_band", "n_uniform", "n_carve", "max_rays")}
        if any(not isinstance(v, int) or v < 0 for v in counts.values()) or not all(
                counts[k] for k in ("n_rays", "n_carve", "max_rays")):
            raise ConfigError(f"DepthRays needs integer sample counts (n_rays, n_carve, max_rays >= 1, others >= 0), "
                              f"got {counts}")
        if not self.truncation > 0 or self.noise_model not in ("kinect", "constant") or not self.sigma > 0:
            raise ConfigError(f"DepthRays needs truncation > 0, sigma > 0 and noise_model kinect or constant, got "
                              f"truncation={self.truncation}, noise_model={self.noise_model!r}, sigma={self.sigma}")

    @classmethod
    def from_scene(cls, scene, **options) -> DepthRays:
        """The scene's depth frames (a `neuralsurf.scenes.Scene`) with these options; NotObserved
        when the scene has none."""
        if scene.frames is None or not scene.depth_input:
            raise NotObserved(f"scene {scene.name!r} is not a depth capture (no depth frames as its input); "
                              f"fit it with PointSamples (observation=points)")
        return cls(scene.frames, **options)

    def _sigma_of_depth(self):
        return kinect_sigma if self.noise_model == "kinect" else (lambda z: torch.full_like(z, self.sigma))

    def _world_rays(self) -> Rays:
        return depth_rays(self.frames.to("cpu"), self._sigma_of_depth())

    def bounds(self) -> Tensor:
        rays = self._world_rays()
        points = (rays.origins + rays.hit[:, None] * rays.directions).double()
        return torch.stack([points.min(0).values, points.max(0).values])

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> RaySampler:
        rays = self._world_rays()
        if len(rays.hit) > self.max_rays:
            keep = torch.randperm(len(rays.hit), generator=torch.Generator().manual_seed(seed))[: self.max_rays]
            rays = Rays(*(getattr(rays, name)[keep.sort().values] for name in Rays.__dataclass_fields__))
        scale = normalization.scale
        unit = Rays(normalization.to_unit(rays.origins.double()).float(), rays.directions, rays.hit / scale,
                    rays.sigma / scale, rays.cosine.clamp_min(0.05), rays.normals)
        unit = Rays(*(getattr(unit, name).to(device) for name in Rays.__dataclass_fields__))
        entry = box_entry(unit.origins, unit.directions, box)
        band = torch.clamp(3 * unit.sigma, min=self.truncation)
        generator = torch.Generator().manual_seed(seed)
        pool = (2 * torch.rand(self.n_carve, 3, generator=generator, dtype=torch.float64) - 1) * box
        labels = carve_labels(normalization.to_world(pool), self.frames, self.truncation * scale, self._sigma_of_depth(),
                              self.bounds())
        carved = (pool.float().to(device), labels.to(device))
        return RaySampler(unit, entry, band, self.weights, self.n_rays, self.n_free, self.n_band, self.n_uniform, carved)
