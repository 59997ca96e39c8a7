"""Our ICP vs Open3D's registration_icp on the same input, in one run: seconds, iterations, and
how far apart the two results are.

    python benchmarks/bench_icp.py [--points 50000] [--repeats 3] [--threads 2]

Input: two different area-uniform samples of the bunny (neuralsurf.scenes.bunny), the source
moved by 10 degrees and 3 % of the size; both methods run from the identity with the same
max_distance, criteria and iteration cap, target normals given (from the mesh). Each timing is the
best of `--repeats`. Ours builds the target's k-d tree inside the call; Open3D builds its own too.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from neuralsurf.baselines.icp import register_icp
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


if __name__ == "__main__":
    main()
