"""Camera tracking of a depth sequence without poses (KinectFusion, Newcombe et al. 2011).

`track_frames(frames)` returns a camera-to-world pose per frame, the first at `initial_pose`:

- **Frame-to-model** (`mode="model"`, KinectFusion): each frame is registered to the surface raycast
  from the TSDF volume fused so far (`TSDFVolume`), seen from the previous pose, then fused at the pose
  found. The raycast starts each ray at the previous frame's depth (the surface the last fused frame saw
  along it) and steps to the zero crossing of the trilinear TSDF (`raycast_volume`).
- **Frame-to-frame** (`mode="frame"`): each frame is registered to the previous frame's depth; no
  volume, faster, drifts more.

Registration: point-to-plane Gauss-Newton ICP with projective data association (a source point is
matched with the model pixel it projects to), coarse to fine over an image pyramid (2 x 2 block
averages of the depth), with a robust kernel (Huber or Tukey) on the residuals and correspondences
rejected beyond `max_distance` or with normals apart by more than `max_normal_angle`. Frame k starts
from frame k-1's pose moved by the motion from frame k-2 to k-1 (constant velocity).

With colour (`photometric` > 0 and colour images registered to the depth), each Gauss-Newton step also
minimises the grey-level differences between the frame's pixels and the previous frame's image where they
project (direct photometric alignment, as in RGB-D odometry: Steinbruecker et al. 2011, Kerl et al. 2013),
weighted `photometric` metres per unit of grey level against the point-to-plane distances.

VGA frames are registered and fused at half size (`downsample`: 2 x 2 block means, which also average the sensor's
noise; a 2 cm voxel still spans pixels there). On a CPU the two loops that dominate a frame, the raycast's volume sampling and the
ICP iterations' sums, can run compiled (`compiled=True`; `track_frames` compiles long sequences).

Tracking is lost when too few of the frame's points find an inlier (`min_inlier_share`), when their
point-to-plane RMSE is above `max_rmse`, or when the normal equations are degenerate: the tracker raises
`TrackingLostError` naming the frame, instead of fusing it at a wrong pose.

Everything runs on the frames' device (CUDA tensors: CUDA) with vectorised torch ops.
"""

from neuralsurf.baselines.tracking.alignment import (
    FrameFit,
    GreyPair,
    gauss_newton_step,
    icp_equations,
    moved_and_projected,
    photometric_equations,
    photometric_rows,
    point_to_plane_rows,
    point_to_plane_update,
    projective_matches,
    register_maps,
)
from neuralsurf.baselines.tracking.maps import (
    SurfaceMap,
    bilateral_filter,
    depth_pyramid,
    downsample_depth,
    downsample_intrinsics,
    grey_levels,
    grey_pyramid,
    surface_map,
    surface_maps,
    with_gradients,
)
from neuralsurf.baselines.tracking.tracker import (
    MODES,
    Tracker,
    TrackingLostError,
    Trajectory,
    block_slots,
    raycast_volume,
    track_frames,
    trilinear_tsdf,
)

__all__ = [
    "MODES",
    "FrameFit",
    "GreyPair",
    "SurfaceMap",
    "Tracker",
    "TrackingLostError",
    "Trajectory",
    "bilateral_filter",
    "block_slots",
    "depth_pyramid",
    "downsample_depth",
    "downsample_intrinsics",
    "gauss_newton_step",
    "grey_levels",
    "grey_pyramid",
    "icp_equations",
    "moved_and_projected",
    "photometric_equations",
    "photometric_rows",
    "point_to_plane_rows",
    "point_to_plane_update",
    "projective_matches",
    "raycast_volume",
    "register_maps",
    "surface_map",
    "surface_maps",
    "track_frames",
    "trilinear_tsdf",
    "with_gradients",
]
