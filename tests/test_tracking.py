"""Camera tracking (neuralsurf.baselines.tracking), trajectory metrics and trajectory files.

Oracles: a synthetic room (boxes and a sphere inside a box room, depth rendered with Kinect noise along
a known path) tracked to a known ATE; a frame of another scene detected as lost; hand-computed pyramid
levels, ICP steps and trajectory errors; the numpy point-to-plane step of the ICP baseline as reference.
"""

from __future__ import annotations

import math
import subprocess
import sys
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralsurf.baselines.registration import point_to_plane_step
from neuralsurf.baselines.registration.estimation import axis_angle_to_matrix as rodrigues
from neuralsurf.baselines.tracking import (
    GreyPair,
    Tracker,
    TrackingLostError,
    downsample_depth,
    downsample_intrinsics,
    grey_pyramid,
    photometric_rows,
    point_to_plane_update,
    raycast_volume,
    register_maps,
    surface_maps,
    track_frames,
    with_gradients,
)
from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.io.rgbd import read_depth_frames, read_trajectory_log, tum_trajectory_to_poses
from neuralsurf.io.trajectories import sensor_intrinsics, write_trajectory_log, write_tum_trajectory
from neuralsurf.metrics import absolute_trajectory_error, align_trajectory, relative_pose_error
from neuralsurf.scenes.analytic import Box, Sphere
from neuralsurf.scenes.scanner import intrinsics_from_fov, look_at, scan_depth
from neuralsurf.structures import DepthFrames, Mesh


