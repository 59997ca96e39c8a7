"""Camera tracking without poses: our KinectFusion-style tracker (frame-to-model, and frame-to-frame)
against Open3D's multi-scale RGB-D odometry chained frame to frame, on the shared room sequences, in one
run: ATE and RPE against the sequences' own poses (hidden from both trackers), ms per frame, and their
ratios; then the held-out depth error of the meshes fused at the tracked and at the given poses.

    PYTHONPATH=. python benchmarks/bench_tracking.py [--device cpu|cuda] [--max-frames N]

Sequences ($NEURALSURF_DATA): livingroom1_redwood (211 frames at 30 Hz, PrimeSense K) and
7scenes_redkitchen_every10 (every 10th frame: 10x the motion between frames; a tracker may stop there
with the first lost frame named). Open3D: `o3d.t.pipelines.odometry.rgbd_odometry_multi_scale`, its
default criteria (10/5/3 iterations over 3 levels, coarse to fine), depth_max as ours, method Hybrid (depth and colour)
and PointToPlane (depth only), on the same device as ours. The trackers take the frames in turn, one
frame each (so that load from other processes hits them alike); times are wall-clock per frame, frame 0
excluded, after a warm-up pair, and CPU time per frame (robust to other processes' load); the load average
is printed. On a CPU ours runs twice, eager and compiled
(torch.compile of the raycast's sampling and the ICP iterations; the compilation is part of the warm-up,
printed, not of the time per frame), and eager with its grey-level term where the colour is loaded (with
Open3D; 7-Scenes' colour is not registered to its depth, so there the term sees shifted colours).

Held-out depth error: every 10th frame held out; the others fused into a TSDF (1 cm voxels) at the
given poses, and at the tracked poses moved onto the given ones by the ATE alignment; each mesh
ray-cast from the held-out frames' given poses (`metrics.depth_metrics`), and from those poses registered to
the mesh (`evaluation.rooms.localised_depth_metrics`: the shape scored without the trajectory's offset).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from neuralsurf.baselines.tracking import Tracker, TrackingLostError
from neuralsurf.baselines.tsdf import TSDFVolume, depth_bounds
from neuralsurf.evaluation.rooms import localised_depth_metrics
from neuralsurf.io.rgbd import read_rgbd_folder
from neuralsurf.metrics import absolute_trajectory_error, align_trajectory, depth_metrics, relative_pose_error
from neuralsurf.scenes.recipes import data_root
from neuralsurf.structures import DepthFrames

SEQUENCES = {"livingroom1": "livingroom1_redwood", "redkitchen": "7scenes_redkitchen_every10"}
MAX_DEPTH = 4.0
PHOTOMETRIC = 0.5
"""Weight of ours' grey-level term where colour is loaded (chosen on livingroom1 among 0.1 to 10: ATE 1.18 cm without,
1.12 cm at 0.5, 3.05 cm at 3)."""


class Open3DOdometry:
    """Open3D's multi-scale RGB-D odometry chained frame to frame, one frame per `track` call, as ours."""

    def __init__(self, frames: DepthFrames, method: str, device: str):
        import open3d as o3d

        self.o3d, self.odometry = o3d, o3d.t.pipelines.odometry
        self.device = o3d.core.Device("CUDA:0" if device == "cuda" else "CPU:0")
        self.K = o3d.core.Tensor(frames.K[0].double().numpy())
        self.method = getattr(self.odometry.Method, method)
        self.identity = o3d.core.Tensor(np.eye(4))
        self.poses: list[np.ndarray] = []
        self.previous = None
        self.first_unfit: int | None = None  # first frame whose fitness is below ours' inlier-share bar

    def image(self, depth: torch.Tensor, color: torch.Tensor):
        geometry = self.o3d.t.geometry
        return geometry.RGBDImage(geometry.Image(self.o3d.core.Tensor(color.contiguous().numpy())).to(self.device),
                                  geometry.Image(self.o3d.core.Tensor(depth.numpy()[..., None])).to(self.device))

    def track(self, depth: torch.Tensor, color: torch.Tensor) -> None:
        image = self.image(depth, color)
        if self.previous is None:
            self.poses.append(np.eye(4))
        else:
            result = self.odometry.rgbd_odometry_multi_scale(
                image, self.previous, self.K, init_source_to_target=self.identity, depth_scale=1.0,
                depth_max=MAX_DEPTH, method=self.method)
            if self.first_unfit is None and result.fitness < 0.3:
                self.first_unfit = len(self.poses)
            self.poses.append(self.poses[-1] @ result.transformation.cpu().numpy())
        self.previous = image


