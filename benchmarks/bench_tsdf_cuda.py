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

7-Scenes (redkitchen, 100 frames 640 x 480, `--data` or $NEURALSURF_DATA or ../shared/data): sparse
1 cm and 2 cm volumes on the GPU and the CPU: ms/frame, blocks, peak GPU memory.

The CPU side is ours, not Open3D's (Open3D's CPU figures: benchmarks/bench_tsdf.py); the GPU
machine need not have Open3D. Without a GPU the script says so and exits.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from neuralsurf.baselines import TSDFVolume, depth_bounds
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
        make = lambda device, n=None: TSDFVolume(bounds, voxel, 3 * voxel, device=device, sparse=sparse,
                                                 frames_per_pass=n)
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


def bench_kitchen(data: Path, frames_per_pass: list[int]) -> None:
    from neuralsurf.io import read_rgbd_folder

    folder = data / "7scenes_redkitchen_every10"
    if not folder.is_dir():
        print(f"\n7-Scenes: skipped, {folder} not found (--data or NEURALSURF_DATA)")
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = read_rgbd_folder(folder, format="7scenes", with_color=False)
    bounds = depth_bounds(frames, margin=0.05)
    print(f"\n7-Scenes redkitchen: {len(frames)} frames 640x480, sparse, truncation 4 voxels")
    header = (f"{'voxel':6} {'per pass':>9} {'GPU ms/frame':>13} {'CPU ms/frame':>13} {'GPU/CPU':>8} {'blocks':>8} "
              f"{'GPU peak MB':>12} {'faces':>9}")
    print(header + "\n" + "-" * len(header))
    for voxel in (0.02, 0.01):
        make = lambda device, n=None: TSDFVolume(bounds, voxel, 4 * voxel, device=device, sparse=True,
                                                 frames_per_pass=n)
        cpu_seconds = timed_integration(make("cpu"), frames)
        for n in frames_per_pass:
            timed_integration(make("cuda", n), on(frames, "cuda"))  # warm-up
            torch.cuda.reset_peak_memory_stats()
            gpu_seconds = timed_integration(gpu := make("cuda", n), on(frames, "cuda"))
            peak = torch.cuda.max_memory_allocated() / 2**20
            faces = len(gpu.extract_mesh().faces)
            print(f"{voxel * 100:.0f} cm {n:>9} {gpu_seconds / len(frames) * 1e3:>13.2f} "
                  f"{cpu_seconds / len(frames) * 1e3:>13.1f} {cpu_seconds / gpu_seconds:>7.0f}x "
                  f"{gpu.n_blocks:>8} {peak:>12.0f} {faces:>9,}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--views", type=int, default=100, help="bunny views to render")
    parser.add_argument("--cpu-views", type=int, default=10, help="of those, fused on the CPU for the ratio")
    parser.add_argument("--repeats", type=int, default=5, help="GPU: best of this many integrations")
    parser.add_argument("--frames", help="load the bunny views from this .npz (from --save-frames)")
    parser.add_argument("--save-frames", help="render the bunny views, save them here, and go on")
    parser.add_argument("--data", default=os.environ.get("NEURALSURF_DATA", ROOT.parent / "shared" / "data"))
    parser.add_argument("--threads", type=int, default=None, help="CPU threads of torch")
    parser.add_argument("--frames-per-pass", type=int, nargs="+", default=[1, 8, 16, 32],
                        help="GPU: frames fused per pass (TSDFVolume.frames_per_pass), one row each")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if not torch.cuda.is_available():
        if args.save_frames:
            bunny_views(args)
            print(f"saved {args.views} views to {args.save_frames}")
        print("no CUDA GPU: this benchmark needs one (CPU figures: benchmarks/bench_tsdf.py)")
        return
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name(0)}, {os.cpu_count()} CPU cores")
    bench_bunny(args)
    bench_kitchen(Path(args.data), args.frames_per_pass)


if __name__ == "__main__":
    main()
