"""Depth rays: every valid pixel of depth images is a ray from its camera to the surface it saw.

Per step, a batch of rays with samples along each (iSDF, Ortiz et al. 2022; Azinovic et al. 2022), and more
hits alone (`hit_fraction`):
- `surface`: f = 0 at the measured hit;
- `band`: in a truncation band around the hit, f equals the signed distance to the hit along the
  ray, projected on the normal of the depth map there (exact for a plane), weighted by the inverse
  of the sensor noise sigma at that depth;
- `free`: stratified between the box and the band, where the ray saw free space: 0 <= f <= the
  distance to the hit along the ray (the hit is a surface point, so it bounds the distance);
- `carve`: on uniform points of the box labelled by all views at once (space carving): a point in
  front of a reading in some view is free (f >= 0); a point behind the readings of every view that
  sees it (at least two, no missing pixel among them) is inside (f <= 0); what carving leaves unknown takes
  its side from the winding number of the hits (`winding_labels`). A labelled point must lie on its side by
  its distance to the nearest hit (`carve_margin`), not by any small amount. Without this term the field is
  free inside the object and in corners no ray crosses, and grows pockets and bubbles;
- `normal`: grad f at the hit along the depth map's normal there (1 - cos), weighted by the normal's
  confidence (depth noise against pixel spacing: finite differences of far Kinect depth are noise);
- `eikonal`: |grad f| = 1 on every sample and on the uniform points.
Missing pixels (depth 0) are skipped, never fitted as surface. Before the fit, each hit moves along its ray
onto the quadric of its nearest hits (`denoise_hits`): the sensor noise is averaged over a neighbourhood.
The rays are sized to the capture: a room's frames hold tens of millions of valid pixels, so the rays of
every s-th pixel along both axes are fitted, s the smallest stride whose valid pixels number at most
`max_rays` (`budget_stride`); the frames overlap, so the strided pixels still cover what they saw.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property

import torch
from torch import Tensor, nn

from neuralsurf.cameras import Rays, box_span, depth_rays, frame_readings, kinect_sigma
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import cloud_spacing, cloud_winding_number, knn, point_areas, quadric_heights
from neuralsurf.losses import eikonal_loss
from neuralsurf.observations.base import NotObserved, Observation, Sampler, check_weights
from neuralsurf.observations.observed import ObservedSurface, observed_points
from neuralsurf.strategies import choose, names, register
from neuralsurf.structures import DepthFrames, Normalization

RAY_TERMS = ("surface", "band", "free", "carve", "normal", "eikonal")


@register("depth sigma", "kinect")
def kinect_depth_sigma(z: Tensor, sigma: float) -> Tensor:
    """Kinect v1's axial noise sigma at depths z [...] metres (`cameras.kinect_sigma`; `sigma` unused)."""
    return kinect_sigma(z)


@register("depth sigma", "constant")
def constant_depth_sigma(z: Tensor, sigma: float) -> Tensor:
    """`sigma` metres at every depth z [...]."""
    return torch.full_like(z, sigma)
DEFAULT_RAY_WEIGHTS = {"surface": 3.0, "band": 1.0, "free": 100.0, "carve": 1.0, "normal": 0.5, "eikonal": 0.03}


def strided_count(depth: Tensor, stride: int) -> int:
    """Number of valid readings (depth > 0) among every `stride`-th pixel along both axes of depth
    Float[Tensor, "f h w"]: the rays `depth_rays` builds from `stride_frames(frames, stride)`."""
    return int((depth[:, ::stride, ::stride] > 0).sum())


def budget_stride(depth: Tensor, max_rays: int, min_stride: int = 1) -> int:
    """The smallest pixel stride >= `min_stride` whose valid readings of depth Float[Tensor, "f h w"]
    (`strided_count`) number at most `max_rays`. Raises ConfigError when even one pixel per frame
    (a stride of the image's larger side) is more than `max_rays`."""
    if not (max_rays >= 1 and min_stride >= 1):
        raise ConfigError(f"budget_stride needs max_rays >= 1 and min_stride >= 1, got {max_rays} and {min_stride}")
    largest = max(depth.shape[-2:])  # from here on, one pixel per frame
    for stride in range(min_stride, max(largest, min_stride) + 1):
        if strided_count(depth, stride) <= max_rays:
            return stride
    raise ConfigError(f"DepthRays: max_rays={max_rays} is fewer than one ray per frame "
                      f"({strided_count(depth, largest)} of the {len(depth)} frames' first pixels are valid); "
                      f"raise max_rays or fit fewer frames")


