"""Rigid registration (baselines.registration): known motions, Open3D side by side, real range scans."""

import functools

import numpy as np
import pytest
import torch

from neuralsurf.baselines.registration import (
    Registration,
    evaluate_registration,
    kabsch,
    ransac_rigid,
    register_global,
    register_icp,
    register_multiway,
    voxel_downsample,
)
from neuralsurf.baselines.registration.estimation import apply_transform
from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.geometry import cloud_from_mesh
from neuralsurf.structures import PointCloud

# ----------------------------------------------------------------------------- helpers


def rotation(axis, degrees) -> np.ndarray:
    """3x3 rotation about `axis` (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def random_motion(seed: int, degrees: float, shift: float, center=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4: a rotation by `degrees` about a random axis through `center`, then a shift of length `shift`."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=3)
    matrix = np.eye(4)
    matrix[:3, :3] = rotation(rng.normal(size=3), degrees)
    center = np.asarray(center, dtype=np.float64)
    matrix[:3, 3] = center - matrix[:3, :3] @ center + shift * direction / np.linalg.norm(direction)
    return matrix


def errors(estimate, truth) -> tuple[float, float]:
    """(rotation error in degrees, translation error) between two 4x4 transforms."""
    estimate, truth = np.asarray(estimate, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    relative = estimate[:3, :3].T @ truth[:3, :3]
    sine = (
        np.linalg.norm(
            [
                relative[2, 1] - relative[1, 2],
                relative[0, 2] - relative[2, 0],
                relative[1, 0] - relative[0, 1],
            ]
        )
        / 2
    )
    angle = np.degrees(np.arctan2(sine, (np.trace(relative) - 1) / 2))
    return float(angle), float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


def moved(cloud: PointCloud, matrix: np.ndarray) -> PointCloud:
    """The cloud with points (and normals) mapped by the 4x4 `matrix`."""
    m = torch.from_numpy(matrix)
    cloud = PointCloud(cloud.points.double(), None if cloud.normals is None else cloud.normals.double())
    normals = None if cloud.normals is None else cloud.normals @ m[:3, :3].T
    return PointCloud(cloud.points @ m[:3, :3].T + m[:3, 3], normals)


@pytest.fixture(scope="module")
def bunny():
    from neuralsurf.scenes import bunny

    mesh = bunny()
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    return mesh, size


@pytest.fixture(scope="module")
def target(bunny):
    return cloud_from_mesh(bunny[0], 5000, seed=0)


# ----------------------------------------------------------------------------- known motions


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_rigid_motion_of_the_same_sample(bunny, target, method, seed):
    """Source = the target's points moved by up to 15 degrees and 5 % of the size: exact recovery."""
    _, size = bunny
    truth = random_motion(seed, 15.0, 0.05 * size, center=target.points.mean(0).numpy())
    source = moved(target, np.linalg.inv(truth))
    result = register_icp(source, target, 0.1 * size, method=method, max_iterations=100)
    angle, shift = errors(result.transform, truth)
    assert angle < 0.01 and shift < 1e-5 * size
    assert result.fitness == 1.0 and result.inlier_rmse < 1e-6 * size
    assert result.transform.dtype == torch.float64 and result.transform.shape == (4, 4)


