"""Rooms fitted at TSDF's cost: a sparse voxel SDF (`models.grid.VoxelSDF`) that starts as the TSDF fusion of the
frames and is refined by `fit` on the same frames' depth rays, then meshed on its observed voxels.

TSDF fusion averages each view's projective distance; the rays then ask the field, over every view at once,
for zero at the hits, the projected distance around them and free space beside depth edges
(`observations.edges.EdgeRays`; any observation of the frames will do). The field has values only at the grid
points fusion observed, so no surface appears in space no frame saw; its mesh is marching cubes of the grid
itself (cells with all corners observed, as TSDF meshes).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from neuralsurf.baselines import TSDFVolume
from neuralsurf.errors import ExtractionError
from neuralsurf.evaluation.methods import NotApplicable, input_box
from neuralsurf.marching import cube_triangles, merge_edge_vertices
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.observations import NotObserved
from neuralsurf.scenes import Scene
from neuralsurf.structures import DepthFrames, Mesh, Normalization
from neuralsurf.training import default_optimizer, fit


def fused_voxels(frames: DepthFrames, bounds: torch.Tensor, voxel: float, truncation: float,
                 normalization: Normalization, device: str = "cpu") -> VoxelSDF:
    """The TSDF fusion of `frames` over the world box `bounds` (Float64[Tensor, "2 3"]) with `voxel`-sized
    voxels and `truncation` (metres), as a unit-frame VoxelSDF of `normalization`: its observed voxels and
    their distances (outside: the truncation)."""
    volume = TSDFVolume(bounds, voxel, truncation, device=device, sparse=True).integrate(frames, progress=False)
    values, weight = volume.to_dense()
    origin = normalization.to_unit(torch.as_tensor(volume.origin, dtype=torch.float64)[None])[0]
    scale = normalization.scale
    return VoxelSDF.from_grid(values.cpu().div_(scale), weight.cpu() > 0, origin.tolist(), voxel / scale,
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


def neural_voxels(scene: Scene, observations: Mapping[str, Callable | None], *, voxel_fraction: float = 1 / 512,
                  truncation_voxels: float = 4.0, margin_fraction: float = 0.05, optimizer: Callable | None = None,
                  trainer: dict[str, Any] | None = None, device: str = "cpu", save_checkpoint: bool = False,
                  seed: int = 0, run_dir: str | Path | None = None, config: dict | None = None) -> Mesh:
    """A method of evaluate.py for depth captures: TSDF fusion with voxels of `voxel_fraction` of the longest side
    of the input's box (truncation `truncation_voxels` voxels, over that box enlarged by `margin_fraction`) as a
    VoxelSDF, refined by `fit` on the scene's `observations` (builders, e.g. EdgeRays.from_scene partials) with
    `optimizer` and `trainer`, meshed on its observed voxels (`voxel_mesh`)."""
    builders = [b for b in observations.values() if b is not None]
    if scene.frames is None or not builders:
        raise NotApplicable("the voxel fit needs depth frames and at least one observation of them")
    try:
        fitted = [build(scene) for build in builders]
    except NotObserved as error:
        raise NotApplicable(str(error)) from None
    bounds, size = input_box(scene, margin_fraction)
    voxel = voxel_fraction * size
    normalization = Normalization.from_points(bounds)  # the box of the input: no second pass over the rays
    model = fused_voxels(scene.frames, bounds, voxel, truncation_voxels * voxel, normalization, device)
    trainer = {**(trainer or {}), "resume": False}
    fit_dir = Path(run_dir) if (run_dir is not None and save_checkpoint) else None
    result = fit(model, fitted, optimizer=optimizer or default_optimizer, device=device, seed=seed,
                 normalization=normalization, run_dir=fit_dir, config=config or {}, **trainer)
    return voxel_mesh(result.model, normalization)