def hit_bounds(rays: Rays) -> Tensor:
    """Float64[Tensor, "2 3"]: the box (min and max corner) of the rays' hit points."""
    points = (rays.origins + rays.hit[:, None] * rays.directions).double()
    return torch.stack([points.min(0).values, points.max(0).values])


def box_entry(origins: Tensor, directions: Tensor, box: float) -> Tensor:
    """Float[Tensor, "r"]: distance along each ray where it enters the cube [-box, box]^3 (0 when the
    origin lies inside; rays that miss the cube get their exit, which is smaller than their entry).
    origins, directions: Float[Tensor, "r 3"]."""
    return box_span(origins, directions, torch.tensor([-box, box], dtype=origins.dtype, device=origins.device)[:, None])[0]


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

    free = torch.zeros(len(points), dtype=torch.bool)
    near = torch.zeros(len(points), dtype=torch.bool)
    behind, missing, seen_by = (torch.zeros(len(points), dtype=torch.int32) for _ in range(3))
    for depth, K, pose in zip(frames.depth.cpu(), frames.K.cpu(), frames.cam_to_world.cpu()):
        z, reading, seen = (t[0] for t in frame_readings(points.double(), depth[None], K[None].double(),
                                                            pose[None].double()))
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


def winding_labels(points: Tensor, rays: Rays, n_points: int, seed: int = 0, tolerance: float = 0.25) -> Tensor:
    """Free / inside labels of points by the generalised winding number w of `n_points` hits with the
    depth map's normals (facing their camera). The cameras lie on the free side of what they saw: a
    point whose w is within `tolerance` of the cameras' is free, within `tolerance` of theirs + 1
    inside (an object seen from outside: 0 and 1; a room seen from within: -1 and 0); other values
    (thin parts) and points within the reach of the hits' spacing (`sampling.winding_signs`) stay
    unknown, and so does every point when the cameras' w is not within `tolerance` / 2 of an integer
    (the hits do not close around them: a room seen in part, as 7-Scenes redkitchen's -0.25).
    points: Float[Tensor, "n 3"], same frame as `rays`. Returns Int8[Tensor, "n"]: +1 free, -1 inside, 0 unknown."""
    with_normal = (rays.normals.norm(dim=-1) > 0).nonzero()[:, 0]
    pick = with_normal[torch.randperm(len(with_normal), generator=torch.Generator().manual_seed(seed))[:n_points]]
    hits = (rays.origins[pick] + rays.hit[pick, None] * rays.directions[pick]).double()
    normals = torch.nn.functional.normalize(rays.normals[pick].double(), dim=-1)
    labels = torch.zeros(len(points), dtype=torch.int8)
    if len(hits) < 2 or not len(points):
        return labels
    areas = point_areas(hits)
    cameras = cloud_winding_number(rays.origins.unique(dim=0).double(), hits, normals, areas).median()
    if (cameras - cameras.round()).abs() >= tolerance / 2:
        return labels
    far = knn(points.double(), hits, 1)[0][:, 0] > 3 * cloud_spacing(hits)
    w = cloud_winding_number(points[far].double(), hits, normals, areas)
    free, inside = (w - cameras).abs() < tolerance, (w - cameras - 1).abs() < tolerance
    labels[far] = torch.where(free, 1, torch.where(inside, -1, 0)).to(labels)
    return labels


def denoise_hits(rays: Rays, k: int) -> Rays:
    """`rays` with each hit moved along its ray onto the quadric fitted to its k nearest hits (of every view;
    `geometry.quadric_heights`, in the frame of the depth map's normal, or of the ray where it has none):
    averages the sensor noise, which lies along the ray, over the neighbourhood. The move is height / cos
    (exact for noise along the ray), the cosine at least 0.2, and at most 3 noise sigmas of the reading.
    k is clamped to the number of hits; under 6 hits (a quadric's unknowns) they stay as they are."""
    if len(rays.hit) < 6:
        return rays
    k = min(k, len(rays.hit))
    hits = (rays.origins + rays.hit[:, None] * rays.directions).double()
    directions = rays.directions.double()
    has_normal = rays.normals.norm(dim=-1, keepdim=True) > 0
    normals = torch.where(has_normal, torch.nn.functional.normalize(rays.normals.double(), dim=-1), -directions)
    cosine = (directions * normals).sum(-1)  # negative: the normals face the camera
    move = quadric_heights(hits, normals, k) / cosine.clamp(max=-0.2)
    limit = 3 * rays.sigma.double()
    return replace(rays, hit=(rays.hit.double() + torch.maximum(torch.minimum(move, limit), -limit)).to(rays.hit.dtype))


