"""TSDF fusion on a CUDA GPU: frames/s at 640 x 480, against our CPU run of the same frames.

    python benchmarks/bench_tsdf_cuda.py                              # renders the bunny views (Open3D)
    python benchmarks/bench_tsdf_cuda.py --save-frames /tmp/views.npz # render once, keep them
    python benchmarks/bench_tsdf_cuda.py --frames /tmp/views.npz --data DIR  # where Open3D is absent

Bunny: `--views` exact 640 x 480 views from `scan_depth` (orbit cameras), fused into a dense 256^3
grid over the bunny's box (voxel = longest side / 248, 4 blocks of margin), truncation 3 voxels, and
into the sparse volume on the same grid. Each integration of all views runs `--repeats` times on the
GPU (after one warm-up, with torch.cuda.synchronize) and once on the CPU over `--cpu-views` views;
printed: frames/s on each and their ratio, and how far the GPU and CPU meshes are apart (mean
distance of the GPU mesh's vertices to the CPU mesh, in voxels).

7-Scenes (redkitchen, 100 frames 640 x 480, `--data` or $NEURALSURF_DATA or the fetch cache): sparse
1 cm and 2 cm volumes, truncation 3 voxels, on the GPU and the CPU: ms/frame, blocks, peak GPU
memory; beside them Open3D's VoxelBlockGrid on CUDA (its fastest path: compute_unique_block_coordinates
then integrate per frame, after one warm-up run) on the same frames and grid, with the ratio of our
GPU time to its time, the vertex counts and the median gap of our mesh to its mesh in voxels. That
row needs an Open3D wheel built with CUDA (open3d.core.cuda.is_available()); else it says so.

Open3D's CPU figures: benchmarks/bench_tsdf.py. Without a CUDA GPU the script says so and exits.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from open3d_tsdf import integrate_voxel_block_grid, voxel_block_grid, voxel_block_grid_inputs  # this folder

from neuralsurf.baselines import FusionSettings, TSDFVolume, depth_bounds
from neuralsurf.scenes.recipes import data_root
from neuralsurf.structures import DepthFrames

ROOT = Path(__file__).resolve().parents[1]


def bunny_views(args) -> tuple[DepthFrames, torch.Tensor]:
    """The views and the bunny's (2, 3) box: rendered (Open3D), or loaded from --frames."""
    if args.frames:
        data = np.load(args.frames)
        frames = DepthFrames(*(torch.from_numpy(data[k]) for k in ("depth", "K", "cam_to_world")))
        return frames, torch.from_numpy(data["box"])
    from neuralsurf.scenes import bunny, scan_depth

    truth = bunny()
    frames = scan_depth(truth, n_views=args.views, width=640, height=480)
    box = truth.bounds.double()
    if args.save_frames:
        np.savez_compressed(args.save_frames, depth=frames.depth.numpy(), K=frames.K.numpy(),
                            cam_to_world=frames.cam_to_world.numpy(), box=box.numpy())
    return frames, box


def timed_integration(volume: TSDFVolume, frames: DepthFrames) -> float:
    """Seconds to fuse `frames` (already on the volume's device)."""
    if volume.device.type == "cuda":
        torch.cuda.synchronize()
    started = time.perf_counter()
    volume.integrate(frames)
    if volume.device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - started


def on(frames: DepthFrames, device: str) -> DepthFrames:
    return DepthFrames(*(t.to(device) for t in (frames.depth, frames.K, frames.cam_to_world)))


def mesh_gap_voxels(gpu: TSDFVolume, cpu: TSDFVolume) -> float:
    """Mean distance from the GPU mesh's vertices to the CPU mesh's nearest vertex, in voxels."""
    from scipy.spatial import cKDTree

    a, b = gpu.extract_mesh().vertices.double().numpy(), cpu.extract_mesh().vertices.double().numpy()
    return float(cKDTree(b).query(a)[0].mean() / gpu.voxel_size)


def bench_bunny(args) -> None:
    frames, (lo, hi) = bunny_views(args)
    voxel = float((hi - lo).max()) / 248
    bounds = torch.stack([lo - 4 * voxel, lo - 4 * voxel + 255 * voxel])  # 256 grid points per side
    gpu_frames = on(frames, "cuda")
    cpu_frames = frames[: args.cpu_views]
    print(f"\nBunny: {len(frames)} views 640x480, voxel {voxel * 1000:.3f} mm, truncation 3 voxels")
    header = (f"{'volume':8} {'grid':>12} {'per pass':>9} {'GPU frames/s':>13} {'CPU frames/s':>13} "
              f"{'GPU/CPU':>8} {'mesh gap':>9}")
    print(header + "\n" + "-" * len(header))
    for sparse in (False, True):
        make = lambda device, n=None, sparse=sparse: TSDFVolume(bounds, voxel, 3 * voxel, sparse=sparse, device=device,
                                                                fusion=FusionSettings(frames_per_pass=n))
        cpu_seconds = timed_integration(cpu := make("cpu"), cpu_frames)
        gap = mesh_gap_voxels(make("cuda").integrate(gpu_frames[: args.cpu_views]), cpu)
        cpu_fps = len(cpu_frames) / cpu_seconds
        for n in args.frames_per_pass:
            timed_integration(make("cuda", n), gpu_frames)  # warm-up: kernels, allocator
            runs = [timed_integration(gpu := make("cuda", n), gpu_frames) for _ in range(args.repeats)]
            gpu_seconds = min(runs)
            gpu_fps = len(frames) / gpu_seconds
            print(f"{'sparse' if sparse else 'dense':8} {'x'.join(map(str, gpu.grid_shape)):>12} {n:>9} "
                  f"{gpu_fps:>13.0f} {cpu_fps:>13.1f} {gpu_fps / cpu_fps:>7.0f}x {gap:>8.4f}v")
    print(f"CPU: {args.cpu_views} views, one per pass, {torch.get_num_threads()} threads; mesh gap: GPU "
          f"(default frames per pass) vs CPU mesh of the same {args.cpu_views} views, mean vertex distance in "
          f"voxels")


