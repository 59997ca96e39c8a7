"""register_icp against Open3D's registration_icp on the same input, in one run: seconds, their
ratio, and how far apart the results are; then our global registration against Open3D's FPFH + RANSAC.

    PYTHONPATH=. python benchmarks/bench_icp.py [--points 50000] [--repeats 3] [--global-trials 8]

Rows: "ours" is register_icp as a user calls it (engine="open3d", the default: checks, conversion
to Open3D, its legacy ICP on the CPU, fitness/RMSE of the finest level as Open3D's); "reference" is our numpy
loop (engine="reference"); "Open3D" is o3d.pipelines.registration.registration_icp called directly
on clouds converted beforehand. Same max_distance, criteria and iteration cap; target normals given.
Timings are the best of --repeats, rows interleaved, so that load from other processes hits them
alike; the load average is printed.

Bunny: two different area-uniform samples of neuralsurf.scenes.bunny, the source moved by 10 degrees
and 3 % of the size, from the identity; errors against the known motion.

Real scans ($NEURALSURF_DATA or the fetch cache, Stanford bunny range scans): each scan but the first,
its .conf pose perturbed by 5 degrees and 1 cm, point-to-plane against the other nine at their .conf
poses, through a voxel pyramid of 4, 2, 1 mm (Open3D directly: voxel_down_sample of both clouds per
level, its averaged normals, registration_icp); errors against .conf, summed times.

Global: `--global-trials` rotations of 30 to 180 degrees of a 5,000-point sample onto another,
voxel 1/30 of the size; both RANSACs get the same downsampled clouds and FPFH features, mutual
matching, 100,000 iterations, confidence 0.999, 1.5 voxel inlier distance. A trial succeeds when
the rotation is within 10 degrees of the truth (ICP takes it from there).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
import torch

from neuralsurf.baselines.registration import register_global, register_icp
from neuralsurf.baselines.registration.global_registration import fpfh_features
from neuralsurf.geometry import cloud_from_mesh
from neuralsurf.scenes import bunny
from neuralsurf.scenes.recipes import data_root
from neuralsurf.structures import PointCloud

DATA = data_root()


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


def angle_degrees(a: np.ndarray, b: np.ndarray) -> float:
    relative = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1))))


def bench_bunny(points: int, repeats: int) -> None:
    import open3d as o3d

    mesh = bunny()
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    target = cloud_from_mesh(mesh, points, seed=0)
    truth = motion(10.0, 0.03 * size)
    inverse = torch.from_numpy(np.linalg.inv(truth))
    source = PointCloud(cloud_from_mesh(mesh, points, seed=1).points @ inverse[:3, :3].T + inverse[:3, 3])
    source_o3d, target_o3d = source.to_open3d(), target.to_open3d()
    max_distance, iterations = 0.05 * size, 50
    pipeline = o3d.pipelines.registration
    print(f"\nBunny: {points} points per cloud, 10 degrees and 3 % of the size apart, best of {repeats}")
    print(f"{'method':<16}{'ours s':>8}{'Open3D s':>10}{'ratio':>8}{'reference s':>13}{'ratio':>8}"
          f"{'err deg':>9}{'Open3D err':>11}{'ours-Open3D deg':>17}")
    for method, estimation in (
        ("point_to_point", pipeline.TransformationEstimationPointToPoint()),
        ("point_to_plane", pipeline.TransformationEstimationPointToPlane()),
    ):
        runs = {
            "ours": lambda method=method: register_icp(
                source, target, max_distance, method=method, max_iterations=iterations).transform.numpy(),
            "reference": lambda method=method: register_icp(
                source, target, max_distance, method=method, max_iterations=iterations, engine="reference"
            ).transform.numpy(),
            "Open3D": lambda estimation=estimation: np.asarray(pipeline.registration_icp(
                source_o3d, target_o3d, max_distance, np.eye(4), estimation,
                pipeline.ICPConvergenceCriteria(1e-6, 1e-6, iterations)).transformation),
        }
        seconds, results = interleaved(runs, repeats)
        print(f"{method:<16}{seconds['ours']:8.3f}{seconds['Open3D']:10.3f}{seconds['ours'] / seconds['Open3D']:7.2f}x"
              f"{seconds['reference']:13.3f}{seconds['reference'] / seconds['Open3D']:7.2f}x"
              f"{angle_degrees(results['ours'], truth):9.4f}{angle_degrees(results['Open3D'], truth):11.4f}"
              f"{angle_degrees(results['ours'], results['Open3D']):17.1e}")


def interleaved(runs: dict, repeats: int) -> tuple[dict, dict]:
    """Best seconds and last result of each run, the runs taking turns `repeats` times."""
    seconds, results = {name: float("inf") for name in runs}, {}
    for _ in range(repeats):
        for name, run in runs.items():
            start = time.perf_counter()
            results[name] = run()
            seconds[name] = min(seconds[name], time.perf_counter() - start)
    return seconds, results


def open3d_pyramid(source, target, max_distance: float, init: np.ndarray, sizes) -> np.ndarray:
    """Open3D as its users run a pyramid: voxel_down_sample both clouds per level (normals averaged),
    point-to-plane registration_icp, max_distance scaled with the level."""
    import open3d as o3d

    pipeline = o3d.pipelines.registration
    transform = init
    for size in sizes:
        result = pipeline.registration_icp(
            source.voxel_down_sample(size), target.voxel_down_sample(size), max_distance * size / sizes[-1],
            transform, pipeline.TransformationEstimationPointToPlane(), pipeline.ICPConvergenceCriteria(1e-6, 1e-6, 50),
        )
        transform = np.asarray(result.transformation)
    return transform


def scan_runs(scan: PointCloud, target: PointCloud, init: np.ndarray, sizes) -> dict:
    """The three ways to register one real scan (see the module docstring)."""
    source_o3d, target_o3d = scan.to_open3d(), target.to_open3d()
    return {
        "ours": lambda: register_icp(scan, target, 0.002, init=init, method="point_to_plane",
                                     voxel_sizes=sizes).transform.numpy(),
        "Open3D": lambda: open3d_pyramid(source_o3d, target_o3d, 0.002, init, sizes),
    }


def bench_scans(repeats: int) -> None:
    folder = DATA / "stanford_bunny" / "data"
    if not folder.is_dir():
        print(f"\nReal scans: skipped, {folder} not found (set NEURALSURF_DATA)")
        return
    from neuralsurf.io.range_scans import read_range_scan, read_range_scan_conf

    conf = read_range_scan_conf(folder / "bun.conf")
    scans = [read_range_scan(folder / name) for name, _ in conf]
    poses = [pose.double().numpy() for _, pose in conf]
    sizes = (0.004, 0.002, 0.001)
    world = [scan.points.double().numpy() @ pose[:3, :3].T + pose[:3, 3] for scan, pose in zip(scans, poses)]
    world_normals = [scan.normals.double().numpy() @ pose[:3, :3].T for scan, pose in zip(scans, poses)]
    totals = {"ours": 0.0, "Open3D": 0.0}
    errors = {name: [] for name in totals}
    for i in range(1, len(scans)):
        others = [j for j in range(len(scans)) if j != i]
        target = PointCloud(torch.from_numpy(np.concatenate([world[j] for j in others])),
                            torch.from_numpy(np.concatenate([world_normals[j] for j in others])))
        seconds, results = interleaved(scan_runs(scans[i], target, motion(5.0, 0.01, seed=i) @ poses[i], sizes),
                                       repeats)
        for name, total in seconds.items():
            totals[name] += total
            errors[name].append(angle_degrees(results[name], poses[i]))
    print(f"\nReal scans: 9 Stanford bunny scans back to their .conf poses from 5 degrees / 1 cm off, point-to-plane, "
          f"pyramid 4-2-1 mm, best of {repeats} each")
    print(f"{'method':<12}{'total s':>9}{'vs Open3D':>10}{'median err deg':>16}{'max err deg':>13}")
    for name, total in totals.items():
        print(f"{name:<12}{total:9.3f}{total / totals['Open3D']:9.2f}x{np.median(errors[name]):16.3f}"
              f"{max(errors[name]):13.3f}")


def main() -> None:
    import open3d as o3d

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=50_000, help="points per cloud")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--global-trials", type=int, default=8, help="rotations for global registration")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.1f}; Open3D {o3d.__version__} (its own threads); ratio = ours / Open3D seconds")
    bench_bunny(args.points, args.repeats)
    bench_scans(args.repeats)
    bench_global(bunny(), float((bunny().bounds[1] - bunny().bounds[0]).max()), args.global_trials)
    print(f"\nload average at the end: {os.getloadavg()[0]:.1f}")


def open3d_global(source: np.ndarray, target: np.ndarray, voxel: float, seed: int) -> np.ndarray:
    """Open3D 0.20's FPFH + RANSAC with the settings of register_global: 4x4 transform."""
    import open3d as o3d

    pipeline = o3d.pipelines.registration
    clouds = []
    for points in (source, target):
        down, features = fpfh_features(points, voxel)
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
            ("ours", lambda source=source: register_global(
                PointCloud(torch.from_numpy(source)), target, voxel).transform.numpy()),
            ("Open3D", lambda source=source: open3d_global(source, target.points.numpy(), voxel, seed=0)),
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
