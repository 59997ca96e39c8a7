"""RGB-D folders: 7-Scenes (real data), TUM and Redwood (synthetic folders), and bad input."""

import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from neuralsurf.cameras import backproject_depth, project_points
from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.io import read_rgbd_folder
from neuralsurf.io.rgbd import (
    MARKERS,
    TUM_K,
    associate,
    detect_rgbd_format,
    read_trajectory_log,
    tum_intrinsics,
)
from neuralsurf.structures import DepthFrames

H, W = 48, 64
K_SMALL = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
K_OTHER = np.array([[70.0, 0.0, 30.5], [0.0, 72.0, 22.5], [0.0, 0.0, 1.0]])  # neither K_SMALL nor 7-Scenes' K
PLANE_NORMAL, PLANE_OFFSET = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0]), 2.0


def random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(scale=0.15, size=3)).as_matrix()
    pose[:3, 3] = rng.normal(scale=0.2, size=3)
    return pose


def plane_depth(pose: np.ndarray, K: np.ndarray, h=H, w=W) -> np.ndarray:
    """Exact z-depth (h, w) of the plane PLANE_NORMAL . x = PLANE_OFFSET seen from `pose`."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return (PLANE_OFFSET - PLANE_NORMAL @ pose[:3, 3]) / (rays @ pose[:3, :3].T @ PLANE_NORMAL)


def save_depth(path, metres: np.ndarray, scale: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.round(metres * scale).astype(np.uint16)).save(path)  # 16-bit, mode "I;16"


def save_color(path, seed: int, h=H, w=W) -> np.ndarray:
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path)
    return rgb


def assert_on_plane(frames: DepthFrames, atol: float) -> None:
    points = backproject_depth(frames)[frames.depth > 0].double().numpy()
    assert len(points) > 0.9 * frames.depth.numel()
    assert np.abs(points @ PLANE_NORMAL - PLANE_OFFSET).max() < atol


# ---------------------------------------------------------------------------------------------
# synthetic folders


def millimetres(pose: np.ndarray, K: np.ndarray, h=H, w=W) -> np.ndarray:
    """The 16-bit depth (h, w) that make_7scenes writes for `pose`: the plane in millimetres, and the
    sensor's "no reading" code 65535 in the first 4 pixels of row 0."""
    depth = np.round(plane_depth(pose, K, h, w) * 1000).astype(np.uint16)
    depth[0, :4] = 65535
    return depth


def make_7scenes(root, n=3, K=K_SMALL, intrinsics=True, h=H, w=W, subfolder="frames", color=".color.png"):
    """n frames of the plane in root/subfolder (root itself when None), camera-intrinsics.txt in root;
    returns the camera-to-world poses [(4, 4)]."""
    frames = root / subfolder if subfolder else root
    frames.mkdir(parents=True, exist_ok=True)
    poses = [random_pose(i) for i in range(n)]
    for i, pose in enumerate(poses):
        Image.fromarray(millimetres(pose, K, h, w)).save(frames / f"frame-{i:06d}.depth.png")  # mode "I;16"
        save_color(frames / f"frame-{i:06d}{color}", i, h, w)
        np.savetxt(frames / f"frame-{i:06d}.pose.txt", pose)
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", K)
    return poses


def pixel_to_world(frames: DepthFrames, i: int, u: int, v: int) -> np.ndarray:
    """Pixel (u, v) of frame i back-projected through its K and pose, in numpy: (3,) world point."""
    K, pose = frames.K[i].double().numpy(), frames.cam_to_world[i].double().numpy()
    z = float(frames.depth[i, v, u])
    camera = z * np.array([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0])
    return pose[:3, :3] @ camera + pose[:3, 3]