def axis_angle_to_matrix(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' rotation Float64[Tensor, "3 3"] of an axis-angle Float64[Tensor, "3"]."""
    return torch.from_numpy(rodrigues(omega.numpy()))


REPO = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT = 160, 120


def _merge(meshes: list[Mesh]) -> Mesh:
    vertices, faces, offset = [], [], 0
    for mesh in meshes:
        vertices.append(mesh.vertices.double())
        faces.append(mesh.faces + offset)
        offset += len(mesh.vertices)
    return Mesh(torch.cat(vertices), torch.cat(faces))


@lru_cache(maxsize=1)
def room() -> Mesh:
    """A 4 x 2.6 x 4 m room (floor at y = 0) with three boxes and a sphere."""
    parts = [
        Box((0.0, 1.3, 0.0), (2.0, 1.3, 2.0)),
        Box((-0.9, 0.4, -1.2), (0.4, 0.4, 0.3)),
        Box((0.8, 0.25, -1.0), (0.3, 0.25, 0.5)),
        Box((1.5, 1.0, 0.2), (0.2, 1.0, 0.4)),
    ]
    return _merge([p.mesh() for p in parts] + [Sphere((0.1, 0.6, -1.5), 0.3).mesh(4)])


def path(n: int) -> torch.Tensor:
    """Float64[Tensor, "n 4 4"]: a camera walking 3 cm and turning ~1 degree a frame, looking into the room."""
    poses = []
    for k in range(n):
        s = k / max(n - 1, 1)
        eye = (-0.4 + 0.8 * s, 1.4 + 0.1 * math.sin(3 * s), 1.3 - 0.2 * s)
        target = (-0.3 + 0.6 * s, 0.6, -1.5)
        poses.append(look_at(eye, target))
    return torch.stack(poses)


def capture(poses: torch.Tensor, mesh: Mesh | None = None, seed: int = 0, K: torch.Tensor | None = None,
            width: int = WIDTH, height: int = HEIGHT) -> DepthFrames:
    """Kinect-noise depth of `mesh` (default the room) seen at `poses` through K (default a 45-degree view)."""
    K = intrinsics_from_fov(width, height, 45.0) if K is None else K
    return scan_depth(mesh or room(), width=width, height=height, noise="kinect", seed=seed,
                      cam_to_world=poses, K=K.expand(len(poses), 3, 3))


SETTINGS = {"voxel_size": 0.02, "margin": 1.0, "smoothing": 1}  # small noisy frames: filtered


# ----------------------------------------------------------------------------- tracking


N_FRAMES = 16


@lru_cache(maxsize=2)
def tracked(mode: str):
    """(trajectory of `mode` on the synthetic room, the true poses relative to the first)."""
    truth = path(N_FRAMES)
    trajectory = track_frames(capture(truth), progress=False, mode=mode, **SETTINGS)
    return trajectory, truth[0].inverse() @ truth  # the tracker starts at the identity


@pytest.mark.parametrize("mode, bound", [("model", 0.006), ("frame", 0.012)])
def test_synthetic_room_is_tracked_within_a_known_ate(mode, bound):
    trajectory, truth = tracked(mode)
    assert trajectory.cam_to_world.shape == (N_FRAMES, 4, 4)
    assert torch.equal(trajectory.cam_to_world[0], torch.eye(4, dtype=torch.float64))
    assert absolute_trajectory_error(trajectory.cam_to_world, truth) < bound
    assert (trajectory.inlier_share[1:] > 0.5).all()
    # unaligned too: the first pose is fixed, so the drift itself is bounded
    assert float((trajectory.cam_to_world[:, :3, 3] - truth[:, :3, 3]).norm(dim=1).max()) < 3 * bound


def test_frame_to_model_drifts_less_than_frame_to_frame():
    (model, truth), (frame, _) = tracked("model"), tracked("frame")
    assert absolute_trajectory_error(model.cam_to_world, truth) < absolute_trajectory_error(frame.cam_to_world, truth)


def test_a_frame_of_another_scene_is_reported_as_lost():
    truth = path(8)
    frames = capture(truth)
    elsewhere = capture(truth[:1], _merge([Sphere((0.0, 0.0, 0.0), 0.5).mesh(4),
                                           Box((0.0, -0.8, 0.0), (1.0, 0.05, 1.0)).mesh()]))
    K = frames.K[0]
    depth = torch.cat([frames.depth[:5], elsewhere.depth, frames.depth[5:]])
    mixed = DepthFrames(depth, K.expand(len(depth), 3, 3), torch.eye(4).expand(len(depth), 4, 4))
    with pytest.raises(TrackingLostError, match="frame 5") as lost:
        track_frames(mixed, progress=False, **SETTINGS)
    assert lost.value.frame == 5
    assert lost.value.inlier_share < 0.3 or lost.value.rmse > 0.03


def test_views_registered_to_the_mesh_recover_their_poses():
    """Held-out views given 1 cm and half a degree off their true poses are registered back onto the true mesh
    (`localised_poses`, the scoring of meshes made at tracked poses) to within 2 mm and 0.05 degrees."""
    from neuralsurf.evaluation.rooms import localised_poses

    truth = path(6)[::2]
    offset = torch.eye(4, dtype=torch.float64)
    offset[:3, :3] = axis_angle_to_matrix(torch.tensor([0.006, -0.004, 0.003], dtype=torch.float64))
    offset[:3, 3] = torch.tensor([0.008, -0.006, 0.005])
    frames = capture(truth)
    given = DepthFrames(frames.depth, frames.K, (truth @ offset).float())
    poses, lost = localised_poses(room(), given)
    assert lost == 0
    error = torch.linalg.inv(truth) @ poses
    assert float(error[:, :3, 3].norm(dim=1).max()) < 0.002
    angle = torch.arccos(((error[:, :3, :3].diagonal(dim1=1, dim2=2).sum(1) - 1) / 2).clamp(-1, 1))
    assert float(angle.max()) < math.radians(0.05)
    before = torch.linalg.inv(truth) @ given.cam_to_world.double()
    assert float(before[:, :3, 3].norm(dim=1).min()) > 0.009  # it moved them


def test_raycast_of_a_fused_plane_is_its_depth():
    K = intrinsics_from_fov(WIDTH, HEIGHT, 45.0).float()
    depth = torch.full((HEIGHT, WIDTH), 1.5)
    tracker = Tracker(K, **SETTINGS)
    tracker.track(depth)
    guide = torch.full_like(depth, 1.45)
    assert (raycast_volume(tracker.volume, guide, K, torch.eye(4), steps=1) == 0).all()  # 5 cm off: not trusted
    ray = raycast_volume(tracker.volume, guide, K, torch.eye(4), steps=2)
    inner = ray[10:-10, 10:-10]
    assert (inner > 0).all()
    assert float((inner - 1.5).abs().max()) < 1e-3


# ----------------------------------------------------------------------------- pyramid and ICP step


def test_downsample_depth_hand_computed():
    depth = torch.tensor([
        [1.0, 1.0, 2.0, 0.0],
        [1.0, 0.0, 2.2, 5.0],
        [0.0, 0.0, 3.0, 3.01],
        [0.0, 0.0, 3.02, 3.03],
    ])
    expected = torch.tensor([[1.0, 2.1], [0.0, 3.015]])  # nearer surface kept across the 2 -> 5 jump
    assert torch.allclose(downsample_depth(depth, max_jump=0.25), expected)


def test_downsampled_intrinsics_see_points_at_the_block_centre():
    K = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]], dtype=torch.float64)
    point = torch.tensor([0.3, -0.2, 2.0], dtype=torch.float64)
    u, v, _ = K @ point / point[2]
    u2, v2, _ = downsample_intrinsics(K) @ point / point[2]
    assert math.isclose(u2, (u - 0.5) / 2) and math.isclose(v2, (v - 0.5) / 2)
    # a block of pixels (0, 0) (1, 0) (0, 1) (1, 1) lands at half-pixel (0, 0)
    assert torch.allclose(downsample_intrinsics(K)[:2, 2], torch.tensor([159.5, 119.5], dtype=torch.float64))


