"""Where depth frames observed a surface: a voxel grid of the frames' votes, which limits where a field
fitted to them is meshed (as TSDF fusion meshes only voxels that frames observed).

A voxel is *observed near the surface* when it holds at least `min_hits` back-projected readings; so is
a neighbour of such a voxel unless, projecting its centre into every frame, more views saw through it
(`free`: their reading lies beyond the centre by more than the band) than read a depth within the band of
it (`near`): a surface measured near a voxel's side may be fitted just across it, but not into the free
space in front of it. Voxels every view saw as free space and space no view saw near a reading are not
observed. (Voting on the voxels that hold readings too, to drop readings the other views contradict,
removed real surfaces seen at grazing angles on 7-Scenes redkitchen: a voxel's centre projects to a pixel
that reads the surface far behind it.) A field is then
evaluated only in the observed voxels and their neighbours and its mesh keeps the faces inside observed
voxels (`extract_observed`): no surface is extrapolated into unseen space, and none is closed against the
edge of what was seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.cameras import frame_readings, kinect_sigma, strided_hits
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.extract import evaluate_grid_points, field_device, make_grid, marching_cubes
from neuralsurf.structures import DepthFrames, Mesh


def _dilate(mask: Tensor) -> Tensor:
    """Bool[Tensor, "X Y Z"] -> the mask grown by one voxel along every axis and diagonal."""
    return torch.nn.functional.max_pool3d(mask[None, None].float(), 3, 1, 1)[0, 0] > 0


def view_votes(centres: Tensor, frames: DepthFrames, band: float, sigma_of_depth=kinect_sigma,
               chunk: int = 8) -> tuple[Tensor, Tensor]:
    """Votes of the frames on world points: (near, free) Int32[Tensor, "n"], the number of views that
    read a depth within max(band, 3 noise sigmas) of the point's depth, and those whose reading lies
    farther than that behind it (they saw through the point). centres: Float64[Tensor, "n 3"]."""
    near = torch.zeros(len(centres), dtype=torch.int32)
    free = torch.zeros(len(centres), dtype=torch.int32)
    for start in range(0, len(frames), chunk):
        K, pose = frames.K[start : start + chunk].cpu().double(), frames.cam_to_world[start : start + chunk].cpu().double()
        z, reading, seen = frame_readings(centres, frames.depth[start : start + chunk].cpu(), K, pose)
        valid = seen & (reading > 0)
        margin = torch.clamp(3 * sigma_of_depth(reading), min=band)
        near += (valid & ((z - reading).abs() <= margin)).sum(0).int()
        free += (valid & (z < reading - margin)).sum(0).int()
    return near, free


@dataclass(frozen=True)
class ObservedSurface:
    """Voxels where depth frames observed a surface (the module's docstring says which)."""

    origin: Tensor
    """Float64[Tensor, "3"]: world corner of voxel (0, 0, 0)."""
    voxel: float
    """Side of the cubic voxels, world units."""
    mask: Tensor
    """Bool[Tensor, "X Y Z"]: voxels observed near the surface."""

    @classmethod
    def from_frames(cls, frames: DepthFrames, voxel: float, band: float | None = None, min_hits: int = 2,
                    pixel_stride: int = 2, max_free_ratio: float | None = 1.0,
                    sigma_of_depth=kinect_sigma) -> ObservedSurface:
        """The observed voxels of `frames` (world frame) on a grid of `voxel`-sized cubes over their
        readings: those with `min_hits` readings of every `pixel_stride`-th pixel, and their neighbours with
        at most `max_free_ratio` times as many `free` as `near` votes (`view_votes` of the centre, with
        `band`: by default the voxel's half diagonal; None: every neighbour)."""
        if not (voxel > 0 and min_hits >= 1 and pixel_stride >= 1):
            raise ConfigError(f"ObservedSurface needs voxel > 0, min_hits >= 1 and pixel_stride >= 1, got "
                              f"voxel={voxel}, min_hits={min_hits}, pixel_stride={pixel_stride}")
        valid = frames.depth > 0
        if not valid.any():
            raise InputError(f"all {frames.depth.numel()} depth pixels of the {len(frames)} frames are missing (0); "
                             f"no surface was observed: check the depth scale (metres) and the invalid-value code")
        band = 0.5 * 3**0.5 * voxel if band is None else band
        points = strided_hits(frames, pixel_stride)
        origin = points.min(0).values - 2 * voxel  # every neighbour of a reading's voxel inside the grid
        shape = tuple((((points.max(0).values - origin) / voxel).floor().long() + 3).tolist())
        cells = ((points - origin) / voxel).floor().long()
        counts = torch.bincount((cells[:, 0] * shape[1] + cells[:, 1]) * shape[2] + cells[:, 2],
                                minlength=shape[0] * shape[1] * shape[2]).reshape(shape)
        candidate = counts >= min_hits
        shell = _dilate(candidate) & ~candidate
        cells = (candidate | shell).nonzero()
        near, free = view_votes(origin + (cells.double() + 0.5) * voxel, frames, band, sigma_of_depth)
        trusted = max_free_ratio is None
        agreed = trusted | (free <= (max_free_ratio or 0.0) * near)
        has_hits = candidate[tuple(cells.T)]
        observed = torch.zeros(shape, dtype=torch.bool)
        observed[tuple(cells[has_hits].T)] = True
        mask = observed.clone()
        neighbours = cells[~has_hits & agreed]  # beside an observed voxel and not seen through
        mask[tuple(neighbours[_dilate(observed)[tuple(neighbours.T)]].T)] = True
        return cls(origin, float(voxel), mask)

    @property
    def bounds(self) -> Tensor:
        """Float64[Tensor, "2 3"]: world box of the grid."""
        return torch.stack([self.origin, self.origin + torch.tensor(self.mask.shape) * self.voxel])

    def contains(self, points: Tensor, grown: bool = False) -> Tensor:
        """Bool[Tensor, "..."]: world points (Float[Tensor, "... 3"]) inside an observed voxel (`grown`: or
        one of its neighbours)."""
        mask = _dilate(self.mask) if grown else self.mask
        return self._lookup(mask, points)

    def _lookup(self, mask: Tensor, points: Tensor) -> Tensor:
        cells = ((points.detach().double().cpu() - self.origin) / self.voxel).floor().long()
        inside = ((cells >= 0) & (cells < torch.tensor(mask.shape))).all(-1)
        found = torch.zeros(points.shape[:-1], dtype=torch.bool)
        c = cells[inside]
        found[inside] = mask[c[..., 0], c[..., 1], c[..., 2]]
        return found.to(points.device)

    def crop(self, mesh: Mesh) -> Mesh:
        """`mesh` without the faces whose centroid lies outside the observed voxels (and without the
        vertices no face uses). Raises InputError when no face remains."""
        centroids = mesh.vertices.double()[mesh.faces].mean(1)
        faces = mesh.faces[self.contains(centroids).to(mesh.faces.device)]
        if not len(faces):
            raise InputError("no face of the mesh lies in an observed voxel: the mesh and the frames are not in "
                             "the same frame, or the field has no surface where the frames saw one")
        used, faces = torch.unique(faces, return_inverse=True)
        colors = mesh.vertex_colors[used] if mesh.vertex_colors is not None else None
        return Mesh(mesh.vertices[used], faces.reshape(-1, 3), colors)


def observed_points(observed: ObservedSurface, n: int, generator: torch.Generator) -> Tensor:
    """Float64[Tensor, "n 3"]: world points drawn uniformly in the observed voxels of `observed` and their
    neighbours (each voxel equally likely)."""
    cells = _dilate(observed.mask).nonzero()
    pick = cells[torch.randint(len(cells), (n,), generator=generator)]
    return observed.origin + (pick.double() + torch.rand(n, 3, generator=generator, dtype=torch.float64)) * observed.voxel


def extract_observed(field, observed: ObservedSurface, resolution: int = 512, chunk_size: int = 65_536,
                     level: float = 0.0, progress: bool = False) -> Mesh:
    """Marching cubes of the `level` set of `field` (world x[..., 3] -> f[...]) evaluated only at the grid
    points inside the observed voxels of `observed` and their neighbours, its faces kept inside the
    observed voxels (`ObservedSurface.crop`): the surface only where the frames saw one, never closed
    against the edge of what they saw. `resolution`: cells along the longest side of the observed box;
    `chunk_size`: points per field call. Raises ExtractionError when the field has no surface there."""
    grid = make_grid(observed.bounds.numpy(), resolution)
    grown = _dilate(observed.mask).numpy()
    axes = [np.floor((grid.origin[a] + np.arange(n) * grid.spacing - float(observed.origin[a])) / observed.voxel)
            .astype(np.int64) for a, n in enumerate(grid.shape)]
    inside = [(i >= 0) & (i < grown.shape[a]) for a, i in enumerate(axes)]
    axes = [np.clip(i, 0, grown.shape[a] - 1) for a, i in enumerate(axes)]
    evaluated = grown[np.ix_(*axes)] & inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
    values = np.full(grid.shape, level + 1.0, dtype=np.float32)
    index = np.argwhere(evaluated)
    values[evaluated] = evaluate_grid_points(field, grid, index, chunk_size, field_device(field, None), progress, "extract")
    return observed.crop(marching_cubes(values, grid, level, valid=evaluated))