def interleaved(frames: DepthFrames, device: str, reference: bool) -> dict[str, tuple]:
    """Every tracker over the frames, one frame each in turn (load from other processes hits them
    alike): {label: (poses (n, 4, 4) or None, wall and CPU seconds per frame after the first, error or None)}."""
    colors = frames.colors if frames.colors is not None else frames.depth[..., None].expand(-1, -1, -1, 3) / MAX_DEPTH
    depth = frames.depth.to(device)
    trackers = {f"ours ({mode})": Tracker(frames.K[0], mode=mode) for mode in ("model", "frame")}
    if device == "cpu":
        trackers["ours (model, compiled)"] = Tracker(frames.K[0], compiled=True)
    if frames.colors is not None:
        trackers["ours (model, photometric)"] = Tracker(frames.K[0], photometric=PHOTOMETRIC)
    if reference:
        trackers.update({f"Open3D {m}": Open3DOdometry(frames, m, device) for m in ("Hybrid", "PointToPlane")})
    seconds, cpu = dict.fromkeys(trackers, 0.0), dict.fromkeys(trackers, 0.0)
    lost: dict[str, Exception] = {}
    for i in range(len(frames)):
        for label, tracker in trackers.items():
            if label in lost:
                continue
            start, start_cpu = time.perf_counter(), time.process_time()
            try:
                if isinstance(tracker, Tracker):
                    tracker.track(depth[i], colors[i].to(device) if tracker.photometric else None)
                    if device == "cuda":
                        torch.cuda.synchronize()
                else:
                    tracker.track(frames.depth[i], colors[i])
            except TrackingLostError as error:
                lost[label] = error
            if i > 0:
                seconds[label] += time.perf_counter() - start
                cpu[label] += time.process_time() - start_cpu
    for label, tracker in trackers.items():  # ours fuses a frame while it prepares the next: the last one's fusion
        if isinstance(tracker, Tracker) and label not in lost:
            start, start_cpu = time.perf_counter(), time.process_time()
            _ = tracker.volume  # fuses the last frame
            seconds[label] += time.perf_counter() - start
            cpu[label] += time.process_time() - start_cpu
    rows = {}
    for label, tracker in trackers.items():
        poses = None if label in lost else np.stack([np.asarray(p) for p in tracker.poses])
        note = lost.get(label) or (None if isinstance(tracker, Tracker) or tracker.first_unfit is None
                                   else f"fitness < 0.3 first at frame {tracker.first_unfit}")
        rows[label] = (poses, seconds[label] / (len(frames) - 1), cpu[label] / (len(frames) - 1), note)
    return rows