@pytest.mark.parametrize(
    "method, kernel, pyramid",
    [
        ("point_to_point", None, False),
        ("point_to_plane", None, False),
        ("point_to_plane", "huber", False),
        ("point_to_plane", "tukey", False),
        ("point_to_point", None, True),
        ("point_to_plane", None, True),
    ],
)
def test_open3d_engine_agrees_with_the_reference_steps(bunny, target, method, kernel, pyramid):
    """The wrapper around Open3D's ICP (the default engine) against our numpy reference loop, on a
    known motion of another sample of the bunny (target normals estimated): both reach the truth,
    and, on one level, each other with the same fitness and RMSE."""
    _, size = bunny
    truth = random_motion(7, 12.0, 0.04 * size, center=target.points.mean(0).numpy())
    source = moved(cloud_from_mesh(bunny[0], 5000, seed=3), np.linalg.inv(truth))
    bare = PointCloud(target.points)
    v = 0.01 * size
    options = dict(method=method, kernel=kernel, kernel_scale=None if kernel is None else 0.02 * size,
                   max_iterations=200, relative_fitness=1e-10, relative_rmse=1e-10,
                   voxel_sizes=(4 * v, 2 * v, v) if pyramid else None)
    fast = register_icp(source, bare, 0.1 * size, engine="open3d", **options)
    reference = register_icp(source, bare, 0.1 * size, engine="reference", **options)
    for result in (fast, reference):
        angle, shift = errors(result.transform, truth)
        assert angle < 0.5 and shift < 5e-3 * size  # different samples: close to, not at, the truth
    angle, shift = errors(fast.transform, reference.transform)
    if pyramid:  # Open3D's voxel grid is not ours: other centroids, so only nearly the same result
        assert angle < 0.1 and shift < 1e-3 * size  # measured 0.02-0.05 degrees
        for result in (fast, reference):  # of the finest level's centroids: close to the full clouds'
            full_fitness, full_rmse = evaluate_registration(source, bare, result.transform, 0.1 * size)
            assert result.fitness == pytest.approx(full_fitness, abs=0.02)
            assert result.inlier_rmse == pytest.approx(full_rmse, rel=0.2)
    else:
        assert angle < 1e-3 and shift < 1e-5 * size
        assert fast.fitness == pytest.approx(reference.fitness, abs=1e-3)
        assert fast.inlier_rmse == pytest.approx(reference.inlier_rmse, rel=1e-3)
    assert reference.iterations > 1 and fast.iterations is None


@pytest.mark.parametrize("pyramid", [False, True])
def test_open3d_tensor_pipeline_recovers_the_motion(bunny, target, pyramid):
    """The GPU path (Open3D's tensor ICP / multi-scale ICP), run on the CPU here, against the
    reference on an exact motion of the same sample."""
    from neuralsurf.baselines.registration.estimation import LEAST_SQUARES
    from neuralsurf.baselines.registration.icp import ICPProblem, _icp_open3d_tensor
    from neuralsurf.strategies import choose

    _, size = bunny
    truth = random_motion(8, 10.0, 0.03 * size, center=target.points.mean(0).numpy())
    source = moved(target, np.linalg.inv(truth))
    v = 0.01 * size
    levels = [4 * v, 2 * v, v] if pyramid else [None]
    problem = ICPProblem(
        source.points.numpy(), target.points.double().numpy(), target.normals.double().numpy(), np.eye(4), levels,
        0.1 * size, choose("ICP method", "point_to_plane"), LEAST_SQUARES, None, 100, 1e-10, 1e-10, True, "cpu",
    )
    transform, fitness, rmse, iterations = _icp_open3d_tensor(problem, device="CPU:0")
    angle, shift = errors(transform, truth)
    assert angle < 0.01 and shift < 1e-4 * size
    # exact on the full clouds; on the finest level's voxel centroids, which differ between the two clouds
    assert fitness == pytest.approx(1.0) and rmse < (0.5 * v if pyramid else 1e-4 * size) and iterations >= 1


def test_engine_and_device_are_checked(target):
    with pytest.raises(ConfigError, match="unknown ICP engine 'pcl'; choose one of 'reference', 'open3d'"):
        register_icp(target, target, 0.01, engine="pcl")
    with pytest.raises(ConfigError, match="device must be"):
        register_icp(target, target, 0.01, device="tpu")


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_converges_to_open3d_transform(bunny, target, method):
    """Different samples of the surface (no exact answer): ours and Open3D's registration_icp run
    to convergence from the same start and reach the same transform."""
    import open3d as o3d

    _, size = bunny
    source = moved(
        cloud_from_mesh(bunny[0], 5000, seed=1), np.linalg.inv(random_motion(3, 10.0, 0.03 * size))
    )
    pipeline = o3d.pipelines.registration
    estimation = (
        pipeline.TransformationEstimationPointToPoint()
        if method == "point_to_point"
        else pipeline.TransformationEstimationPointToPlane()
    )
    reference = pipeline.registration_icp(
        source.to_open3d(),
        target.to_open3d(),
        0.1 * size,
        np.eye(4),
        estimation,
        pipeline.ICPConvergenceCriteria(1e-12, 1e-12, 300),
    )
    ours = register_icp(
        source,
        target,
        0.1 * size,
        method=method,
        max_iterations=300,
        relative_fitness=1e-12,
        relative_rmse=1e-12,
    )
    angle, shift = errors(ours.transform, reference.transformation)
    assert angle < 1e-4 and shift < 1e-6 * size
    assert ours.fitness == pytest.approx(reference.fitness, abs=1e-9)
    assert ours.inlier_rmse == pytest.approx(reference.inlier_rmse, rel=1e-6)