def make_tum(root, n=4):
    """TUM layout: depth at 30 Hz; rgb 5 ms later; ground truth 3 ms after each depth image plus a
    wrong pose 12 ms after it (nearest must win); one extra depth image has no pose near it."""
    poses = [random_pose(10 + i) for i in range(n)]
    stamps = 100.0 + 0.0333 * np.arange(n)
    depth_lines, rgb_lines, truth_lines = (
        ["# depth maps", "# timestamp filename"],
        ["# color images"],
        ["# ground truth"],
    )
    for i, (t, pose) in enumerate(zip(stamps, poses)):
        save_depth(root / "depth" / f"{t:.6f}.png", plane_depth(pose, K_SMALL), 5000)
        save_color(root / "rgb" / f"{t + 0.005:.6f}.png", i)
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
        rgb_lines.append(f"{t + 0.005:.6f} rgb/{t + 0.005:.6f}.png")
        for dt, p in ((0.003, pose), (0.012, random_pose(99))):
            q = Rotation.from_matrix(p[:3, :3]).as_quat()  # x y z w
            truth_lines.append(f"{t + dt:.4f} " + " ".join(f"{v:.9f}" for v in (*p[:3, 3], *q)))
    late = stamps[-1] + 1.0  # no pose within tolerance
    save_depth(root / "depth" / "late.png", plane_depth(poses[0], K_SMALL), 5000)
    depth_lines.append(f"{late:.6f} depth/late.png")
    for name, lines in (("depth.txt", depth_lines), ("rgb.txt", rgb_lines), ("groundtruth.txt", truth_lines)):
        (root / name).write_text("\n".join(lines) + "\n")
    return poses


def make_redwood(root, n=3, color_size=(W, H)):
    poses = [random_pose(20 + i) for i in range(n)]
    log = []
    for i in range(n):
        save_depth(root / "depth" / f"{i:06d}.png", plane_depth(poses[i], K_SMALL), 1000)
        save_color(root / "image" / f"{i:06d}.jpg", i, color_size[1], color_size[0])
    for i in (2, 0, 1):  # the log's first number, not its order, names the frame
        log.append(f"{i} {i} {n}")
        log += [" ".join(f"{v:.9f}" for v in row) for row in poses[i]]
    (root / "scene-traj.log").write_text("\n".join(log) + "\n")
    return poses


# ---------------------------------------------------------------------------------------------
# real data: 7-Scenes redkitchen


def test_7scenes_frames_in_metres_with_poses_and_colour(shared_data):
    folder = shared_data / "7scenes_redkitchen_every10"
    with pytest.warns(UserWarning, match="unregistered"):
        frames = read_rgbd_folder(folder, stride=10)
    assert len(frames) == 10 and frames.depth.shape == (10, 480, 640)
    assert torch.allclose(frames.K[0], torch.tensor([[585.0, 0, 320], [0, 585, 240], [0, 0, 1]]))
    pose = np.loadtxt(folder / "frames" / "frame-000100.pose.txt")  # frame 1 after a stride of 10
    assert np.allclose(frames.cam_to_world[1].numpy(), pose, atol=1e-6)
    valid = frames.depth[frames.depth > 0]
    assert 0.3 < float(valid.min()) and float(valid.max()) < 8.0  # metres; 65535 codes became 0
    raw = np.array(Image.open(folder / "frames" / "frame-000000.depth.png"))
    assert np.allclose(frames.depth[0].numpy(), np.where(raw == 65535, 0, raw) / 1000.0)
    assert frames.colors.shape == (10, 480, 640, 3) and frames.colors.dtype == torch.uint8  # as the JPEGs hold them
    assert detect_rgbd_format(folder) == "7scenes"


def test_7scenes_successive_frames_agree_through_their_poses(shared_data, record_property):
    start = time.perf_counter()
    frames = read_rgbd_folder(shared_data / "7scenes_redkitchen_every10", with_color=False)
    print(f"7-Scenes: loaded {len(frames)} depth frames in {time.perf_counter() - start:.1f} s")
    assert len(frames) == 100

    def median_disagreement(pair: DepthFrames) -> float:
        """Median |z| difference where frame 1's points, projected into frame 0, meet a valid pixel."""
        points = backproject_depth(pair)[1][pair.depth[1] > 0]
        uv, z = project_points(points, pair.K[0], pair.cam_to_world[0])
        u, v = uv.round().long().unbind(-1)
        inside = (z > 0) & (u >= 0) & (u < pair.width) & (v >= 0) & (v < pair.height)
        seen = pair.depth[0][v[inside], u[inside]]
        overlap = seen > 0
        assert overlap.sum() > 50_000  # successive frames overlap a lot
        return float((z[inside][overlap] - seen[overlap]).abs().median())

    pairs = [frames[[i, i + 1]] for i in range(0, 99, 11)]  # 9 pairs along the trajectory
    medians = [median_disagreement(pair) for pair in pairs]
    print(
        "7-Scenes: median depth disagreement of successive frames (mm):", [round(m * 1e3, 1) for m in medians]
    )
    record_property("sevenscenes_reprojection_median_mm", float(np.median(medians)) * 1e3)
    assert np.median(medians) < 0.008 and max(medians) < 0.02  # Kinect v1 noise is ~1 cm at 2 m
    # reading pose.txt as world-to-camera instead breaks the agreement
    inverted = [DepthFrames(p.depth, p.K, torch.linalg.inv(p.cam_to_world)) for p in pairs[1:5]]
    assert np.median([median_disagreement(pair) for pair in inverted]) > 5 * np.median(medians)