def test_one_icp_step_recovers_a_translation_of_three_planes_exactly():
    g = torch.Generator().manual_seed(0)
    rows = []
    for axis in range(3):  # points on the planes x = 1, y = 1, z = 1 with their normals
        p = torch.rand(50, 3, generator=g, dtype=torch.float64)
        p[:, axis] = 1.0
        n = torch.zeros(50, 3, dtype=torch.float64)
        n[:, axis] = 1.0
        rows.append((p, n))
    target = torch.cat([p for p, _ in rows])
    normals = torch.cat([n for _, n in rows])
    shift = torch.tensor([0.02, -0.01, 0.03], dtype=torch.float64)
    step = point_to_plane_update(target + shift, target, normals, torch.ones(len(target), dtype=torch.float64))
    assert torch.allclose(step[:3, :3], torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(step[:3, 3], -shift, atol=1e-12)


def test_icp_step_matches_the_numpy_reference():
    g = torch.Generator().manual_seed(1)
    target = torch.rand(200, 3, generator=g, dtype=torch.float64)
    normals = torch.nn.functional.normalize(torch.randn(200, 3, generator=g, dtype=torch.float64), dim=1)
    rotation = axis_angle_to_matrix(torch.tensor([0.02, -0.01, 0.015], dtype=torch.float64))
    source = target @ rotation.T + torch.tensor([0.01, 0.0, -0.02], dtype=torch.float64)
    weights = torch.rand(200, generator=g, dtype=torch.float64)
    ours = point_to_plane_update(source, target, normals, weights)
    reference = point_to_plane_step(source.numpy(), target.numpy(), normals.numpy(), weights.numpy())
    assert np.allclose(ours.numpy(), reference, atol=1e-10)


def textured_plane_view(shift: tuple[float, float], K: torch.Tensor, width: int = 160, height: int = 120
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth Float[Tensor, "h w"] and grey levels Float[Tensor, "h w"] of the plane z = 1 painted with
    0.5 + 0.25 sin(2 pi X / 0.2) sin(2 pi Y / 0.15) (world X, Y), seen by a camera at (shift, 0) looking
    along z, in closed form."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    x, y = (u - K[0, 2]) / K[0, 0] + shift[0], (v - K[1, 2]) / K[1, 1] + shift[1]
    grey = 0.5 + 0.25 * torch.sin(2 * math.pi * x / 0.2) * torch.sin(2 * math.pi * y / 0.15)
    return torch.ones(height, width, dtype=torch.float64), grey


def test_grey_levels_pin_down_the_slide_along_a_plane_that_depth_cannot():
    K = torch.tensor([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]], dtype=torch.float64)
    shift = (0.02, -0.01)
    model_depth, model_grey = textured_plane_view((0.0, 0.0), K)
    source_depth, source_grey = textured_plane_view(shift, K)
    source, model = surface_maps(source_depth, K, 3, 0.05), surface_maps(model_depth, K, 3, 0.05)
    settings = {"iterations": (10, 10, 10), "kernel": "huber", "kernel_scale": 0.01, "max_distance": 0.1,
                    "min_cosine": 0.9}
    start = torch.eye(4, dtype=torch.float64)
    assert register_maps(source, model, start, **settings).degenerate  # a plane leaves 3 of 6 motions free
    grey = GreyPair(grey_pyramid(source_grey, 3), [with_gradients(g) for g in grey_pyramid(model_grey, 3)], 1.0)
    fit = register_maps(source, model, start, **settings, grey=grey)
    assert not fit.degenerate
    assert torch.allclose(fit.transform[:3, 3], torch.tensor([*shift, 0.0], dtype=torch.float64), atol=5e-4)
    assert torch.allclose(fit.transform[:3, :3], torch.eye(3, dtype=torch.float64), atol=1e-3)


def test_photometric_jacobian_is_the_derivative_of_the_residual():
    K = torch.tensor([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]], dtype=torch.float64)
    _, grey = textured_plane_view((0.0, 0.0), K)
    image = with_gradients(grey)
    g = torch.Generator().manual_seed(0)
    points = torch.cat([torch.rand(100, 2, generator=g, dtype=torch.float64) * 0.4 - 0.2,
                        torch.full((100, 1), 1.0, dtype=torch.float64)], 1)
    values = torch.rand(100, generator=g, dtype=torch.float64)
    rows, inside = photometric_rows(points, values, torch.eye(4, dtype=torch.float64), image, K)
    assert inside.all()
    for axis in range(6):  # central differences of the residual along each motion direction
        step = torch.zeros(6, dtype=torch.float64)
        step[axis] = 1e-5
        moved = []
        for sign in (1, -1):
            motion = torch.eye(4, dtype=torch.float64)
            motion[:3, :3], motion[:3, 3] = axis_angle_to_matrix(sign * step[:3]), sign * step[3:]
            moved.append(photometric_rows(points, values, motion, image, K)[0][:, 6])
        numeric = (moved[0] - moved[1]) / 2e-5
        # bilinear sampling is piecewise linear: its derivative is the central difference only on average
        assert torch.corrcoef(torch.stack([numeric, rows[:, axis]]))[0, 1] > 0.98


