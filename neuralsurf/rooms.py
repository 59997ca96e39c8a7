"""Rooms from depth frames at TSDF's cost: a sparse voxel SDF (`models.grid.VoxelSDF`) that starts as the TSDF
fusion of the frames, is then fitted to the same frames' depth rays, meshed on its observed voxels and coloured
from the frames.

TSDF fusion averages each view's projective distance, so a thin surface seen by some views is cancelled by the
free-space votes of the views that see past it. The fit asks the field, over every view at once, for zero at
the hits and the distance along the surface normal in a band around them (`ray_equations`), held to its start
where the rays say nothing: the field is linear in its grid values, so this is one sparse least-squares problem,
solved by conjugate gradients (`models.grid.solve_values`). The field has values only at the grid points fusion observed,
so no surface appears in space no frame saw; its mesh is marching cubes of the grid itself (cells with all
corners observed, as TSDF meshes).

Sizes are metres: a room is at the sensor's scale, and its noise (`cameras.kinect_sigma`) is too. One setting
serves every room (`RoomSettings`' defaults); objects take voxels in proportion to their box instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.baselines import TSDFVolume
from neuralsurf.cameras import depth_rays, kinect_sigma, project_points, stride_frames, strided_hits
from neuralsurf.errors import ConfigError, ExtractionError, InputError
from neuralsurf.marching import cube_triangles, merge_edge_vertices
from neuralsurf.models.grid import VoxelSDF, solve_values
from neuralsurf.structures import DepthFrames, Mesh, Normalization, float_colors


@dataclass(frozen=True)
class RoomSettings:
    """How a room is fused, fitted and meshed (metres where a length)."""

    voxel: float = 0.01
    """Grid spacing of the fused start and of the fitted field."""
    truncation: float = 0.04
    """TSDF truncation: the band around each reading that fusion updates (a few noise sigmas at room depths)."""
    margin: float = 0.1
    """The grid's box: the back-projected readings' box enlarged by this on each side."""
    pixel_stride: int = 8
    """Rays of every `pixel_stride`-th pixel along both axes are fitted (a room's frames overlap)."""
    n_band: int = 2
    """Band samples per ray, at -band and +band around the hit (band: 3 noise sigmas, at least a voxel)."""
    prior_weight: float = 10.0
    """The pull to the fused start, x the mean data weight of a grid value."""
    iterations: int = 5
    """Conjugate-gradient steps of the solve (0: the fused start as it is)."""
    colors: bool = True
    """Colour the mesh's vertices from the frames that see them (when the frames carry colour)."""

    def __post_init__(self) -> None:
        for name in ("voxel", "truncation"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"RoomSettings.{name} must be a length > 0 in metres, got {getattr(self, name)!r}")
        if self.truncation < self.voxel:
            raise ConfigError(f"RoomSettings.truncation ({self.truncation:g}) must be at least a voxel "
                              f"({self.voxel:g}): thinner bands leave holes; use 3 to 5 voxels")
        if not (self.margin >= 0 and self.pixel_stride >= 1 and self.n_band >= 0 and self.prior_weight > 0
                and self.iterations >= 0):
            raise ConfigError(f"RoomSettings needs margin >= 0, pixel_stride >= 1, n_band >= 0, prior_weight > 0 and "
                              f"iterations >= 0; got {self}")


@dataclass(frozen=True)
class RoomFit:
    """A fitted room: its field (unit frame of `normalization`) and its mesh (world frame)."""

    field: VoxelSDF
    """The fitted sparse voxel SDF, unit frame."""
    normalization: Normalization
    """World <-> unit frame of `field`."""
    mesh: Mesh
    """Marching cubes of `field` on its observed cells, world frame, vertex colours when the frames had colour."""


def reading_box(frames: DepthFrames, margin: float, pixel_stride: int = 4) -> Tensor:
    """Float64[Tensor, "2 3"]: the world box of the back-projected valid readings of every `pixel_stride`-th
    pixel of `frames` (`observed.strided_hits`), enlarged by `margin` metres on each side."""
    if not (frames.depth > 0).any():
        raise InputError(f"none of the {len(frames)} frames has a valid depth reading (all 0): nothing to fit")
    points = strided_hits(frames, pixel_stride)
    points = points if len(points) else strided_hits(frames, 1)
    return torch.stack([points.min(0).values - margin, points.max(0).values + margin])


def fused_voxels(frames: DepthFrames, bounds: Tensor, voxel: float, truncation: float,
                 normalization: Normalization, device: str = "cpu") -> VoxelSDF:
    """The TSDF fusion of `frames` over the world box `bounds` (Float64[Tensor, "2 3"]) with `voxel`-sized
    voxels and `truncation` (metres), as a unit-frame VoxelSDF of `normalization`: its observed voxels and
    their distances (outside: the truncation)."""
    volume = TSDFVolume(bounds, voxel, truncation, device=device, sparse=True).integrate(frames, progress=False)
    linear, values = volume.observed_voxels()
    origin = normalization.to_unit(torch.as_tensor(volume.origin, dtype=torch.float64)[None])[0]
    scale = normalization.scale
    return VoxelSDF.from_observed(list(volume.grid_shape), linear, values / scale, origin.tolist(), voxel / scale,
                                  truncation / scale)


def voxel_mesh(model: VoxelSDF, normalization: Normalization, slab: int = 64) -> Mesh:
    """Marching cubes of the 0-level set of `model`'s grid over the cells whose corners are all observed, in
    the world frame of `normalization`, faces oriented outward; in slabs of `slab` cells along the first axis
    (bounded memory), their vertices joined by grid edge (`marching.cube_triangles`). Raises ExtractionError
    when it has none."""
    size = model.shape[0]
    keys, positions = [], []
    for start in range(0, size - 1, slab):
        values, observed = model.dense(start, min(start + slab + 1, size))
        origin = torch.tensor([[start, 0, 0]], device=values.device)
        k, p = cube_triangles(values[None], observed[None], origin, model.shape)
        keys.append(k)
        positions.append(p.double())
    keys, positions = torch.cat(keys), torch.cat(positions)
    if not len(keys):
        raise ExtractionError("the voxel field has no zero crossing between observed grid points: the frames saw no "
                              "surface with both sides inside the truncation band")
    points, faces = merge_edge_vertices(keys, positions)
    unit = model.origin.double().cpu() + points.cpu() * model.voxel
    return Mesh(normalization.to_world(unit).float(), faces.cpu().long())


def ray_equations(frames: DepthFrames, normalization: Normalization, voxel: float, pixel_stride: int = 8,
                  n_band: int = 2) -> tuple[Tensor, Tensor, Tensor]:
    """What the rays of every `pixel_stride`-th pixel of `frames` say about a field in the unit frame of
    `normalization`, as weighted equations f(point) = target: 0 at each hit, and at `n_band` points spread over
    [hit - band, hit + band] the distance to the hit along the depth map's normal (band: 3 noise sigmas, at least
    `voxel`, unit frame); weights 1 / noise sigma, mean 1. Returns (points Float[Tensor, "m 3"], targets
    Float[Tensor, "m"], weights Float[Tensor, "m"]), m = rays x (1 + n_band), on the CPU."""
    if pixel_stride < 1 or n_band < 0:
        raise ConfigError(f"ray_equations needs pixel_stride >= 1 and n_band >= 0, got {pixel_stride} and {n_band}")
    rays = depth_rays(stride_frames(frames.to("cpu"), pixel_stride), kinect_sigma)
    origins = normalization.to_unit(rays.origins.double()).float()
    hit, sigma = rays.hit / normalization.scale, rays.sigma / normalization.scale
    spread = torch.cat([torch.zeros(1), torch.linspace(-1, 1, n_band)])
    offset = torch.clamp(3 * sigma, min=voxel)[:, None] * spread  # (rays, 1 + n_band) along each ray
    points = origins[:, None] + (hit[:, None] + offset)[..., None] * rays.directions[:, None]
    targets = -offset * rays.cosine.clamp_min(0.05)[:, None]
    weights = ((1 / sigma) / (1 / sigma).mean())[:, None].expand_as(offset)
    return points.reshape(-1, 3), targets.reshape(-1), weights.reshape(-1)


@torch.no_grad()
def frame_colors(points: Tensor, frames: DepthFrames, tolerance: float, chunk: int = 1 << 20) -> Tensor:
    """Float[Tensor, "n 3"]: the mean colour of world `points` (Float[Tensor, "n 3"]) over the frames that see
    them: the point projects inside the image onto a reading within `tolerance` metres (or 3 noise sigmas) of
    its depth. Points no frame sees get grey (0.5). Needs `frames.colors`."""
    if frames.colors is None:
        raise InputError("frame_colors needs frames with colours: read the capture with colour (with_color=True)")
    height, width = frames.height, frames.width
    total = torch.zeros(len(points), 3, dtype=torch.float64)
    count = torch.zeros(len(points), dtype=torch.float64)
    for i in range(len(frames)):
        depth, colors = frames.depth[i].cpu().reshape(-1), float_colors(frames.colors[i].cpu()).reshape(-1, 3)
        for start in range(0, len(points), chunk):
            part = points[start : start + chunk].float()
            uv, z = project_points(part, frames.K[i].cpu(), frames.cam_to_world[i].cpu())
            pixel = uv.round().long()
            inside = (z > 0) & (pixel[:, 0] >= 0) & (pixel[:, 0] < width) & (pixel[:, 1] >= 0) & (pixel[:, 1] < height)
            index = (pixel[:, 1].clamp(0, height - 1) * width + pixel[:, 0].clamp(0, width - 1))
            reading = depth[index]
            seen = inside & (reading > 0) & ((z - reading).abs() < torch.clamp(3 * kinect_sigma(reading), min=tolerance))
            total[start : start + chunk] += torch.where(seen[:, None], colors[index].double(), 0.0)
            count[start : start + chunk] += seen.double()
    return torch.where(count[:, None] > 0, total / count.clamp_min(1)[:, None], 0.5).float()


def fit_room(frames: DepthFrames, settings: RoomSettings = RoomSettings(), device: str = "cpu") -> RoomFit:
    """Fuse `frames` into a sparse voxel SDF (`fused_voxels`, over `reading_box`), fit it to the frames' rays
    (`ray_equations`, `models.grid.solve_values`), mesh it on its observed cells (`voxel_mesh`) and colour the mesh from the
    frames (`frame_colors`, when `settings.colors` and the frames carry colour). World frame in and out."""
    bounds = reading_box(frames, settings.margin)
    normalization = Normalization.from_points(bounds)
    model = fused_voxels(frames, bounds, settings.voxel, settings.truncation, normalization, device).to(device)
    if settings.iterations:
        equations = ray_equations(frames, normalization, model.voxel, settings.pixel_stride, settings.n_band)
        model = solve_values(model, *equations, settings.prior_weight, settings.iterations)
    mesh = voxel_mesh(model, normalization)
    if settings.colors and frames.colors is not None:
        colors = frame_colors(mesh.vertices, frames, settings.voxel)
        mesh = Mesh(mesh.vertices, mesh.faces, vertex_colors=colors)
    return RoomFit(model, normalization, mesh)