@dataclass(frozen=True)
class RayBatch(Rays):
    """Rays drawn for one step (the fields of `Rays`, unit frame), with the distances of their samples.
    The first r rays carry free and band samples; the rest (hits only) add to the surface and normal
    terms (`cosine` projects ray distances on the normal)."""

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
    uniform_margin: Tensor
    """Float[Tensor, "u"]: how far from 0 the field must be on their labelled side (0 where unknown)."""


def draw_rays(rays: Rays, entry: Tensor, n_rays: int, n_free: int, n_band: int, band: Tensor, n_uniform: int,
              carved: tuple[Tensor, Tensor, Tensor], generator: torch.Generator, n_hits: int = 0) -> RayBatch:
    """`n_rays` rays at random with `n_free` stratified free samples in [entry, hit - band] and `n_band`
    uniform samples in [hit - band, hit + band] each, `n_hits` more rays with their hit only, and
    `n_uniform` points of the `carved` pool (points Float[Tensor, "p 3"], labels Int8[Tensor, "p"], margins
    Float[Tensor, "p"]).
    Random numbers are drawn on the CPU with `generator` (a resumed fit draws the same batches) and moved
    to the rays' device. band: Float[Tensor, "r"], half-width of each ray's band."""
    device = rays.hit.device
    every = torch.randint(len(rays.hit), (n_rays + n_hits,), generator=generator).to(device)
    pick = every[:n_rays]
    u_free = torch.rand(n_rays, n_free, generator=generator).to(device)
    u_band = torch.rand(n_rays, n_band, generator=generator).to(device)
    chosen = torch.randint(len(carved[0]), (n_uniform,), generator=generator).to(device)
    hit, half = rays.hit[pick], band[pick]
    start, stop = entry[pick], hit - half
    strata = (torch.arange(n_free, device=device) + u_free) / max(n_free, 1)
    free_t = start[:, None] + strata * (stop - start).clamp_min(0)[:, None]
    band_t = hit[:, None] + half[:, None] * (2 * u_band - 1)
    return RayBatch(rays.origins[every], rays.directions[every], rays.hit[every], rays.sigma[every],
                    rays.cosine[every], rays.normals[every], free_t,
                    (stop > start)[:, None].expand_as(free_t), band_t, *(pool[chosen] for pool in carved))


