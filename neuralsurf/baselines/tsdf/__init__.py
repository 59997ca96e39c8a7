"""TSDF fusion of depth frames, one concern per module:

- `volume`: `TSDFVolume` (the block grid, `integrate`, `extract_mesh`) and `depth_bounds`;
- `bands`: the blocks that the frames' truncation bands touch;
- `voxels`: the voxel pass, projective signed distances and their running weighted averages;
- `files`: a volume to and from .npz files.
"""

from neuralsurf.baselines.tsdf.volume import WEIGHTINGS, TSDFVolume, available_memory, depth_bounds

__all__ = ["WEIGHTINGS", "TSDFVolume", "available_memory", "depth_bounds"]
