"""Rigid registration of point clouds, one concern per module (as Open3D splits its registration):

- `estimation`: input checks, robust kernels and transformation estimations (point to point, point to plane);
- `icp`: `register_icp` (our reference loop and Open3D's engines), `register_meshes`, `Registration`;
- `global_registration`: `register_global`, FPFH features with a seeded RANSAC;
- `multiway`: `register_multiway`, a pose graph of pairwise ICP edges.
"""

from neuralsurf.baselines.registration.estimation import kabsch, point_to_plane_step, voxel_downsample
from neuralsurf.baselines.registration.global_registration import (
    match_features,
    ransac_rigid,
    register_global,
)
from neuralsurf.baselines.registration.icp import (
    Registration,
    evaluate_registration,
    register_icp,
    register_meshes,
)
from neuralsurf.baselines.registration.multiway import register_multiway

__all__ = [
    "Registration",
    "evaluate_registration",
    "kabsch",
    "match_features",
    "point_to_plane_step",
    "ransac_rigid",
    "register_global",
    "register_icp",
    "register_meshes",
    "register_multiway",
    "voxel_downsample",
]