def test_tukey_kernel_resists_outliers_like_open3d(bunny, target):
    import open3d as o3d

    _, size = bunny
    truth = random_motion(4, 5.0, 0.02 * size)
    clean = moved(cloud_from_mesh(bunny[0], 5000, seed=2), np.linalg.inv(truth))
    rng = np.random.default_rng(0)
    outliers = clean.points.numpy()[rng.choice(len(clean), 1000)] + rng.normal(size=(1000, 3)) * 0.05 * size
    source = PointCloud(torch.cat([clean.points, torch.from_numpy(outliers)]))
    scale, distance = 0.015 * size, 0.1 * size
    plain = register_icp(source, target, distance, method="point_to_plane", max_iterations=100)
    robust = register_icp(
        source,
        target,
        distance,
        method="point_to_plane",
        kernel="tukey",
        kernel_scale=scale,
        max_iterations=100,
        relative_fitness=1e-12,
        relative_rmse=1e-12,
    )
    pipeline = o3d.pipelines.registration
    reference = pipeline.registration_icp(
        source.to_open3d(),
        target.to_open3d(),
        distance,
        np.eye(4),
        pipeline.TransformationEstimationPointToPlane(pipeline.TukeyLoss(k=scale)),
        pipeline.ICPConvergenceCriteria(1e-12, 1e-12, 100),
    )
    assert errors(robust.transform, truth)[0] < errors(plain.transform, truth)[0] / 5
    angle, shift = errors(robust.transform, reference.transformation)
    assert angle < 1e-3 and shift < 1e-5 * size


def test_huber_point_to_point_recovers_motion(bunny, target):
    _, size = bunny
    truth = random_motion(5, 10.0, 0.03 * size)
    result = register_icp(
        moved(target, np.linalg.inv(truth)),
        target,
        0.1 * size,
        kernel="huber",
        kernel_scale=0.01 * size,
        max_iterations=100,
    )
    angle, shift = errors(result.transform, truth)
    assert angle < 0.01 and shift < 1e-5 * size


@pytest.mark.parametrize("engine", ["open3d", "reference"])
def test_voxel_pyramid_reaches_what_a_small_max_distance_cannot(bunny, target, engine):
    _, size = bunny
    truth = random_motion(6, 30.0, 0.1 * size, center=target.points.mean(0).numpy())
    source = moved(cloud_from_mesh(bunny[0], 5000, seed=1), np.linalg.inv(truth))
    v = 0.01 * size
    single = register_icp(source, target, 1.5 * v, method="point_to_plane", engine=engine)
    pyramid = register_icp(
        source, target, 1.5 * v, method="point_to_plane", voxel_sizes=(8 * v, 4 * v, 2 * v, v), engine=engine
    )
    assert errors(single.transform, truth)[0] > 5.0  # stuck in a local minimum
    angle, shift = errors(pyramid.transform, truth)
    assert angle < 0.05 and shift < 1e-3 * size
    assert pyramid.iterations > 4 if engine == "reference" else pyramid.iterations is None


@pytest.mark.parametrize("degrees", [90.0, 180.0])
def test_global_then_icp_recovers_any_rotation(bunny, target, degrees):
    _, size = bunny
    truth = random_motion(int(degrees), degrees, 2.0 * size)
    source = moved(cloud_from_mesh(bunny[0], 5000, seed=7), np.linalg.inv(truth))
    coarse = register_global(source, target, voxel_size=size / 30)
    assert errors(coarse.transform, truth)[0] < 10.0 and coarse.fitness > 0.5
    fine = register_icp(source, target, size / 30, init=coarse.transform, method="point_to_plane")
    angle, shift = errors(fine.transform, truth)
    assert angle < 0.05 and shift < 1e-3 * size