def scores(estimated: np.ndarray | torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    estimated = torch.as_tensor(estimated, dtype=torch.float64)
    truth = truth[: len(estimated)].double()
    rpe = relative_pose_error(estimated, truth)
    return {"ate_cm": 100 * absolute_trajectory_error(estimated, truth), "rpe_cm": 100 * rpe.translation,
            "rpe_deg": rpe.rotation}


def held_out_error(frames: DepthFrames, poses: torch.Tensor, device: str) -> tuple[float, float]:
    """Median depth error (cm) on every 10th frame of the mesh fused from the others at `poses`: from the held-out
    frames' given poses, and from those poses registered to the mesh (`localised_depth_metrics`)."""
    index = torch.arange(len(frames))
    held = index % 10 == 9
    fused = DepthFrames(frames.depth[~held], frames.K[~held], poses[~held].float())
    volume = TSDFVolume(depth_bounds(fused, 0.05), 0.01, device=device, sparse=True)
    mesh = volume.integrate(fused, progress=False).extract_mesh()
    held_out = frames[index[held]]
    return (100 * depth_metrics(mesh, held_out)["depth_error_median"],
            100 * localised_depth_metrics(mesh, held_out)["localised_depth_error_median"])


def run(name: str, folder: str, device: str, max_frames: int | None, fuse: bool, reference: bool) -> None:
    frames = read_rgbd_folder(data_root() / folder, max_frames=max_frames, with_color=reference, progress=False)
    depth = torch.where(frames.depth <= MAX_DEPTH, frames.depth, 0.0)
    frames = DepthFrames(depth, frames.K, frames.cam_to_world, frames.colors)
    truth = frames.cam_to_world.double()
    print(f"\n== {name}: {len(frames)} frames {frames.width}x{frames.height}, device {device}")
    for compiled in (False, True) if device == "cpu" else (False,):  # first calls (allocations, compilation) untimed
        start = time.perf_counter()
        warm = Tracker(frames.K[0], compiled=compiled)
        warm.track(frames.depth[0].to(device)), warm.track(frames.depth[1].to(device))
        print(f"  warm-up {'compiled' if compiled else 'eager'}: {time.perf_counter() - start:.1f} s")
    if reference:
        colors = frames.colors if frames.colors is not None else frames.depth[..., None].expand(-1, -1, -1, 3)
        warm_open3d = Open3DOdometry(frames, "Hybrid", device)
        warm_open3d.track(frames.depth[0], colors[0]), warm_open3d.track(frames.depth[1], colors[1])
    rows = interleaved(frames, device, reference)
    baseline = "Open3D Hybrid" if reference else "ours (model)"
    for label, (poses, per_frame, cpu_per_frame, note) in rows.items():
        if poses is None:
            print(f"  {label:22s} stopped: {note}")
            continue
        s = scores(poses, truth)
        wall, cpu = per_frame / rows[baseline][1], cpu_per_frame / rows[baseline][2]
        print(f"  {label:22s} ATE {s['ate_cm']:6.2f} cm  RPE {s['rpe_cm']:5.2f} cm {s['rpe_deg']:5.2f} deg  "
              f"{1000 * per_frame:6.1f} ms/frame ({wall:.2f}x), CPU {1000 * cpu_per_frame:6.1f} ms ({cpu:.2f}x "
              f"{baseline})" + (f"  ({note})" if note else ""))
    if fuse and reference:  # the meshes are ray-cast by Open3D
        given, given_localised = held_out_error(frames, truth, device)
        print(f"  held-out median depth error, mesh fused at the given poses: {given:.2f} cm from the given "
              f"views, {given_localised:.2f} cm from views registered to the mesh")
        for label, (poses, *_) in rows.items():
            if poses is not None and label.startswith("ours") and "compiled" not in label:
                aligned = align_trajectory(torch.as_tensor(poses), truth) @ torch.as_tensor(poses)
                tracked, localised = held_out_error(frames, aligned, device)
                print(f"  ... at {label} poses: {tracked:.2f} cm ({tracked / given:.2f}x), registered views "
                      f"{localised:.2f} cm ({localised / given_localised:.2f}x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--sequences", nargs="+", default=list(SEQUENCES), choices=list(SEQUENCES))
    parser.add_argument("--no-fuse", action="store_true", help="skip the held-out depth error of fused meshes")
    parser.add_argument("--no-open3d", action="store_true", help="ours only (where Open3D is not installed)")
    args = parser.parse_args()
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, load average {os.getloadavg()}")
    for name in args.sequences:
        run(name, SEQUENCES[name], args.device, args.max_frames, not args.no_fuse, not args.no_open3d)
    print(f"load average at the end {os.getloadavg()}")


if __name__ == "__main__":
    main()
