"""Normal maps: photometric normals at the surface points a depth map places under each pixel.

Per view, a normal map in the camera frame (photometric stereo: normals facing the camera have
z < 0) with a per-pixel confidence, and a depth map of the same camera pose, possibly of lower
resolution (a Kinect beside a camera): the depth is resampled to the normal map's pixels
(`resample_depth`: bilinear, missing across discontinuities), each pixel becomes the 3D point of
its depth, and its normal is turned into the world frame. The loss term `normal` is
1 - cos(grad f, n) at those points, weighted by the stereo confidence (a weighted mean over the
batch). Pixels without a normal, with zero confidence or without depth are not used.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from neuralsurf.cameras import pixel_rays, resample_depth
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.observations.base import NotObserved, Observation, Sampler, check_weights
from neuralsurf.structures import DepthFrames, Normalization

NORMAL_TERMS = ("normal",)
DEFAULT_NORMAL_WEIGHTS = {"normal": 0.1}


@dataclass(frozen=True)
class OrientedPoints:
    """Surface points with measured normals and their weights, in one frame of reference."""

    points: Tensor
    """Float[Tensor, "p 3"]: back-projected pixels."""
    normals: Tensor
    """Float[Tensor, "p 3"]: unit normals (outward, facing the camera that saw them)."""
    confidence: Tensor
    """Float[Tensor, "p"]: weight of each normal, > 0."""


@dataclass(frozen=True)
class NormalBatch:
    """Pixels drawn for one step (unit frame)."""

    points: Tensor
    """Float[Tensor, "b 3"]: surface points from the depth."""
    normals: Tensor
    """Float[Tensor, "b 3"]: unit world normals there."""
    confidence: Tensor
    """Float[Tensor, "b"]: their weights."""


def normal_pixels(normals: Tensor, confidence: Tensor, K: Tensor, cam_to_world: Tensor, depth: DepthFrames,
                  max_depth_jump: float = 0.05) -> OrientedPoints:
    """World points and world normals of every pixel with a normal, a positive confidence and a depth.

    Args:
        normals: Float[Tensor, "v h w 3"] camera-frame normals (0 = none).
        confidence: Float[Tensor, "v h w"] (0 = not used).
        K: Float[Tensor, "v 3 3"] intrinsics of the normal maps; cam_to_world: Float[Tensor, "v 4 4"].
        depth: v depth frames of the same poses (any resolution, resampled to h x w).
    """
    v, h, w = normals.shape[:3]
    if len(depth) != v or not torch.allclose(depth.cam_to_world.double().cpu(), cam_to_world.double().cpu(),
                                             atol=1e-5):
        raise InputError(f"NormalMaps needs one depth frame per normal map with the same camera pose: {v} normal "
                         f"maps, {len(depth)} depth frames (poses must agree to 1e-5)")
    points, world_normals, weights = [], [], []
    for i in range(v):
        z = resample_depth(depth.depth[i], depth.K[i], K[i], h, w, max_depth_jump).double()
        n = normals[i].double().cpu()
        keep = (z > 0) & (n.norm(dim=-1) > 0.5) & (confidence[i].cpu() > 0)
        pose = cam_to_world[i].double().cpu()
        camera = pixel_rays(torch.as_tensor(K[i], dtype=torch.float64).cpu(), h, w)[keep] * z[keep][:, None]
        points.append(camera @ pose[:3, :3].T + pose[:3, 3])
        world_normals.append(torch.nn.functional.normalize(n[keep], dim=-1) @ pose[:3, :3].T)
        weights.append(confidence[i].cpu().double()[keep])
    result = OrientedPoints(torch.cat(points), torch.cat(world_normals), torch.cat(weights))
    if len(result.points) == 0:
        raise InputError("NormalMaps: no pixel has a normal, a positive confidence and a depth; check the masks, "
                         "the confidence and that the depth frames see the same object")
    return result


@dataclass(frozen=True)
class NormalSampler(Sampler):
    pixels: OrientedPoints
    weights: dict[str, float]
    n_pixels: int

    def sample(self, generator: torch.Generator) -> NormalBatch:
        pick = torch.randint(len(self.pixels.points), (self.n_pixels,), generator=generator)
        pick = pick.to(self.pixels.points.device)
        return NormalBatch(self.pixels.points[pick], self.pixels.normals[pick], self.pixels.confidence[pick])

    def losses(self, model: nn.Module, batch: NormalBatch) -> dict[str, Tensor]:
        return normal_map_terms(model, batch, self.weights)


def normal_map_terms(model: nn.Module, batch: NormalBatch, weights: Mapping[str, float]) -> dict[str, Tensor]:
    """`normal`: the confidence-weighted mean of 1 - cos(grad f, n) at the batch's points."""
    if not weights.get("normal"):
        raise ConfigError("the NormalMaps term 'normal' is switched off; give it a positive weight")
    points = batch.points.detach().requires_grad_(True)
    values = model(points)
    (gradient,) = torch.autograd.grad(values.sum(), points, create_graph=True)
    cosine = torch.nn.functional.cosine_similarity(gradient, batch.normals, dim=-1, eps=1e-8)
    return {"normal": (batch.confidence * (1 - cosine)).sum() / batch.confidence.sum().clamp_min(1e-12)}


