"""TSDF fusion of depth frames, one concern per module:

- `volume`: `TSDFVolume` (the block grid, `integrate`, `extract_mesh`) and `depth_bounds`;
- `settings`: `FusionSettings`, the fusion rule and its execution (threads, frames per pass, torch.compile);
- `bands`: the blocks that the frames' truncation bands touch;
- `voxels`: the voxel pass, projective signed distances and their running weighted averages;
- `files`: a volume to and from .npz files.
"""

from neuralsurf.baselines.tsdf.settings import WEIGHTINGS, FusionSettings
from neuralsurf.baselines.tsdf.volume import TSDFVolume, available_memory, depth_bounds

__all__ = ["WEIGHTINGS", "FusionSettings", "TSDFVolume", "available_memory", "depth_bounds"]