def ray_terms(model: nn.Module, batch: RayBatch, weights: Mapping[str, float]) -> dict[str, Tensor]:
    """Unweighted ray loss terms (surface, band, free, carve, normal, eikonal; those with a positive weight) of the
    unit-frame `model` on `batch`, from one forward pass over all samples."""
    r, f = batch.free_t.shape
    b = batch.band_t.shape[1]
    t = torch.cat([batch.hit[:r, None], batch.band_t, batch.free_t], dim=1)  # (r, 1 + b + f)
    points = batch.origins[:r, None] + t[..., None] * batch.directions[:r, None]
    hits_only = batch.origins[r:] + batch.hit[r:, None] * batch.directions[r:]  # (h, 3)
    need_gradient = bool(weights.get("eikonal") or weights.get("normal"))
    points = torch.cat([points.reshape(-1, 3), hits_only, batch.uniform]).requires_grad_(need_gradient)
    values = model(points)
    n_along, n_hits = r * (1 + b + f), len(hits_only)
    along = values[:n_along].reshape(r, 1 + b + f)
    at_hits = torch.cat([along[:, 0], values[n_along : n_along + n_hits]])  # every ray's hit, batch order
    noise_weight = 1.0 / batch.sigma
    noise_weight = noise_weight / noise_weight.mean()
    terms: dict[str, Tensor] = {}
    if weights.get("surface"):
        terms["surface"] = (noise_weight * at_hits.abs()).mean()
    if weights.get("band"):
        target = (batch.hit[:r, None] - batch.band_t) * batch.cosine[:r, None]
        terms["band"] = (noise_weight[:r, None] * (along[:, 1 : 1 + b] - target).abs()).mean()
    if weights.get("free") and f:
        bound = batch.hit[:r, None] - batch.free_t
        free = along[:, 1 + b :]
        violation = torch.relu(free - bound) + torch.relu(-free)
        terms["free"] = (violation * batch.free_valid).sum() / batch.free_valid.sum().clamp_min(1)
    if weights.get("carve"):
        label = batch.uniform_label.to(values.dtype)
        violation = torch.relu(batch.uniform_margin - label * values[n_along + n_hits :]) * (label != 0)
        terms["carve"] = violation.sum() / (label != 0).sum().clamp_min(1)
    if need_gradient:
        (gradient,) = torch.autograd.grad(values.sum(), points, create_graph=True)
    if weights.get("normal"):
        confidence = batch.normals.norm(dim=-1)
        at_hit = torch.cat([gradient[:n_along].reshape(r, 1 + b + f, 3)[:, 0],
                            gradient[n_along : n_along + n_hits]])
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
    carved: tuple[Tensor, Tensor, Tensor]
    n_hits: int = 0

    def sample(self, generator: torch.Generator) -> RayBatch:
        return draw_rays(self.rays, self.entry, self.n_rays, self.n_free, self.n_band, self.band, self.n_uniform,
                         self.carved, generator, self.n_hits)

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
    """Rays per step with free and band samples."""
    hit_fraction: float = 0.0125
    """Hits per step (surface and normal terms), as a fraction of all rays: those beyond the `n_rays` come
    without free and band samples. A fixed fraction draws every hit about as often however many views
    there are (the noise of each hit averages out; drawn far more often, the fit follows it)."""
    max_hits: int = 4096
    """At most this many hits per step (rooms have millions of rays)."""
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
    max_rays: int = 2_000_000
    """At most this many rays (memory and the time to build and denoise them grow with the count). Frames
    with more valid pixels are fitted at the smallest pixel stride, at least `pixel_stride`, whose rays fit
    (`budget_stride`; `stride`), with a warning naming it: the 24 synthetic 320x240 bunny views keep every
    pixel; the 90 Kinect frames of 7-Scenes redkitchen (24.6 million valid pixels) every 4th."""
    carve_voxel: float = 0.0
    """World units: draw half of the carve pool inside the voxels of this size where the frames observed a
    surface, and their neighbours (`observed.ObservedSurface`; thin gaps and silhouettes get labelled points,
    not only the empty box); 0: the whole pool uniform in the box."""
    pixel_stride: int = 1
    """Rays of every this-many-th pixel along both image axes only (`depth_rays`; their normals from the
    full-resolution depth map): a room's frames overlap, so 1 / stride^2 of the pixels still cover it, and
    building and denoising the rays costs that much less time and memory. A larger stride is taken where the
    rays would exceed `max_rays`."""
    noise_model: str | Callable = "kinect"
    """Noise sigma of a depth reading, a "depth sigma" strategy: "kinect" (Nguyen et al. 2012: 1.2 mm at
    0.4 m, growing with the square of the depth), "constant" (`sigma` metres), or a function (z, sigma) -> sigma."""
    sigma: float = 0.001
    """Noise sigma of the "constant" model, metres."""
    carve_margin: float = 1.0
    """Labelled carve points must lie on their side by this fraction of their distance to the nearest hit
    (which bounds their true distance from above), not only by any amount: bubbles of the wrong sign
    inside (or floaters outside) then cost more than a slightly wrong value; 0: sign only."""
    winding_points: int = 5000
    """Points carving leaves unknown are labelled by the winding number of this many hits (`winding_labels`:
    interior pockets no pair of views reaches, corners no view sees); 0: carving alone."""
    denoise_k: int = 30
    """Move each hit along its ray onto the quadric fitted to its this many nearest hits (`denoise_hits`:
    averages the sensor noise before the fit; at most all hits, none with fewer than 6); 0: off."""
    name: str = "rays"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, RAY_TERMS, "DepthRays"))
        if not isinstance(self.frames, DepthFrames):
            raise InputError(f"DepthRays expects neuralsurf.DepthFrames, got {type(self.frames).__name__}")
        counts = {k: getattr(self, k) for k in ("n_rays", "max_hits", "n_free", "n_band", "n_uniform", "n_carve",
                                                 "max_rays", "winding_points", "denoise_k", "pixel_stride")}
        if any(not isinstance(v, int) or v < 0 for v in counts.values()) or not all(
                counts[k] for k in ("n_rays", "n_carve", "max_rays", "pixel_stride")) or 0 < self.denoise_k < 6:
            raise ConfigError(f"DepthRays needs integer sample counts (n_rays, n_carve, max_rays, pixel_stride >= 1, "
                              f"denoise_k 0 or "
                              f">= 6, others >= 0), got {counts}")
        amounts = {k: getattr(self, k) for k in ("hit_fraction", "carve_margin", "truncation", "sigma")}
        if not (amounts["hit_fraction"] >= 0 and amounts["carve_margin"] >= 0 and amounts["truncation"] > 0
                and amounts["sigma"] > 0
                and (not isinstance(self.noise_model, str) or self.noise_model in names("depth sigma"))):
            raise ConfigError(f"DepthRays needs hit_fraction >= 0, carve_margin >= 0, truncation > 0, sigma > 0 and "
                              f"noise_model kinect or constant, got {amounts}, noise_model={self.noise_model!r}")

    @classmethod
    def from_scene(cls, scene, **options) -> DepthRays:
        """The scene's depth frames (a `neuralsurf.scenes.Scene`) with these options; NotObserved
        when the scene has none."""
        if scene.frames is None or not scene.depth_input:
            points = scene.cloud is not None and not getattr(scene, "cloud_from_truth", False)
            raise NotObserved(f"scene {scene.name!r} is not a depth capture (no depth frames as its input)" +
                              ("; fit its points with PointSamples (observation=points)" if points else
                               ", and it has no measured points either"))
        return cls(scene.frames, **options)

    def _sigma_of_depth(self):
        model = choose("depth sigma", self.noise_model)
        return lambda z: model(z, self.sigma)

    @cached_property
    def stride(self) -> int:
        """The pixel stride the rays are built at: `pixel_stride`, or the smallest larger one whose valid
        pixels number at most `max_rays` (`budget_stride`; warns once, naming the stride and the counts)."""
        stride = budget_stride(self.frames.depth, self.max_rays, self.pixel_stride)
        if stride > self.pixel_stride:
            warnings.warn(f"DepthRays: the {len(self.frames)} frames hold "
                          f"{strided_count(self.frames.depth, self.pixel_stride):,} valid pixels at pixel_stride="
                          f"{self.pixel_stride}, more than max_rays={self.max_rays:,}: fitting the rays at "
                          f"pixel_stride={stride} ({strided_count(self.frames.depth, stride):,} rays); "
                          f"raise max_rays (memory grows with it) or set pixel_stride to choose", stacklevel=3)
        return stride

    @cached_property
    def world_rays(self) -> Rays:
        """The frames' world-frame rays at `stride` (`depth_rays`), built once for `bounds` and `prepare`."""
        return depth_rays(self.frames.to("cpu"), self._sigma_of_depth(), pixel_stride=self.stride)

    def bounds(self) -> Tensor:
        return hit_bounds(self.world_rays)

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> RaySampler:
        rays = self.world_rays
        bounds = hit_bounds(rays)  # of every ray, before the denoising
        if self.denoise_k:
            rays = denoise_hits(rays, self.denoise_k)
        scale = normalization.scale
        unit = Rays(normalization.to_unit(rays.origins.double()).float(), rays.directions, rays.hit / scale,
                    rays.sigma / scale, rays.cosine.clamp_min(0.05), rays.normals)
        unit = Rays(*(getattr(unit, name).to(device) for name in Rays.__dataclass_fields__))
        entry = box_entry(unit.origins, unit.directions, box)
        band = torch.clamp(3 * unit.sigma, min=self.truncation)
        generator = torch.Generator().manual_seed(seed)
        pool = (2 * torch.rand(self.n_carve, 3, generator=generator, dtype=torch.float64) - 1) * box
        if self.carve_voxel:  # half of the pool where surfaces were observed: carving sharpens edges and gaps
            observed = ObservedSurface.from_frames(self.frames, self.carve_voxel, max_free_ratio=None)
            near = observed_points(observed, self.n_carve // 2, generator)
            pool[: len(near)] = normalization.to_unit(near).clamp(-box, box)
        labels = carve_labels(normalization.to_world(pool), self.frames, self.truncation * scale, self._sigma_of_depth(),
                              bounds)
        if self.winding_points:
            unknown = labels == 0
            labels[unknown] = winding_labels(normalization.to_world(pool[unknown]), rays, self.winding_points, seed)
        margin = torch.zeros(len(pool), dtype=torch.float64)
        if self.carve_margin:
            hits = unit.origins.cpu().double() + unit.hit.cpu().double()[:, None] * unit.directions.cpu().double()
            labelled = labels != 0
            margin[labelled] = self.carve_margin * knn(pool[labelled], hits, 1)[0][:, 0]
        carved = (pool.float().to(device), labels.to(device), margin.float().to(device))
        n_hits = max(min(round(self.hit_fraction * len(unit.hit)), self.max_hits) - self.n_rays, 0)
        return RaySampler(unit, entry, band, self.weights, self.n_rays, self.n_free, self.n_band, self.n_uniform, carved,
                          n_hits)
