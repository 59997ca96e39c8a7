"""Camera trajectories and depth-sensor intrinsics.

- `write_tum_trajectory`: TUM RGB-D text, one line `timestamp tx ty tz qx qy qz qw` per frame (the camera's
  position and orientation in the world, Hamilton quaternion scalar last), as `groundtruth.txt`.
- `write_trajectory_log`: Redwood / Open3D `.log`, per frame a line `id id n` then the 4 x 4
  camera-to-world matrix (`io.rgbd.read_trajectory_log` reads it back).
- `sensor_intrinsics`: the 3 x 3 K of a named depth sensor (SENSORS), for captures that come without a
  calibration file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neuralsurf.errors import ConfigError, InputError

SENSORS = {
    "primesense": (525.0, 525.0, 319.5, 239.5, 640, 480),
    "kinect_v1": (525.0, 525.0, 319.5, 239.5, 640, 480),
    "kinect_v2": (365.5, 365.5, 255.5, 211.5, 512, 424),
    "realsense_d435": (383.0, 383.0, 319.5, 239.5, 640, 480),
}
"""Nominal depth-camera intrinsics (fx, fy, cx, cy, width, height): PrimeSense / Kinect v1 (the ROS and
Redwood default), Kinect v2's depth camera, RealSense D435's depth stream at 640x480. A unit's own
calibration is more accurate: pass K where one exists."""


def sensor_intrinsics(sensor: str | None, width: int | None = None, height: int | None = None) -> np.ndarray:
    """Float64[ndarray, "3 3"] K of a named sensor (SENSORS). ConfigError naming the options when `sensor`
    is None or unknown, or when the images' `width` x `height` (if given) is not the preset's."""
    options = ", ".join(SENSORS)
    if sensor is None:
        raise ConfigError(
            f"the capture has no intrinsics: pass K (3x3), put a calibration file in the folder, or name the "
            f"sensor (sensor= one of {options})"
        )
    if sensor not in SENSORS:
        raise ConfigError(f"unknown sensor {sensor!r}; use one of {options}, or pass K (3x3)")
    fx, fy, cx, cy, w, h = SENSORS[sensor]
    if (width is not None and width != w) or (height is not None and height != h):
        raise ConfigError(
            f"sensor {sensor!r} images are {w}x{h} but these are {width}x{height}; pass K (3x3) for this "
            f"resolution or another sensor ({options})"
        )
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Float[ndarray, "n 3 3"] rotations -> Float64[ndarray, "n 4"] unit quaternions (x, y, z, w), w >= 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_quat()
    return np.where(q[:, 3:] < 0, -q, q)


def _poses(cam_to_world) -> np.ndarray:
    poses = np.asarray(cam_to_world, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.isfinite(poses).all():
        raise InputError(f"a trajectory is finite camera-to-world poses (n, 4, 4), got shape {poses.shape}")
    return poses


def _write_atomic(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)
    return path


def write_tum_trajectory(path, cam_to_world, timestamps=None, fps: float = 30.0) -> Path:
    """Write poses Float[ndarray | Tensor, "n 4 4"] as a TUM trajectory; `timestamps` (n,) seconds, default
    frame index / `fps`. Returns the path."""
    poses = _poses(cam_to_world)
    stamps = np.arange(len(poses)) / fps if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    if stamps.shape != (len(poses),):
        raise InputError(f"{len(poses)} poses need {len(poses)} timestamps, got shape {stamps.shape}")
    quaternions = rotation_to_quaternion(poses[:, :3, :3])
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join([f"{t:.6f}"] + [f"{x:.9f}" for x in (*p[:3, 3], *q)])
              for t, p, q in zip(stamps, poses, quaternions)]
    return _write_atomic(Path(path), "\n".join(lines) + "\n")


def write_trajectory_log(path, cam_to_world, ids=None) -> Path:
    """Write poses Float[ndarray | Tensor, "n 4 4"] as a Redwood / Open3D .log; `ids` (n,) frame ids, default
    0 .. n-1. Returns the path."""
    poses = _poses(cam_to_world)
    ids = np.arange(len(poses)) if ids is None else np.asarray(ids, dtype=np.int64)
    lines = []
    for i, pose in zip(ids, poses):
        lines.append(f"{i} {i} {i + 1}")
        lines += [" ".join(f"{x:.9f}" for x in row) for row in pose]
    return _write_atomic(Path(path), "\n".join(lines) + "\n")


__all__ = ["SENSORS", "rotation_to_quaternion", "sensor_intrinsics", "write_trajectory_log", "write_tum_trajectory"]