def test_global_registration_repeats_bit_for_bit_with_its_seed(bunny, target):
    _, size = bunny
    truth = random_motion(3, 150.0, 2.0 * size)
    source = moved(cloud_from_mesh(bunny[0], 5000, seed=5), np.linalg.inv(truth))
    first, again = (register_global(source, target, voxel_size=size / 30, seed=1) for _ in range(2))
    assert torch.equal(first.transform, again.transform) and first.fitness == again.fitness
    other = register_global(source, target, voxel_size=size / 30, seed=2)
    assert errors(other.transform, truth)[0] < 10.0  # another seed, another sample: still right


def test_ransac_finds_the_motion_among_outlier_matches():
    """Half the matches are random: RANSAC returns the true motion and marks exactly the true half."""
    rng = np.random.default_rng(0)
    truth = random_motion(4, 120.0, 0.5)
    source = rng.uniform(-1, 1, (400, 3))
    target = apply_transform(source, truth)
    target[200:] = rng.uniform(-1, 1, (200, 3))
    transform, inliers = ransac_rigid(source, target, 1e-6, np.random.default_rng(0))
    np.testing.assert_allclose(transform, truth, atol=1e-9)
    assert inliers[:200].all() and not inliers[200:].any()


def partial_views(mesh, size, n=4, points=3000):
    """`n` scans of the mesh seen from directions around it, each in its own frame: (scans, truth
    poses scan -> world)."""
    cloud = cloud_from_mesh(mesh, n * points * 3, seed=11)
    center = cloud.points.mean(0)
    scans, poses = [], []
    for i in range(n):
        angle = 2 * np.pi * i / n
        view = torch.tensor([np.cos(angle), 0.3, np.sin(angle)], dtype=torch.float64)
        seen = (cloud.normals @ view > 0.0) & ((cloud.points - center) @ view > -0.1 * size)
        pose = random_motion(20 + i, 30.0, 0.2 * size)
        scans.append(moved(cloud.select(seen.nonzero()[:, 0][:points]), np.linalg.inv(pose)))
        poses.append(pose)
    return scans, poses


def test_multiway_recovers_poses_of_partial_views(bunny):
    mesh, size = bunny
    scans, truth = partial_views(mesh, size)
    init = [pose @ random_motion(30 + i, 3.0, 0.01 * size) if i else pose for i, pose in enumerate(truth)]
    poses = register_multiway(scans, voxel_size=0.01 * size, init_poses=[torch.from_numpy(p) for p in init])
    assert torch.equal(poses[0], torch.eye(4, dtype=torch.float64))
    for pose, true in zip(poses[1:], truth[1:]):
        angle, shift = errors(pose, np.linalg.inv(truth[0]) @ true)
        assert angle < 0.1 and shift < 2e-3 * size


# ----------------------------------------------------------------------------- record and pieces


def test_fitness_and_rmse_definitions():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(1000, 3, generator=g, dtype=torch.float64)
    far = torch.rand(250, 3, generator=g, dtype=torch.float64) + 10
    source = torch.cat([target[:750] + torch.tensor([0.0, 0.0, 1e-3], dtype=torch.float64), far])
    for engine, iterations in (("reference", 1), ("open3d", None)):  # Open3D's CPU ICP does not count
        result = register_icp(source, target, 0.05, max_iterations=1, engine=engine)
        assert isinstance(result, Registration)
        assert result.fitness == pytest.approx(750 / 1000)
        assert result.iterations == iterations and result.inlier_rmse < 1e-3
    # the same definitions for any transform: the 750 points 1e-3 from their own target point match
    fitness, rmse = evaluate_registration(source, target, np.eye(4), 0.05)
    assert fitness == pytest.approx(750 / 1000) and rmse == pytest.approx(1e-3, rel=1e-6)
    shifted = np.eye(4)
    shifted[2, 3] = -1e-3
    assert evaluate_registration(source, target, shifted, 0.05) == pytest.approx((0.75, 0.0), abs=1e-9)


