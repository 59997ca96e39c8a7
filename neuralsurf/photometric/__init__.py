"""Photometric stereo, chrome-ball calibration and normal integration, batched in PyTorch (CPU or CUDA:
the inputs' device).

Frames: the project's camera frame (OpenCV: x right, y down, z forward). Light directions point from
the surface towards the light; normals facing the camera have z < 0. Pixel (u, v) = (column, row).

- `stereo`: normals and albedo from images under known lights (least squares, trimmed, robust).
- `calibration`: light directions from a chrome ball.
- `integration`: depth from a normal map (least squares, bilateral) and depth error.
"""

from neuralsurf.photometric.calibration import (
    ChromeBallCalibration,
    calibrate_chrome_ball,
    reflect_view,
    sphere_from_mask,
)
from neuralsurf.photometric.integration import (
    INTEGRATORS,
    DepthError,
    NormalIntegration,
    continuous_pieces,
    depth_error,
    discontinuities,
    integrate_bilateral,
    integrate_least_squares,
)
from neuralsurf.photometric.stereo import (
    METHODS,
    AngularError,
    PhotometricStereoResult,
    angular_error,
    least_squares_stereo,
    photometric_stereo,
    render_lambertian,
    robust_stereo,
    trimmed_stereo,
)

__all__ = [
    "INTEGRATORS",
    "METHODS",
    "AngularError",
    "ChromeBallCalibration",
    "DepthError",
    "NormalIntegration",
    "PhotometricStereoResult",
    "angular_error",
    "calibrate_chrome_ball",
    "continuous_pieces",
    "depth_error",
    "discontinuities",
    "integrate_bilateral",
    "integrate_least_squares",
    "least_squares_stereo",
    "photometric_stereo",
    "reflect_view",
    "render_lambertian",
    "robust_stereo",
    "sphere_from_mask",
    "trimmed_stereo",
]