@dataclass(frozen=True)
class NormalMaps(Observation):
    """Photometric normal maps at the points of depth maps of the same cameras: 1 - cos(grad f, n)."""

    normals: Tensor
    """Float[Tensor, "v h w 3"]: unit normals in each camera's frame (facing it: z < 0), 0 = none."""
    confidence: Tensor
    """Float[Tensor, "v h w"]: per-pixel weight in [0, 1] (photometric stereo's confidence), 0 = not used."""
    K: Tensor
    """Float[Tensor, "v 3 3"]: intrinsics of the normal maps."""
    cam_to_world: Tensor
    """Float[Tensor, "v 4 4"]: OpenCV poses of the normal maps' cameras."""
    depth: DepthFrames
    """One depth map per view, same pose, any resolution: places each normal in space."""
    weights: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_NORMAL_WEIGHTS))
    """Term weights: normal."""
    n_pixels: int = 1024
    """Pixels per step."""
    min_confidence: float = 0.0
    """Pixels whose confidence is at most this are not used."""
    max_depth_jump: float = 0.05
    """Depth resampling: no value across neighbours whose depths differ by more than this fraction."""
    name: str = "normals"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", check_weights(self.weights, NORMAL_TERMS, "NormalMaps"))
        normals = torch.as_tensor(self.normals).float()
        if normals.ndim == 3:
            normals = normals[None]
        if normals.ndim != 4 or normals.shape[-1] != 3:
            raise InputError(f"NormalMaps.normals must be (v, h, w, 3), got {tuple(normals.shape)}")
        v, h, w = normals.shape[:3]
        confidence = torch.as_tensor(self.confidence).float().reshape(-1, h, w) if torch.as_tensor(
            self.confidence).numel() == v * h * w else None
        if confidence is None:
            raise InputError(f"NormalMaps.confidence must be (v, h, w) = {(v, h, w)}, got "
                             f"{tuple(torch.as_tensor(self.confidence).shape)}")
        K = torch.as_tensor(self.K).float()
        K = K.expand(v, 3, 3) if K.shape == (3, 3) else K
        pose = torch.as_tensor(self.cam_to_world).float()
        pose = pose.expand(v, 4, 4) if pose.shape == (4, 4) else pose
        if K.shape != (v, 3, 3) or pose.shape != (v, 4, 4):
            raise InputError(f"NormalMaps needs K (v, 3, 3) and cam_to_world (v, 4, 4) for v = {v} views, got "
                             f"{tuple(K.shape)} and {tuple(pose.shape)}")
        if not isinstance(self.depth, DepthFrames):
            raise InputError(f"NormalMaps.depth must be neuralsurf.DepthFrames, got {type(self.depth).__name__}")
        if not (isinstance(self.n_pixels, int) and self.n_pixels >= 1) or not self.min_confidence >= 0:
            raise ConfigError(f"NormalMaps needs n_pixels >= 1 and min_confidence >= 0, got {self.n_pixels}, "
                              f"{self.min_confidence}")
        confidence = torch.where(confidence > self.min_confidence, confidence, 0.0)
        for name, value in (("normals", normals), ("confidence", confidence), ("K", K), ("cam_to_world", pose)):
            object.__setattr__(self, name, value)

    @classmethod
    def from_scene(cls, scene, **options) -> NormalMaps:
        """The scene's photometric normal maps (`scene.normal_maps`, the stereo results of
        `scene.photometric`) placed by its depth frames; NotObserved when it has none of either."""
        if getattr(scene, "normal_maps", None) is None or getattr(scene, "photometric", None) is None:
            raise NotObserved(f"scene {scene.name!r} has no photometric normal maps; fit it without NormalMaps")
        if scene.frames is None or not scene.depth_input:
            raise NotObserved(f"scene {scene.name!r} has normal maps but no depth frames to place them")
        normals = torch.stack([r.normals for r in scene.normal_maps])
        confidence = torch.stack([r.confidence * r.mask for r in scene.normal_maps])
        K = torch.stack([c.K for c in scene.photometric])
        pose = torch.stack([c.cam_to_world for c in scene.photometric])
        return cls(normals, confidence, K, pose, scene.frames, **options)

    def _world(self) -> OrientedPoints:
        return normal_pixels(self.normals, self.confidence, self.K, self.cam_to_world, self.depth.to("cpu"),
                             self.max_depth_jump)

    def bounds(self) -> Tensor:
        points = self._world().points
        return torch.stack([points.min(0).values, points.max(0).values])

    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> NormalSampler:
        world = self._world()
        unit = OrientedPoints(normalization.to_unit(world.points).float().to(device),
                              world.normals.float().to(device), world.confidence.float().to(device))
        return NormalSampler(unit, self.weights, self.n_pixels)


__all__ = ["NORMAL_TERMS", "NormalBatch", "NormalMaps", "OrientedPoints", "normal_map_terms", "normal_pixels"]
