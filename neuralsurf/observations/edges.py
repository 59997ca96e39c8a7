"""Depth rays for refining a fused surface: hits, a band around them, and the free space beside depth edges.

A pixel on the far side of a depth edge (its reading more than `jump` beyond the nearest reading within
`window` pixels) looks past the near object's silhouette: its ray passes beside that object, at about the
near reading's depth, through space the view saw as free. Fusion smears silhouettes over a voxel or more
(a voxel's value mixes the near surface and the free ray beside it), so a field is asked to be free
(f >= 0) on those rays around the near depth (`edge`), as well as zero at every hit (`surface`) and equal
to the projected distance in a band around it (`band`, as `DepthRays`). Every sample lies near an observed
surface, which is where a field stored on observed voxels has values to change.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import kinect_sigma
from neuralsurf.observations.base import NotObserved, Observation, Sampler, check_weights
from neuralsurf.observations.observed import stride_frames
from neuralsurf.observations.rays import Rays, depth_rays, hit_bounds
from neuralsurf.structures import DepthFrames, Normalization

EDGE_TERMS = ("surface", "band", "edge")


def edge_ratios(depth: Tensor, jump: float, window: int) -> Tensor:
    """Float[Tensor, "f h w"] depth (0: missing) -> Float[Tensor, "f h w"]: at a pixel whose reading lies more
    than `jump` beyond the nearest valid reading within `window` pixels (both axes), that reading's depth
    divided by its own (in (0, 1)); 0 elsewhere."""
    far = torch.where(depth > 0, depth, torch.inf)
    nearest = -torch.nn.functional.max_pool2d(-far[:, None], 2 * window + 1, 1, window)[:, 0]
    edge = (depth > 0) & torch.isfinite(nearest) & (depth - nearest > jump)
    return torch.where(edge, nearest / depth.clamp_min(1e-12), 0.0)


@dataclass(frozen=True)
class EdgeBatch:
    """One step's samples (unit frame): hits with band samples, and edge rays with samples beside the edge."""

    origins: Tensor
    """Float[Tensor, "r 3"]."""
    directions: Tensor
    """Float[Tensor, "r 3"]."""
    hit: Tensor
    """Float[Tensor, "r"]: distance to the reading along each ray."""
    noise_weight: Tensor
    """Float[Tensor, "r"]: inverse noise sigma at the hit, mean 1."""
    cosine: Tensor
    """Float[Tensor, "r"]: |cos| between the ray and the depth map's normal."""
    band_t: Tensor
    """Float[Tensor, "r b"]: distances of samples in the band around the hit."""
    edge_points: Tensor
    """Float[Tensor, "e 3"]: points on rays passing beside a depth edge, around the near reading's depth."""


@dataclass(frozen=True)
class EdgeSampler(Sampler):
    rays: Rays
    band: Tensor
    edge_rays: Tensor
    edge_t: Tensor
    weights: dict[str, float]
    n_rays: int
    n_band: int
    n_edge: int
    spread: float

    def sample(self, generator: torch.Generator) -> EdgeBatch:
        device = self.rays.hit.device
        pick = torch.randint(len(self.rays.hit), (self.n_rays,), generator=generator).to(device)
        u = torch.rand(self.n_rays, self.n_band, generator=generator).to(device)
        n_edge = self.n_edge if len(self.edge_rays) else 0
        chosen = torch.randint(max(len(self.edge_rays), 1), (n_edge,), generator=generator).to(device)
        v = torch.rand(n_edge, generator=generator).to(device)
        sigma = self.rays.sigma[pick]
        weight = (1 / sigma) / (1 / sigma).mean()
        band_t = self.rays.hit[pick, None] + self.band[pick, None] * (2 * u - 1)
        edge = self.edge_rays[chosen]
        t = (self.edge_t[chosen] + self.spread * (2 * v - 1)).clamp_min(0)
        t = torch.minimum(t, self.rays.hit[edge] - self.band[edge])  # in front of the ray's own band
        points = self.rays.origins[edge] + t[:, None] * self.rays.directions[edge]
        return EdgeBatch(self.rays.origins[pick], self.rays.directions[pick], self.rays.hit[pick], weight,
                         self.rays.cosine[pick], band_t, points)

    def losses(self, model: nn.Module, batch: EdgeBatch) -> dict[str, Tensor]:
        r, b = batch.band_t.shape
        t = torch.cat([batch.hit[:, None], batch.band_t], 1)
        along = batch.origins[:, None] + t[..., None] * batch.directions[:, None]
        values = model(torch.cat([along.reshape(-1, 3), batch.edge_points]))
        at = values[: r * (1 + b)].reshape(r, 1 + b)
        terms: dict[str, Tensor] = {}
        if self.weights.get("surface"):
            terms["surface"] = (batch.noise_weight * at[:, 0].abs()).mean()
        if self.weights.get("band") and b:
            target = (batch.hit[:, None] - batch.band_t) * batch.cosine[:, None]
            terms["band"] = (batch.noise_weight[:, None] * (at[:, 1:] - target).abs()).mean()
        if self.weights.get("edge") and len(batch.edge_points):
            terms["edge"] = torch.relu(-values[r * (1 + b):]).mean()
        if not terms:
            raise ConfigError("every EdgeRays term is switched off or has no samples; give surface or band a weight")
        return terms


