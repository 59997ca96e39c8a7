"""Our ICP vs Open3D's registration_icp on the same input, in one run: seconds, iterations, and
how far apart the two results are; then our global registration vs Open3D's FPFH + RANSAC.

    python benchmarks/bench_icp.py [--points 50000] [--repeats 3] [--threads 2] [--global-trials 8]

Input: two different area-uniform samples of the bunny (neuralsurf.scenes.bunny), the source
moved by 10 degrees and 3 % of the size; both methods run from the identity with the same
max_distance, criteria and iteration cap, target normals given (from the mesh). Each timing is the
best of `--repeats`. Ours builds the target's k-d tree inside the call; Open3D builds its own too.

Global: `--global-trials` rotations of 30 to 180 degrees of a 5,000-point sample onto another,
voxel 1/30 of the size; both RANSACs get the same downsampled clouds and FPFH features, mutual
matching, 100,000 iterations, confidence 0.999, 1.5 voxel inlier distance. A trial succeeds when
the rotation is within 10 degrees of the truth (ICP takes it from there).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from neuralsurf.baselines.icp import _fpfh, register_global, register_icp
from neuralsurf.geometry import cloud_from_mesh
from neuralsurf.scenes import bunny
from neuralsurf.structures import PointCloud


def motion(degrees: float, shift: float, seed: int = 0) -> np.ndarray:
    """4x4 rigid motion: `degrees` about a random axis, then a random shift of length `shift`."""
    rng = np.random.default_rng(seed)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = np.radians(degrees)
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    matrix[:3, 3] = shift * direction / np.linalg.norm(direction)
    return matrix


def best_of(repeats: int, run):
    """(best seconds, last result) of `repeats` calls of run()."""
    best, result = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - start)
    return best, result


def angle_degrees(a: np.ndarray, b: np.ndarray) -> float:
    relative = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1))))


def main() -> None:
    import open3d as o3d

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=50_000, help="points per cloud")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--global-trials", type=int, default=8, help="rotations for global registration")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    mesh = bunny()
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    target = cloud_from_mesh(mesh, args.points, seed=0)
    truth = motion(10.0, 0.03 * size)
    inverse = torch.from_numpy(np.linalg.inv(truth))
    source = PointCloud(
        cloud_from_mesh(mesh, args.points, seed=1).points @ inverse[:3, :3].T + inverse[:3, 3]
    )
    source_o3d, target_o3d = source.to_open3d(), target.to_open3d()
    max_distance, iterations = 0.05 * size, 50
    pipeline = o3d.pipelines.registration
    print(
        f"machine: {platform.processor() or platform.machine()}, {torch.get_num_threads()} torch threads; "
        f"Open3D {o3d.__version__}; {args.points} points per cloud, best of {args.repeats}\n"
    )
    print(
        f"{'method':<16}{'ours s':>9}{'Open3D s':>10}{'ratio':>8}{'iters':>12}{'|dR| deg':>11}{'|dt|/size':>11}"
    )
    for method, estimation in (
        ("point_to_point", pipeline.TransformationEstimationPointToPoint()),
        ("point_to_plane", pipeline.TransformationEstimationPointToPlane()),
    ):
        ours_s, ours = best_of(
            args.repeats,
            lambda method=method: register_icp(
                source, target, max_distance, method=method, max_iterations=iterations
            ),
        )
        theirs_s, theirs = best_of(
            args.repeats,
            lambda estimation=estimation: pipeline.registration_icp(
                source_o3d,
                target_o3d,
                max_distance,
                np.eye(4),
                estimation,
                pipeline.ICPConvergenceCriteria(1e-6, 1e-6, iterations),
            ),
        )
        ours_t, theirs_t = ours.transform.numpy(), np.asarray(theirs.transformation)
        shift = np.linalg.norm(ours_t[:3, 3] - theirs_t[:3, 3]) / size
        # Open3D does not report its iteration count
        print(
            f"{method:<16}{ours_s:9.3f}{theirs_s:10.3f}{ours_s / theirs_s:7.2f}x{ours.iterations:>8} / -"
            f"{angle_degrees(ours_t, theirs_t):11.1e}{shift:11.1e}"
        )
    print("\nratio = ours / Open3D seconds (lower is better for us)")
    bench_global(mesh, size, args.global_trials)


def open3d_global(source: np.ndarray, target: np.ndarray, voxel: float, seed: int) -> np.ndarray:
    """Open3D 0.20's FPFH + RANSAC with the settings of register_global: 4x4 transform."""
    import open3d as o3d

    pipeline = o3d.pipelines.registration
    clouds = []
    for points in (source, target):
        down, features = _fpfh(points, voxel)
        feature = pipeline.Feature()
        feature.data = features.T.copy()
        clouds += [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(down)), feature]
    o3d.utility.random.seed(seed)
    result = pipeline.registration_ransac_based_on_feature_matching(
        clouds[0], clouds[2], clouds[1], clouds[3], True, 1.5 * voxel,
        pipeline.TransformationEstimationPointToPoint(False), 3,
        [pipeline.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         pipeline.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        pipeline.RANSACConvergenceCriteria(100_000, 0.999),
    )
    return np.asarray(result.transformation)


def bench_global(mesh, size: float, trials: int) -> None:
    """Seconds and rotation error of both global registrations over `trials` random rotations."""
    target = cloud_from_mesh(mesh, 5000, seed=0)
    voxel = size / 30
    rows = {"ours": [], "Open3D": []}
    for trial in range(trials):
        truth = motion(30.0 + 150.0 * trial / max(trials - 1, 1), 2.0 * size, seed=100 + trial)
        inverse = np.linalg.inv(truth)
        source = cloud_from_mesh(mesh, 5000, seed=1 + trial).points.numpy() @ inverse[:3, :3].T + inverse[:3, 3]
        for name, run in (
            ("ours", lambda: register_global(PointCloud(torch.from_numpy(source)), target, voxel).transform.numpy()),
            ("Open3D", lambda: open3d_global(source, target.points.numpy(), voxel, seed=0)),
        ):
            start = time.perf_counter()
            transform = run()
            rows[name].append((time.perf_counter() - start, angle_degrees(transform, truth)))
    print(f"\nglobal registration, {trials} rotations of 30-180 degrees, 5000 points, voxel size/30")
    print(f"{'method':<10}{'mean s':>9}{'success':>10}{'median err deg':>16}{'max err deg':>13}")
    for name, results in rows.items():
        seconds, angles = np.array(results).T
        print(f"{name:<10}{seconds.mean():9.3f}{f'{(angles < 10).sum()}/{trials}':>10}"
              f"{np.median(angles):16.2f}{angles.max():13.2f}")


if __name__ == "__main__":
    main()