# ---------------------------------------------------------------------------------------------
# synthetic 7-Scenes, TUM, Redwood


@pytest.mark.parametrize("subfolder", ["frames", None, "seq-01"])
def test_7scenes_layout_geometry(tmp_path, subfolder):
    poses = make_7scenes(tmp_path, subfolder=subfolder)
    frames = read_rgbd_folder(tmp_path, format="7scenes", with_color=False)
    assert frames.colors is None and len(frames) == 3
    assert np.allclose(frames.cam_to_world.numpy(), np.stack(poses), atol=1e-6)
    assert (frames.depth[:, 0, :4] == 0).all()  # 65535 -> invalid
    assert_on_plane(frames, atol=2e-3)  # millimetre quantisation at ~2 m
    assert len(read_rgbd_folder(tmp_path, stride=2, with_color=False)) == 2
    assert len(read_rgbd_folder(tmp_path, max_frames=1, with_color=False)) == 1


@pytest.mark.parametrize("color", [".color.png", ".color.jpg"])
def test_7scenes_in_one_subfolder_uses_the_intrinsics_beside_it(tmp_path, color):
    poses = make_7scenes(tmp_path, K=K_OTHER, subfolder="seq-01", color=color)
    (tmp_path / "notes").mkdir()  # a subfolder without frames does not count
    (tmp_path / "notes" / "readme.txt").write_text("captured with a Kinect")
    assert detect_rgbd_format(tmp_path) == "7scenes"
    with pytest.warns(UserWarning, match="unregistered"):
        frames = read_rgbd_folder(tmp_path)
    assert np.allclose(frames.K.numpy(), K_OTHER)  # the file written, not 7-Scenes' published K
    written = np.stack([millimetres(pose, K_OTHER) for pose in poses]).astype(np.float64)
    assert np.allclose(frames.depth.numpy(), np.where(written == 65535, 0, written) / 1000)
    assert np.allclose(frames.cam_to_world.numpy(), np.stack(poses), atol=1e-6)
    assert frames.colors.shape == (3, H, W, 3)
    for i, (u, v) in enumerate([(10, 20), (63, 47), (32, 5)]):
        assert abs(pixel_to_world(frames, i, u, v) @ PLANE_NORMAL - PLANE_OFFSET) < 2e-3  # mm rounding


def test_7scenes_subfolder_given_itself_uses_its_parents_intrinsics(tmp_path, caplog):
    make_7scenes(tmp_path, K=K_OTHER, subfolder="seq-01")
    with caplog.at_level(logging.INFO, logger="neuralsurf"):
        frames = read_rgbd_folder(tmp_path / "seq-01", with_color=False)
    assert np.allclose(frames.K.numpy(), K_OTHER)
    assert f"using the parent folder's {tmp_path.resolve() / 'camera-intrinsics.txt'}" in caplog.text
    assert_on_plane(frames, atol=2e-3)
    np.savetxt(tmp_path / "seq-01" / "camera-intrinsics.txt", K_SMALL)  # one of its own comes first
    assert np.allclose(read_rgbd_folder(tmp_path / "seq-01", with_color=False).K.numpy(), K_SMALL)


def test_several_subfolders_of_frames_are_named(tmp_path):
    for name in ("seq-01", "seq-02"):
        make_7scenes(tmp_path, n=1, K=K_OTHER, subfolder=name)
    for format in ("auto", "7scenes"):
        with pytest.raises(FileFormatError, match=r"frames in 2 subfolders \(seq-01/, seq-02/\).*point at one"):
            read_rgbd_folder(tmp_path, format=format)
    frames = read_rgbd_folder(tmp_path / "seq-02", with_color=False)
    assert len(frames) == 1 and np.allclose(frames.K.numpy(), K_OTHER)