def test_kabsch_weighted_exact():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    truth = random_motion(1, 40.0, 2.0)
    target = points @ truth[:3, :3].T + truth[:3, 3]
    target[:10] += 5.0  # corrupted rows get zero weight
    weights = np.r_[np.zeros(10), rng.uniform(0.5, 2.0, 40)]
    np.testing.assert_allclose(kabsch(points, target, weights), truth, atol=1e-12)


def test_voxel_downsample_centroids_and_normals():
    points = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2]])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # opposite signs: same plane
    down, down_normals = voxel_downsample(points, normals, 1.0)
    order = np.argsort(down[:, 0])
    np.testing.assert_allclose(down[order], [[0.2, 0.2, 0.2], [1.5, 0.2, 0.2]])
    np.testing.assert_allclose(np.abs(down_normals[order]), [[0, 0, 1], [1, 0, 0]])


# ----------------------------------------------------------------------------- bad input


def test_clouds_too_far_apart(target):
    far = PointCloud(target.points + 100.0)
    with pytest.raises(InputError, match="too far apart.*register_global.*larger max_distance"):
        register_icp(far, target, 0.01)


@pytest.mark.parametrize(
    "init, match",
    [
        (np.eye(3), r"4x4 rigid transform.*shape \(3, 3\)"),
        (np.diag([2.0, 2.0, 2.0, 1.0]), "not a rigid transform"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), r"det R = -1"),
        (np.full((4, 4), np.nan), "NaN"),
    ],
)
def test_init_must_be_rigid(target, init, match):
    with pytest.raises(InputError, match=match):
        register_icp(target, target, 0.01, init=init)


def test_point_to_plane_without_normals(target):
    bare = PointCloud(target.points)
    with pytest.raises(InputError, match="needs target normals.*estimate_normals=False"):
        register_icp(bare, bare, 0.01, method="point_to_plane", estimate_normals=False)
    # with estimation on (the default) it runs
    assert register_icp(bare, bare, 0.01, method="point_to_plane").fitness == 1.0


def test_empty_and_malformed_clouds(target):
    with pytest.raises(InputError, match="source has no points"):
        register_icp(torch.zeros(0, 3), target, 0.01)
    with pytest.raises(InputError, match=r"\(n, 3\) tensor"):
        register_icp(target, torch.zeros(10, 2), 0.01)
    with pytest.raises(InputError, match="at least 2 scans"):
        register_multiway([target], voxel_size=0.01)


def test_multiway_scans_without_overlap(target, bunny):
    _, size = bunny
    apart = [target, PointCloud(target.points + 100 * size), target]
    with pytest.raises(InputError, match=r"split into 2 groups.*\[\[0, 2\], \[1\]\]"):
        register_multiway(apart, voxel_size=0.02 * size)


def test_an_engine_of_ones_own_gets_the_checked_problem(target):
    """The engine interface: engine(ICPProblem) -> (transform, fitness, rmse, iterations)."""
    seen = []

    def engine(problem):
        seen.append(problem)
        return problem.init, 0.5, 0.25, 7

    init = np.eye(4)
    init[:3, 3] = (0.01, 0.0, 0.0)
    result = register_icp(target, target, 0.01, init=init, method="point_to_plane", kernel="huber", kernel_scale=0.1,
                          engine=engine, device="cpu")
    assert torch.equal(result.transform, torch.from_numpy(init)) and (result.fitness, result.inlier_rmse) == (0.5, 0.25)
    problem = seen[0]
    assert problem.method.needs_normals and problem.kernel.name == "huber" and problem.levels == [None]
    assert problem.source.dtype == np.float64 and problem.device == "cpu" and result.iterations == 7


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"method": "plane"}, "unknown ICP method"),
        ({"kernel": "cauchy"}, "unknown robust kernel"),
        ({"kernel": "tukey"}, "needs kernel_scale"),
        ({"max_distance": 0.0}, "max_distance must be a positive"),
        ({"voxel_sizes": (0.02, -1.0)}, "voxel_sizes must be positive"),
    ],
)
def test_bad_options(target, kwargs, match):
    kwargs = {"max_distance": 0.01, **kwargs}
    with pytest.raises(ConfigError, match=match):
        register_icp(target, target, **kwargs)


