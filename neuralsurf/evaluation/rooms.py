"""Rooms fitted at TSDF's cost: a sparse voxel SDF (`models.grid.VoxelSDF`) that starts as the TSDF fusion of the
frames and is then fitted to the same frames' depth rays, then meshed on its observed voxels.

TSDF fusion averages each view's projective distance, so a thin surface seen by some views is cancelled by the
free-space votes of the views that see past it. The fit asks the field, over every view at once, for zero at
the hits and the distance along the surface normal in a band around them (`ray_equations`), held to its start
where the rays say nothing: the field is linear in its grid values, so this is one sparse least-squares problem,
solved by conjugate gradients (`solve_on_rays`). The field has values only at the grid points fusion observed,
so no surface appears in space no frame saw; its mesh is marching cubes of the grid itself (cells with all
corners observed, as TSDF meshes).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from neuralsurf.baselines import TSDFVolume
from neuralsurf.devices import resolve_device
from neuralsurf.errors import ConfigError, ExtractionError
from neuralsurf.evaluation.methods import NotApplicable, input_box, scene_input
from neuralsurf.geometry import kinect_sigma
from neuralsurf.marching import cube_triangles, merge_edge_vertices
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.observations.observed import stride_frames
from neuralsurf.observations.rays import depth_rays
from neuralsurf.scenes import Scene
from neuralsurf.structures import DepthFrames, Mesh, Normalization


def fused_voxels(frames: DepthFrames, bounds: torch.Tensor, voxel: float, truncation: float,
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
def solve_on_rays(model: VoxelSDF, points: Tensor, targets: Tensor, weights: Tensor, prior_weight: float = 10.0,
                  iterations: int = 5) -> VoxelSDF:
    """`model` with its values v fitted to the equations model(points) = targets (Float[Tensor, "m 3"],
    Float[Tensor, "m"], weighted by Float[Tensor, "m"]) and held to their start v0: the minimum of
    sum weights (A v - targets)^2 + lam |v - v0|^2, lam = `prior_weight` x the mean data weight of a value (a value
    no equation touches keeps its start), by `iterations` steps of Jacobi-preconditioned conjugate gradients from
    v0. Points with no observed corner are left out (the field reads `outside` there, whatever v)."""
    if not prior_weight > 0 or iterations < 0:
        raise ConfigError(f"solve_on_rays needs prior_weight > 0 and iterations >= 0, got {prior_weight} and {iterations}")
    device = model.values.device
    rows, w = model.corners(points.to(device))
    used = w.sum(-1) > 0
    if not used.any():
        return model
    rows, w, targets, weights = rows[used], w[used], targets.to(device)[used], weights.to(device)[used]
    flat = rows.reshape(-1)
    start = model.values[:, 0].clone()

    def gather(per_equation: Tensor) -> Tensor:  # A^T diag(weights) per_equation
        return torch.zeros_like(start).index_add_(0, flat, (w * (weights * per_equation)[:, None]).reshape(-1))

    diagonal = torch.zeros_like(start).index_add_(0, flat, (w * w * weights[:, None]).reshape(-1))
    lam = prior_weight * diagonal[diagonal > 0].mean()
    preconditioner = 1 / (diagonal + lam)

    def normal(v: Tensor) -> Tensor:  # (A^T W A + lam) v
        return gather((w * v[rows]).sum(-1)) + lam * v

    values = start.clone()
    residual = gather(targets) + lam * start - normal(values)
    z = preconditioner * residual
    direction, rz = z.clone(), (residual * z).sum()
    for _ in range(iterations):
        if rz <= 0:
            break
        product = normal(direction)
        step = rz / (direction * product).sum()
        values += step * direction
        residual -= step * product
        z = preconditioner * residual
        rz, previous = (residual * z).sum(), rz
        direction = z + (rz / previous) * direction
    model.values[:, 0] = values
    return model


def neural_voxels(scene: Scene, *, voxel_fraction: float = 1 / 512, truncation_voxels: float = 4.0,
                  margin_fraction: float = 0.02, pixel_stride: int = 8, n_band: int = 2, prior_weight: float = 10.0,
                  iterations: int = 5, device: str = "auto", seed: int = 0, run_dir: str | Path | None = None,
                  config: dict | None = None) -> Mesh:
    """A method of evaluate.py for depth captures: TSDF fusion with voxels of `voxel_fraction` of the longest side
    of the input's box (truncation `truncation_voxels` voxels, over that box enlarged by `margin_fraction`) as a
    VoxelSDF, fitted to the rays of every `pixel_stride`-th pixel (`ray_equations`, `solve_on_rays`), meshed on
    its observed voxels (`voxel_mesh`). `seed`, `run_dir` and `config` are taken as every method takes them; the
    solve is deterministic and writes nothing."""
    if scene.frames is None:
        raise NotApplicable(f"the voxel fit needs depth frames; {scene_input(scene)}")
    device = str(resolve_device(device))
    bounds, size = input_box(scene, margin_fraction)
    voxel = voxel_fraction * size
    normalization = Normalization.from_points(bounds)  # the box of the input: no second pass over the rays
    model = fused_voxels(scene.frames, bounds, voxel, truncation_voxels * voxel, normalization, device).to(device)
    equations = ray_equations(scene.frames, normalization, model.voxel, pixel_stride, n_band)
    return voxel_mesh(solve_on_rays(model, *equations, prior_weight, iterations), normalization)