def test_unknown_layout_names_what_was_looked_for_and_where(tmp_path):
    save_color(tmp_path / "images" / "0001.png", 0)
    (tmp_path / "depth").mkdir()  # Redwood's depth/ without a trajectory .log
    with pytest.raises(FileFormatError) as error:
        read_rgbd_folder(tmp_path)
    message = str(error.value)
    assert "no RGB-D frames of a known layout" in message
    for layout, markers in MARKERS.items():
        assert f"{layout}: {markers}" in message
    assert "frame-XXXXXX.depth.png" in message and "groundtruth.txt" in message and "*.log" in message
    assert f"Checked {str(tmp_path)!r} and its subfolders depth/, images/" in message


def test_real_7scenes_frames_in_a_subfolder(tmp_path):
    """The shared redkitchen frames laid out as intrinsics + one subfolder read as the original folder does."""
    if not os.environ.get("NEURALSURF_DATA"):
        pytest.skip("set NEURALSURF_DATA to the folder of real captures to run this test")
    source = Path(os.environ["NEURALSURF_DATA"]) / "7scenes_redkitchen_every10"
    if not source.is_dir():
        pytest.skip(f"{source} not found")
    (tmp_path / "seq-01").mkdir()
    (tmp_path / "camera-intrinsics.txt").symlink_to(source / "camera-intrinsics.txt")
    for depth in sorted((source / "frames").glob("frame-*.depth.png"))[:3]:
        for file in depth.parent.glob(depth.name.replace(".depth.png", ".*")):
            (tmp_path / "seq-01" / file.name).symlink_to(file)
    original = read_rgbd_folder(source, max_frames=3, with_color=False)
    for path in (tmp_path, tmp_path / "seq-01"):
        frames = read_rgbd_folder(path, with_color=False)
        assert len(frames) == 3 and torch.equal(frames.depth, original.depth)
        assert torch.equal(frames.K, original.K) and torch.equal(frames.cam_to_world, original.cam_to_world)


def test_rooms_are_meshed_near_their_input_and_objects_everywhere(tmp_path):
    from neuralsurf.scenes.recipes import depth_scene, rgbd_scene

    make_7scenes(tmp_path)
    room = rgbd_scene(str(tmp_path), hold_out_every=0)
    assert room.depth_input and room.near_distance == 0.05  # a room's unseen space stays empty
    # an object's inside lies farther than 5 cm from its surface: a mask would hollow it out
    assert depth_scene("object", room.frames).near_distance is None


def test_7scenes_colour_is_resized_to_the_depth(tmp_path):
    make_7scenes(tmp_path, n=1)
    save_color(tmp_path / "frames" / "frame-000000.color.png", 0, h=H * 2, w=W * 2)
    with pytest.warns(UserWarning, match="only approximate"):
        frames = read_rgbd_folder(tmp_path)
    assert frames.colors.shape == (1, H, W, 3)


def test_7scenes_without_intrinsics_warns_and_uses_the_published_k(tmp_path):
    K = np.array([[585.0, 0, 320], [0, 585, 240], [0, 0, 1]])
    make_7scenes(tmp_path, n=1, K=K, intrinsics=False, h=480, w=640)
    with pytest.warns(UserWarning, match="camera-intrinsics.txt"):
        frames = read_rgbd_folder(tmp_path, with_color=False)
    assert np.allclose(frames.K[0].numpy(), K)
    assert_on_plane(frames, atol=2e-3)