@dataclass(frozen=True)
class EdgeRays(Observation):
    """Depth frames as hits, a band around each, and the free space beside depth edges (the module docstring)."""

    frames: DepthFrames
    """Depth maps (metres, 0 = missing) with intrinsics and camera-to-world poses, world frame."""
    weights: Mapping[str, float] = field(default_factory=lambda: {"surface": 1.0, "band": 1.0, "edge": 10.0})
    """Term weights: surface, band, edge."""
    n_rays: int = 4096
    """Hits per step, each with `n_band` band samples."""
    n_band: int = 2
    """Samples per hit in the band [hit - band, hit + band]."""
    n_edge: int = 4096
    """Samples per step on rays beside depth edges."""
    jump: float = 0.05
    """Metres: a reading this much beyond the nearest one within `window` pixels lies past a depth edge."""
    window: int = 2
    """Pixels (of the strided frames) around each pixel searched for a nearer reading."""
    spread: float = 0.02
    """Metres: edge samples lie within this of the near reading's depth along the ray."""
    truncation: float = 0.002
    """Half-width of the band around each hit, unit frame (at least 3 noise sigmas)."""
    pixel_stride: int = 2
    """Rays of every this-many-th pixel along both image axes."""
    name: str = "edges"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, EDGE_TERMS, "EdgeRays"))
        if not isinstance(self.frames, DepthFrames):
            raise InputError(f"EdgeRays expects neuralsurf.DepthFrames, got {type(self.frames).__name__}")
        counts = {k: getattr(self, k) for k in ("n_rays", "n_band", "n_edge", "window", "pixel_stride")}
        if any(not isinstance(v, int) or v < 0 for v in counts.values()) or not (counts["n_rays"] and counts["window"]
                                                                                  and counts["pixel_stride"]):
            raise ConfigError(f"EdgeRays needs integer counts >= 0 (n_rays, window, pixel_stride >= 1), got {counts}")
        if not (self.jump > 0 and self.spread >= 0 and self.truncation > 0):
            raise ConfigError(f"EdgeRays needs jump > 0, spread >= 0 and truncation > 0, got jump={self.jump}, "
                              f"spread={self.spread}, truncation={self.truncation}")

    @classmethod
    def from_scene(cls, scene, **options) -> EdgeRays:
        """The scene's depth frames with these options; NotObserved when the scene has none."""
        if scene.frames is None or not scene.depth_input:
            raise NotObserved(f"scene {scene.name!r} is not a depth capture (no depth frames as its input)")
        return cls(scene.frames, **options)

    def _strided(self) -> DepthFrames:
        return stride_frames(self.frames.to("cpu"), self.pixel_stride)

    def bounds(self) -> Tensor:
        return hit_bounds(depth_rays(self._strided(), kinect_sigma))

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> EdgeSampler:
        frames = self._strided()
        rays = depth_rays(frames, kinect_sigma)
        ratio = edge_ratios(frames.depth, self.jump, self.window)[frames.depth > 0]  # ray order: frame, row, column
        scale = normalization.scale
        unit = Rays(normalization.to_unit(rays.origins.double()).float(), rays.directions, rays.hit / scale,
                    rays.sigma / scale, rays.cosine.clamp_min(0.05), rays.normals)
        unit = Rays(*(getattr(unit, name).to(device) for name in Rays.__dataclass_fields__))
        band = torch.clamp(3 * unit.sigma, min=self.truncation)
        edge = (ratio > 0).nonzero()[:, 0].to(device)
        edge_t = unit.hit[edge] * ratio.to(device)[edge]
        return EdgeSampler(unit, band, edge, edge_t, self.weights, self.n_rays, self.n_band, self.n_edge,
                           self.spread / scale)