def voxel_block_grid_cuda(frames: DepthFrames, voxel: float) -> tuple[float, np.ndarray] | None:
    """Open3D's VoxelBlockGrid on CUDA: (seconds for all frames, mesh vertices), or None without CUDA
    in Open3D."""
    import open3d as o3d

    if not o3d.core.cuda.is_available():
        return None
    inputs = voxel_block_grid_inputs(frames, "CUDA:0")
    integrate_voxel_block_grid(voxel_block_grid(voxel, device="CUDA:0"), inputs, voxel, 3 * voxel)  # warm-up
    grid = voxel_block_grid(voxel, device="CUDA:0")
    o3d.core.cuda.synchronize()
    started = time.perf_counter()
    integrate_voxel_block_grid(grid, inputs, voxel, 3 * voxel)
    o3d.core.cuda.synchronize()
    seconds = time.perf_counter() - started
    mesh = grid.extract_triangle_mesh(weight_threshold=0.0).to_legacy()
    return seconds, np.asarray(mesh.vertices)


def bench_kitchen(data: Path, frames_per_pass: list[int], threads: int | None) -> None:
    from scipy.spatial import cKDTree

    from neuralsurf.io import read_rgbd_folder

    folder = data / "7scenes_redkitchen_every10"
    if not folder.is_dir():
        print(f"\n7-Scenes: skipped, {folder} not found (--data or NEURALSURF_DATA)")
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = read_rgbd_folder(folder, format="7scenes", with_color=False)
    print(f"\n7-Scenes redkitchen: {len(frames)} frames 640x480, sparse, truncation 3 voxels")
    header = (f"{'voxel':6} {'per pass':>9} {'GPU ms/frame':>13} {'CPU ms/frame':>13} {'GPU/CPU':>8} {'blocks':>8} "
              f"{'GPU peak MB':>12} {'vertices':>9} {'VBG ms/frame':>13} {'ours/VBG':>9} {'VBG vertices':>13} "
              f"{'gap (vox)':>10}")
    print(header + "\n" + "-" * len(header))
    for voxel in (0.02, 0.01):
        bounds = depth_bounds(frames, margin=0.05)
        bounds = torch.stack([torch.floor(bounds[0] / voxel) * voxel, bounds[1]])  # on Open3D's grid
        make = lambda device, n=None, bounds=bounds, voxel=voxel: TSDFVolume(
            bounds, voxel, 3 * voxel, sparse=True, device=device,
            fusion=FusionSettings(frames_per_pass=n, threads=threads))
        cpu_seconds = timed_integration(make("cpu"), frames)
        theirs = voxel_block_grid_cuda(frames, voxel)
        for n in frames_per_pass:
            timed_integration(make("cuda", n), on(frames, "cuda"))  # warm-up
            torch.cuda.reset_peak_memory_stats()
            gpu_seconds = timed_integration(gpu := make("cuda", n), on(frames, "cuda"))
            peak = torch.cuda.max_memory_allocated() / 2**20
            vertices = gpu.extract_mesh().vertices.double().numpy()
            row = (f"{voxel * 100:.0f} cm {n:>9} {gpu_seconds / len(frames) * 1e3:>13.2f} "
                   f"{cpu_seconds / len(frames) * 1e3:>13.1f} {cpu_seconds / gpu_seconds:>7.0f}x "
                   f"{gpu.n_blocks:>8} {peak:>12.0f} {len(vertices):>9,}")
            if theirs is None:
                row += f" {'(no CUDA in Open3D)':>13}"
            else:
                gap = float(np.median(cKDTree(theirs[1]).query(vertices)[0]) / voxel)
                row += (f" {theirs[0] / len(frames) * 1e3:>13.2f} {gpu_seconds / theirs[0]:>8.2f}x "
                        f"{len(theirs[1]):>13,} {gap:>10.2f}")
            print(row)
    print("VBG: Open3D's VoxelBlockGrid on CUDA, same frames and grid; ours/VBG < 1: ours faster; gap: median "
          "distance of our vertices to its vertices")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--views", type=int, default=100, help="bunny views to render")
    parser.add_argument("--cpu-views", type=int, default=10, help="of those, fused on the CPU for the ratio")
    parser.add_argument("--repeats", type=int, default=5, help="GPU: best of this many integrations")
    parser.add_argument("--frames", help="load the bunny views from this .npz (from --save-frames)")
    parser.add_argument("--save-frames", help="render the bunny views, save them here, and go on")
    parser.add_argument("--data", default=data_root())
    parser.add_argument("--threads", type=int, default=1, help="CPU threads of our CPU runs (FusionSettings(threads=...))")
    parser.add_argument("--frames-per-pass", type=int, nargs="+", default=[1, 8, 16, 32],
                        help="GPU: frames fused per pass (FusionSettings.frames_per_pass), one row each")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        if args.save_frames:
            bunny_views(args)
            print(f"saved {args.views} views to {args.save_frames}")
        print("no CUDA GPU: this benchmark (ours and Open3D's VoxelBlockGrid on CUDA) needs one; skipped. "
              "CPU figures, VoxelBlockGrid included: benchmarks/bench_tsdf.py")
        return
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name(0)}, {os.cpu_count()} CPU cores")
    bench_bunny(args)
    bench_kitchen(Path(args.data), args.frames_per_pass, args.threads)


if __name__ == "__main__":
    main()