def test_axis_angle_to_matrix_is_rodrigues():
    omega = torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64)
    expected = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(axis_angle_to_matrix(omega), expected, atol=1e-12)
    assert torch.equal(axis_angle_to_matrix(torch.zeros(3, dtype=torch.float64)), torch.eye(3, dtype=torch.float64))


def test_bad_settings_fail_early():
    K = torch.eye(3)
    with pytest.raises(ConfigError, match="tracking mode"):
        Tracker(K, mode="slam")
    with pytest.raises(ConfigError, match="robust kernel"):
        Tracker(K, kernel="cauchy")
    with pytest.raises(ConfigError, match="iterations"):
        Tracker(K, levels=2, iterations=(4, 5, 10))
    with pytest.raises(ConfigError, match="photometric"):
        Tracker(K, photometric=-1)
    frames = capture(path(2))
    with pytest.raises(InputError, match="colour images"):
        track_frames(frames, progress=False, photometric=0.5)


# ----------------------------------------------------------------------------- trajectory metrics


def _rz(degrees: float) -> torch.Tensor:
    return axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(degrees)], dtype=torch.float64))


def test_ate_of_a_rigidly_moved_trajectory_is_zero():
    truth = path(10)
    motion = torch.eye(4, dtype=torch.float64)
    motion[:3, :3], motion[:3, 3] = _rz(40.0) @ axis_angle_to_matrix(torch.tensor([0.3, 0, 0.1],
                                                                                 dtype=torch.float64)), torch.tensor([1.0, -2, 3])
    moved = motion @ truth
    assert absolute_trajectory_error(moved, truth) < 1e-9
    assert torch.allclose(align_trajectory(moved, truth), motion.inverse(), atol=1e-9)
    rpe = relative_pose_error(moved, truth)
    assert rpe.translation < 1e-9 and rpe.rotation < 1e-5


def test_ate_of_a_saddle_offset_is_the_offset():
    reference = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    corners = torch.tensor([[1.0, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]], dtype=torch.float64)
    reference[:, :3, 3] = corners
    estimated = reference.clone()
    estimated[:, 2, 3] = torch.tensor([0.05, -0.05, 0.05, -0.05], dtype=torch.float64)  # z = 0.05 sign(x y): no rigid motion fits it
    assert math.isclose(absolute_trajectory_error(estimated, reference), 0.05, rel_tol=1e-9)


def test_rpe_of_a_known_drift():
    n = 6
    reference = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    estimated = reference.clone()
    for k in range(n):  # each frame: 0.1 m further along x and 2 degrees more about z
        estimated[k, :3, :3] = _rz(2.0 * k)
        estimated[k, 0, 3] = 0.1 * k
    rpe = relative_pose_error(estimated, reference)
    assert math.isclose(rpe.translation, 0.1, rel_tol=1e-9)
    assert math.isclose(rpe.rotation, 2.0, rel_tol=1e-6)
    over_two = relative_pose_error(estimated, reference, delta=2)
    assert math.isclose(over_two.translation, 0.2, rel_tol=1e-9)
    assert math.isclose(over_two.rotation, 4.0, rel_tol=1e-6)


# ----------------------------------------------------------------------------- trajectory files and sensors


def test_trajectory_files_read_back(tmp_path):
    truth = path(5)
    ids, poses = read_trajectory_log(write_trajectory_log(tmp_path / "out" / "trajectory.log", truth))
    assert ids.tolist() == [0, 1, 2, 3, 4]
    assert np.allclose(poses, truth.numpy(), atol=1e-8)
    table = np.loadtxt(write_tum_trajectory(tmp_path / "trajectory.txt", truth, fps=30.0))
    assert np.allclose(table[:, 0], np.arange(5) / 30.0)
    assert np.allclose(tum_trajectory_to_poses(table[:, 1:]), truth.numpy(), atol=1e-8)


