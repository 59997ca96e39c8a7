"""Camera tracking without poses: our KinectFusion-style tracker (frame-to-model, and frame-to-frame)
against Open3D's multi-scale RGB-D odometry chained frame to frame, on the shared room sequences, in one
run: ATE and RPE against the sequences' own poses (hidden from both trackers), ms per frame, and their
ratios; then the held-out depth error of the meshes fused at the tracked and at the given poses.

    PYTHONPATH=. python benchmarks/bench_tracking.py [--device cpu|cuda] [--max-frames N]

Sequences ($NEURALSURF_DATA): livingroom1_redwood (211 frames at 30 Hz, PrimeSense K) and
7scenes_redkitchen_every10 (every 10th frame: 10x the motion between frames; a tracker may stop there
with the first lost frame named). Open3D: `o3d.t.pipelines.odometry.rgbd_odometry_multi_scale`, its
default criteria (10/5/3 iterations over 3 levels, coarse to fine), depth_max as ours, method Hybrid (depth and colour)
and PointToPlane (depth only), on the same device as ours. Times are wall-clock per frame, whole
sequence, after one warm-up frame pair; the load average is printed, as other processes inflate them.

Held-out depth error: every 10th frame held out; the others fused into a TSDF (1 cm voxels) at the
given poses, and at the tracked poses moved onto the given ones by the ATE alignment; each mesh
ray-cast from the held-out frames' given poses (`metrics.depth_metrics`).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from neuralsurf.baselines.tracking import TrackingLostError, track_frames
from neuralsurf.baselines.tsdf import TSDFVolume, depth_bounds
from neuralsurf.io.rgbd import read_rgbd_folder
from neuralsurf.metrics import absolute_trajectory_error, align_trajectory, depth_metrics, relative_pose_error
from neuralsurf.scenes.recipes import data_root
from neuralsurf.structures import DepthFrames

SEQUENCES = {"livingroom1": "livingroom1_redwood", "redkitchen": "7scenes_redkitchen_every10"}
MAX_DEPTH = 4.0


def open3d_odometry(frames: DepthFrames, method: str, device: str) -> tuple[np.ndarray, float, int | None]:
    """Poses (n, 4, 4) of Open3D's multi-scale RGB-D odometry chained frame to frame, seconds, and the first
    frame where it failed (None: tracked all)."""
    import open3d as o3d

    odometry = o3d.t.pipelines.odometry
    o3d_device = o3d.core.Device("CUDA:0" if device == "cuda" else "CPU:0")
    K = o3d.core.Tensor(frames.K[0].double().numpy())
    colors = frames.colors if frames.colors is not None else frames.depth[..., None].expand(-1, -1, -1, 3) / MAX_DEPTH

    def image(i: int):
        depth = o3d.t.geometry.Image(o3d.core.Tensor(frames.depth[i].numpy()[..., None])).to(o3d_device)
        color = o3d.t.geometry.Image(o3d.core.Tensor(colors[i].contiguous().numpy())).to(o3d_device)
        return o3d.t.geometry.RGBDImage(color, depth)

    kind = getattr(odometry.Method, method)
    identity = o3d.core.Tensor(np.eye(4))
    images = [image(i) for i in range(len(frames))]

    def odometry_step(source, target):
        return odometry.rgbd_odometry_multi_scale(source, target, K, init_source_to_target=identity,
                                                  depth_scale=1.0, depth_max=MAX_DEPTH, method=kind)

    odometry_step(images[1], images[0])  # warm-up
    poses, lost = [np.eye(4)], None
    start = time.perf_counter()
    for i in range(1, len(frames)):
        result = odometry_step(images[i], images[i - 1])
        if lost is None and result.fitness < 0.3:  # the same inlier-share bar as ours
            lost = i
        poses.append(poses[-1] @ result.transformation.cpu().numpy())
    return np.stack(poses), time.perf_counter() - start, lost


def scores(estimated: np.ndarray | torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    estimated = torch.as_tensor(estimated, dtype=torch.float64)
    truth = truth[: len(estimated)].double()
    rpe = relative_pose_error(estimated, truth)
    return {"ate_cm": 100 * absolute_trajectory_error(estimated, truth), "rpe_cm": 100 * rpe.translation,
            "rpe_deg": rpe.rotation}


def held_out_error(frames: DepthFrames, poses: torch.Tensor, device: str) -> float:
    """Median depth error (cm) on every 10th frame of the mesh fused from the others at `poses`."""
    index = torch.arange(len(frames))
    held = index % 10 == 9
    fused = DepthFrames(frames.depth[~held], frames.K[~held], poses[~held].float())
    volume = TSDFVolume(depth_bounds(fused, 0.05), 0.01, device=device, sparse=True)
    mesh = volume.integrate(fused, progress=False).extract_mesh()
    return 100 * depth_metrics(mesh, frames[index[held]])["depth_error_median"]


def run(name: str, folder: str, device: str, max_frames: int | None, fuse: bool) -> None:
    frames = read_rgbd_folder(data_root() / folder, max_frames=max_frames, progress=False)
    depth = torch.where(frames.depth <= MAX_DEPTH, frames.depth, 0.0)
    frames = DepthFrames(depth, frames.K, frames.cam_to_world, frames.colors)
    truth = frames.cam_to_world.double()
    print(f"\n== {name}: {len(frames)} frames {frames.width}x{frames.height}, device {device}")
    rows = {}
    hidden = DepthFrames(frames.depth.to(device), frames.K, torch.eye(4).expand(len(frames), 4, 4))
    for mode in ("model", "frame"):
        track_frames(hidden[:2], progress=False, mode=mode)  # warm-up
        try:
            trajectory = track_frames(hidden, progress=False, mode=mode)
            poses, seconds, lost = trajectory.cam_to_world, trajectory.seconds, None
        except TrackingLostError as error:
            poses, seconds, lost = None, None, error
        rows[f"ours ({mode})"] = (poses, seconds, lost)
    for method in ("Hybrid", "PointToPlane"):
        poses, seconds, lost = open3d_odometry(frames, method, device)
        rows[f"Open3D {method}"] = (poses, seconds, lost)
    reference = rows["Open3D Hybrid"][1] / (len(frames) - 1)
    for label, (poses, seconds, lost) in rows.items():
        if poses is None:
            print(f"  {label:22s} stopped: {lost}")
            continue
        s = scores(poses, truth)
        ms = 1000 * seconds / (len(frames) - 1)
        note = "" if lost is None else f"  (fitness < 0.3 first at frame {lost})"
        print(f"  {label:22s} ATE {s['ate_cm']:6.2f} cm  RPE {s['rpe_cm']:5.2f} cm {s['rpe_deg']:5.2f} deg  "
              f"{ms:7.1f} ms/frame ({ms / (1000 * reference):.2f}x Open3D Hybrid){note}")
    if fuse:
        given = held_out_error(frames, truth, device)
        print(f"  held-out median depth error, mesh fused at the given poses: {given:.2f} cm")
        for label, (poses, _, _) in rows.items():
            if poses is not None and label.startswith("ours"):
                aligned = align_trajectory(torch.as_tensor(poses), truth) @ torch.as_tensor(poses)
                tracked = held_out_error(frames, aligned, device)
                print(f"  ... at {label} poses: {tracked:.2f} cm ({tracked / given:.2f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--sequences", nargs="+", default=list(SEQUENCES), choices=list(SEQUENCES))
    parser.add_argument("--no-fuse", action="store_true", help="skip the held-out depth error of fused meshes")
    args = parser.parse_args()
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, load average {os.getloadavg()}")
    for name in args.sequences:
        run(name, SEQUENCES[name], args.device, args.max_frames, not args.no_fuse)
    print(f"load average at the end {os.getloadavg()}")


if __name__ == "__main__":
    main()