def test_degenerate_point_to_plane_on_a_plane():
    g = torch.Generator().manual_seed(0)
    plane = torch.cat(
        [torch.rand(500, 2, generator=g, dtype=torch.float64), torch.zeros(500, 1, dtype=torch.float64)], 1
    )
    with pytest.raises(NeuralsurfError, match="degenerate"):
        register_icp(plane, plane, 0.1, method="point_to_plane")


# ----------------------------------------------------------------------------- real range scans


def perturbed_conf_poses(scans, conf, seed=0, degrees=5.0, shift=0.01):
    """.conf poses (scan -> world) with every scan but the first rotated by `degrees` about its
    centroid and shifted by `shift` metres."""
    poses = []
    for i, (cloud, (_, pose)) in enumerate(zip(scans, conf)):
        pose = pose.numpy()
        center = cloud.points.double().numpy().mean(0) @ pose[:3, :3].T + pose[:3, 3]
        poses.append(pose if i == 0 else random_motion(seed + i, degrees, shift, center) @ pose)
    return poses


@functools.lru_cache(maxsize=1)
def stanford_scans(folder):
    """The ten bunny range scans, each in its scanner frame (with normals), and the .conf poses."""
    from neuralsurf.io.range_scans import read_range_scan, read_range_scan_conf

    conf = read_range_scan_conf(folder / "bun.conf")
    return [read_range_scan(folder / name) for name, _ in conf], conf


def test_real_scans_return_to_conf_poses(shared_data):
    """Each scan, its .conf pose perturbed by 5 degrees and 1 cm, point-to-plane ICP against the
    other nine (at their .conf poses): back within 0.2 degrees and 0.5 mm."""
    scans, conf = stanford_scans(shared_data / "stanford_bunny" / "data")
    world = [moved(scan, pose.numpy()) for scan, (_, pose) in zip(scans, conf)]
    init = perturbed_conf_poses(scans, conf)
    for i in range(1, len(scans)):
        others = [cloud for j, cloud in enumerate(world) if j != i]
        target = PointCloud(
            torch.cat([c.points.double() for c in others]), torch.cat([c.normals.double() for c in others])
        )
        result = register_icp(
            scans[i], target, 0.002, init=init[i], method="point_to_plane", voxel_sizes=(0.004, 0.002, 0.001)
        )
        angle, shift = errors(result.transform, conf[i][1])
        assert errors(init[i], conf[i][1])[0] == pytest.approx(5.0)
        assert angle < 0.2 and shift < 0.5e-3, conf[i][0]


@pytest.mark.slow
def test_real_scans_multiway_then_poisson_match_the_zipper_mesh(shared_data):
    """All ten scans from perturbed .conf poses (5 degrees, 1 cm): multiway registration, merge,
    Poisson; the poses land within 0.5 degrees / 1 mm of .conf, the mesh within 1 mm of bun_zipper."""
    from neuralsurf.baselines.poisson import reconstruct_poisson
    from neuralsurf.geometry import point_to_mesh_distance, sample_mesh_surface
    from neuralsurf.io import read_mesh

    scans, conf = stanford_scans(shared_data / "stanford_bunny" / "data")
    init = [torch.from_numpy(pose) for pose in perturbed_conf_poses(scans, conf)]
    poses = register_multiway(scans, voxel_size=0.001, max_distance=0.002, init_poses=init)
    for pose, (name, truth) in zip(poses, conf):
        angle, shift = errors(pose, truth)  # bun000's .conf pose is the identity
        assert angle < 0.5 and shift < 1e-3, name
    aligned = [moved(scan, pose.numpy()) for scan, pose in zip(scans, poses)]
    merged = PointCloud(torch.cat([c.points for c in aligned]), torch.cat([c.normals for c in aligned]))
    mesh = reconstruct_poisson(merged, depth=9)
    gt = read_mesh(shared_data / "stanford_bunny" / "reconstruction" / "bun_zipper.ply")
    g = torch.Generator().manual_seed(0)
    accuracy = point_to_mesh_distance(sample_mesh_surface(mesh, 100_000, g)[0].double(), gt).double().mean()
    completeness = (
        point_to_mesh_distance(sample_mesh_surface(gt, 100_000, g)[0].double(), mesh).double().mean()
    )
    assert accuracy < 1e-3 and completeness < 1e-3