def test_sensor_presets_and_the_error_naming_them():
    K = sensor_intrinsics("kinect_v1", 640, 480)
    assert K[0, 0] == 525.0 and K[1, 2] == 239.5
    with pytest.raises(ConfigError, match="primesense, kinect_v1, kinect_v2, realsense_d435"):
        sensor_intrinsics(None)
    with pytest.raises(ConfigError, match="unknown sensor"):
        sensor_intrinsics("phone")
    with pytest.raises(ConfigError, match="512x424"):
        sensor_intrinsics("kinect_v2", 640, 480)


# ----------------------------------------------------------------------------- captures without poses


def write_frames_only(folder: Path, n: int = 6, K: torch.Tensor | None = None, width: int = WIDTH,
                      height: int = HEIGHT) -> torch.Tensor:
    """n synthetic room frames as a capture without poses: depth/*.png (16-bit mm), image/*.png and, unless
    K is given, camera-intrinsics.txt; returns the true poses."""
    from PIL import Image

    truth = path(n)
    frames = capture(truth, K=K, width=width, height=height)
    (folder / "depth").mkdir(parents=True)
    (folder / "image").mkdir()
    if K is None:
        np.savetxt(folder / "camera-intrinsics.txt", frames.K[0].numpy())
    for i, depth in enumerate(frames.depth):
        Image.fromarray(np.round(depth.numpy() * 1000).astype(np.uint16)).save(folder / "depth" / f"{i:05d}.png")
        Image.fromarray(np.full((height, width, 3), 128, np.uint8)).save(folder / "image" / f"{i:05d}.png")
    return truth


def test_a_capture_without_poses_is_tracked_when_poses_are_auto(tmp_path):
    from neuralsurf.scenes.recipes import rgbd_scene

    truth = write_frames_only(tmp_path)
    with pytest.raises(FileFormatError, match="no RGB-D frames of a known layout"):
        rgbd_scene(str(tmp_path), poses="files")
    scene = rgbd_scene(str(tmp_path), poses="auto", hold_out_every=3)
    assert scene.trajectory.shape == (6, 4, 4) and "tracked poses" in scene.description
    assert absolute_trajectory_error(scene.trajectory, truth[0].inverse() @ truth) < 0.01
    assert torch.allclose(scene.held_out.cam_to_world, scene.trajectory[[2, 5]].float())
    frames = read_depth_frames(tmp_path, K=None, with_color=True)
    assert frames.colors.shape == (6, HEIGHT, WIDTH, 3) and torch.equal(frames.cam_to_world[3], torch.eye(4))
    photometric = rgbd_scene(str(tmp_path), poses="auto", hold_out_every=3, photometric=0.5)  # colour read to track
    assert absolute_trajectory_error(photometric.trajectory, truth[0].inverse() @ truth) < 0.01
    assert photometric.frames.colors is None  # ... and not kept: the mesh is not coloured


def test_a_capture_without_intrinsics_names_the_sensor_presets(tmp_path):
    write_frames_only(tmp_path, n=2)
    (tmp_path / "camera-intrinsics.txt").unlink()
    with pytest.raises(ConfigError, match="sensor= one of primesense, kinect_v1, kinect_v2, realsense_d435"):
        read_depth_frames(tmp_path)
    with pytest.raises(ConfigError, match="640x480 but these are 160x120"):
        read_depth_frames(tmp_path, sensor="kinect_v1")


@pytest.mark.subprocess
def test_train_py_on_frames_only_writes_the_trajectory_beside_the_mesh(tmp_path):
    truth = write_frames_only(tmp_path / "capture")
    command = [sys.executable, "train.py", "experiment=room", f"data.path={tmp_path / 'capture'}", "data.hold_out_every=0",
               "trainer.steps=2", "trainer.progress=false", "extract.resolution=32", "observation.rays.denoise_k=0",
               f"hydra.run.dir={tmp_path / 'run'}", "device=cpu"]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    ids, poses = read_trajectory_log(tmp_path / "run" / "trajectory.log")
    assert ids.tolist() == list(range(6)) and any((tmp_path / "run").glob("mesh.*"))
    assert absolute_trajectory_error(torch.from_numpy(poses), truth[0].inverse() @ truth) < 0.01
    table = np.loadtxt(tmp_path / "run" / "trajectory.txt")
    assert np.allclose(tum_trajectory_to_poses(table[:, 1:]), poses, atol=1e-6)