def test_tum_association_quaternions_and_scale(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg2_synthetic"
    poses = make_tum(root)
    with pytest.warns(UserWarning, match="1 of 5 depth images have no pose"):
        frames = read_rgbd_folder(root, K=K_SMALL)
    assert len(frames) == 4 and detect_rgbd_format(root) == "tum"
    assert np.allclose(frames.cam_to_world.numpy(), np.stack(poses), atol=1e-6)  # nearest pose, xyzw
    assert_on_plane(frames, atol=3e-4)  # 1/5000 m quantisation
    expected = np.asarray(Image.open(root / "rgb" / f"{100.0 + 0.0333 + 0.005:.6f}.png"))
    assert np.array_equal(frames.colors[1].numpy(), expected)
    fx, fy, cx, cy = TUM_K["freiburg2"]  # the default K follows the folder name
    assert np.allclose(tum_intrinsics(root), [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    with pytest.warns(UserWarning, match="ROS default"):
        assert tum_intrinsics(tmp_path)[0, 0] == TUM_K["default"][0]


def test_tum_needs_poses_within_tolerance(tmp_path):
    make_tum(tmp_path)
    with (
        pytest.raises(FileFormatError, match="no depth image with a ground-truth pose"),
        pytest.warns(UserWarning, match="5 of 5 depth images"),
    ):
        read_rgbd_folder(tmp_path, K=K_SMALL, tolerance=0.001)


def test_associate_picks_the_nearest_within_tolerance():
    stamps = np.array([3.0, 1.0, 2.0])
    assert associate(np.array([0.99, 1.6, 2.4, 2.95, 5.0]), stamps, 0.5).tolist() == [1, 2, 2, 0, -1]
    assert associate(np.array([7.0, 7.2]), np.array([7.1]), 0.15).tolist() == [0, 0]


def test_redwood_log_ids_and_millimetres(tmp_path):
    poses = make_redwood(tmp_path)
    ids, log_poses = read_trajectory_log(tmp_path / "scene-traj.log")
    assert ids.tolist() == [2, 0, 1] and np.allclose(log_poses[0], poses[2])
    frames = read_rgbd_folder(tmp_path, K=K_SMALL)
    assert detect_rgbd_format(tmp_path) == "redwood"
    assert np.allclose(frames.cam_to_world.numpy(), np.stack([poses[2], poses[0], poses[1]]), atol=1e-6)
    assert_on_plane(frames, atol=2e-3)
    assert frames.colors.shape == (3, H, W, 3)


# ---------------------------------------------------------------------------------------------
# bad input


def test_missing_or_empty_folders(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        read_rgbd_folder(tmp_path / "nowhere")
    with pytest.raises(FileFormatError, match=r"no RGB-D frames of a known layout.*\(no subfolders\)"):
        read_rgbd_folder(tmp_path)
    with pytest.raises(FileFormatError, match="has no frames"):
        read_rgbd_folder(tmp_path, format="7scenes")
    with pytest.raises(FileFormatError, match="depth.txt"):
        read_rgbd_folder(tmp_path, format="tum")
    with pytest.raises(ConfigError, match="unknown RGB-D format"):
        read_rgbd_folder(tmp_path, format="kinect")


def test_bad_stride_and_missing_files(tmp_path):
    make_7scenes(tmp_path, n=2)
    with pytest.raises(ConfigError, match="stride"):
        read_rgbd_folder(tmp_path, stride=0)
    with pytest.raises(ConfigError, match="max_frames"):
        read_rgbd_folder(tmp_path, max_frames=0)
    (tmp_path / "frames" / "frame-000001.pose.txt").unlink()
    with pytest.raises(FileFormatError, match="frame-000001.pose.txt"):
        read_rgbd_folder(tmp_path)


def test_depth_must_be_16_bit(tmp_path):
    make_7scenes(tmp_path, n=1)
    Image.fromarray(np.full((H, W), 200, dtype=np.uint8)).save(tmp_path / "frames" / "frame-000000.depth.png")
    with pytest.raises(FileFormatError, match="not 16-bit"):
        read_rgbd_folder(tmp_path, with_color=False)


def test_mismatched_intrinsics(tmp_path):
    make_7scenes(tmp_path, n=1, K=np.array([[585.0, 0, 320], [0, 585, 240], [0, 0, 1]]))  # K of 640x480
    with pytest.raises(InputError, match="mismatched intrinsics.*principal point"):
        read_rgbd_folder(tmp_path, with_color=False)


def test_non_rigid_pose(tmp_path):
    make_7scenes(tmp_path, n=2)
    np.savetxt(tmp_path / "frames" / "frame-000001.pose.txt", np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(InputError, match="not a rigid"):
        read_rgbd_folder(tmp_path, with_color=False)


def test_mismatched_depth_and_colour_sizes(tmp_path):
    make_redwood(tmp_path, color_size=(W // 2, H // 2))
    with pytest.raises(InputError, match="mismatched depth/colour sizes"):
        read_rgbd_folder(tmp_path, K=K_SMALL)
    assert read_rgbd_folder(tmp_path, K=K_SMALL, with_color=False).colors is None


def test_redwood_trajectory_problems(tmp_path):
    make_redwood(tmp_path)
    (tmp_path / "other.log").write_text("")
    (tmp_path / "scene-traj.log").rename(tmp_path / "scene.log")
    with pytest.raises(FileFormatError, match="exactly one trajectory"):
        read_rgbd_folder(tmp_path, format="redwood")
    (tmp_path / "other.log").unlink()
    (tmp_path / "scene.log").write_text("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 x\n0 0 0 1\n")
    with pytest.raises(FileFormatError, match="lines 1-5"):
        read_rgbd_folder(tmp_path, format="redwood")
