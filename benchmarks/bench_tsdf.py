"""TSDF fusion, ours against Open3D's fastest path (tensor VoxelBlockGrid) and its legacy
UniformTSDFVolume, in one run: ms/frame and its ratio, mesh vertices and their ratio, and how far our
mesh lies from VoxelBlockGrid's (median distance of our vertices to its vertices, in voxels).

    python benchmarks/bench_tsdf.py                       # the bunny and 7-Scenes redkitchen
    python benchmarks/bench_tsdf.py --skip-7scenes        # the bunny only (no real data needed)
    python benchmarks/bench_tsdf.py --threads 2           # our torch threads (default TSDFVolume's "auto")

Settings shared by all: the same frames, voxel size and truncation (3 voxels), grids that coincide
(ours starts on a multiple of the voxel size, as Open3D's grids do), blocks of 8^3 voxels, meshes of
every voxel observed at least once (VoxelBlockGrid: weight_threshold 0; its default, 3, keeps voxels
seen 4 times or more). VoxelBlockGrid runs as Open3D's examples do (compute_unique_block_coordinates,
then integrate, per frame; Open3D's own threads, all cores); ours runs TSDFVolume's defaults (band
only, free_space 0; eager, torch on one thread) and, as "compiled", TSDFVolume(compiled=True) (torch.compile,
torch's threads): its one-time compilation runs on two frames before the timed run and is printed
apart ("warm-up s"; torch caches compiled code on disk, so runs after the first compile less). Times
cover integration only; frames are decoded and converted before. Rows run round robin, best of --repeats, so that load from other processes hits
them alike; the load average is printed. On CUDA (VoxelBlockGrid and ours): bench_tsdf_cuda.py.

Bunny: 24 exact 320 x 240 views from `scan_depth`, voxel = longest side of the box / 256; also the
Chamfer-L1 (exact, unit frame) of each mesh against the bunny.

7-Scenes (redkitchen, every 10th frame: 100 frames of 640 x 480, Kinect v1; $NEURALSURF_DATA or
the fetch cache) at 1 cm and 2 cm: each row runs in its own subprocess, so that its peak RSS is its
own ("fusion MB": peak RSS during integration and extraction minus the RSS before). UniformTSDFVolume
is a cube over the room's box: at 1 cm it would take about 290 M voxels (> 10 GB), so it runs at
2 cm only. Our 1 cm mesh is written to /tmp/redkitchen_tsdf_1cm.ply for a look.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from neuralsurf.scenes.recipes import data_root

ROOT = Path(__file__).resolve().parents[1]
DATA = data_root()
KITCHEN = DATA / "7scenes_redkitchen_every10"
MESH_OUT = Path("/tmp/redkitchen_tsdf_1cm.ply")
WARM_UP: dict[str, float] = {}
"""Seconds of the one-time compilation in this process, by method."""


def peak_mb() -> float:
    """Peak RSS of this process since start (or since `reset_peak`), from /proc (Linux)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def current_mb() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def reset_peak() -> None:
    """Make the peak RSS start again from the current RSS (Linux: clear_refs 5), so that it measures
    the fusion only and not the transient of decoding the frames."""
    try:
        with open("/proc/self/clear_refs", "w") as clear:
            clear.write("5")
    except OSError:
        pass


def snapped(bounds: torch.Tensor, voxel: float) -> torch.Tensor:
    """(2, 3) bounds whose min corner is a multiple of `voxel`: our grid points on Open3D's."""
    return torch.stack([torch.floor(bounds[0] / voxel) * voxel, bounds[1]])


def median_gap(ours: np.ndarray, theirs: np.ndarray, voxel: float) -> float:
    """Median distance from our mesh's vertices to the nearest vertex of theirs, in voxels."""
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(theirs).query(ours)[0]) / voxel)


def fuse(method: str, frames, bounds: torch.Tensor, voxel: float, **options) -> tuple[float, object]:
    """Seconds to integrate all frames with `method`, and what to extract the mesh from."""
    from neuralsurf.baselines import TSDFVolume
    from neuralsurf.baselines.tsdf import (
        integrate_voxel_block_grid,
        open3d_frame,
        voxel_block_grid,
        voxel_block_grid_inputs,
    )

    truncation = 3 * voxel
    if method == "vbg":
        grid, inputs = voxel_block_grid(voxel), voxel_block_grid_inputs(frames)
        started = time.perf_counter()
        integrate_voxel_block_grid(grid, inputs, voxel, truncation)
        return time.perf_counter() - started, grid
    if method == "uniform":
        import open3d as o3d

        integration = o3d.pipelines.integration
        resolution = int(np.ceil(float((bounds[1] - bounds[0]).max()) / voxel)) + 1
        volume = integration.UniformTSDFVolume(
            length=resolution * voxel, resolution=resolution, sdf_trunc=truncation,
            color_type=integration.TSDFVolumeColorType.NoColor, origin=(bounds[0] - 0.5 * voxel).numpy(),
        )
        inputs = [open3d_frame(frames[i]) for i in range(len(frames))]
        started = time.perf_counter()
        for item in inputs:
            volume.integrate(*item)
        return time.perf_counter() - started, volume
    options = dict(options, sparse=method != "dense", compiled=method == "compiled")
    if method == "compiled":  # the one-time compilation, apart
        started = time.perf_counter()
        TSDFVolume(bounds, voxel, truncation, device="cpu", **options).integrate(frames[:2], progress=False)
        WARM_UP[method] = max(WARM_UP.get(method, 0.0), time.perf_counter() - started)  # the first, compiling
    volume = TSDFVolume(bounds, voxel, truncation, device="cpu", **options)
    started = time.perf_counter()
    volume.integrate(frames, progress=False)
    return time.perf_counter() - started, volume


def extract(method: str, fused):
    from neuralsurf.structures import Mesh

    if method == "vbg":
        return Mesh.from_open3d(fused.extract_triangle_mesh(weight_threshold=0.0).to_legacy())
    if method == "uniform":
        return Mesh.from_open3d(fused.extract_triangle_mesh())
    return fused.extract_mesh()


# ------------------------------------------------------------------------------------ bunny


def bench_bunny(repeats: int, threads: int | str) -> None:
    from neuralsurf.metrics import evaluate_mesh
    from neuralsurf.scenes import bunny, scan_depth

    truth = bunny()
    frames = scan_depth(truth, n_views=24, width=320, height=240)
    lo, hi = truth.bounds.double()
    voxel = float((hi - lo).max()) / 256
    bounds = snapped(torch.stack([lo - 8 * voxel, hi + 8 * voxel]), voxel)
    rows = (("vbg", "Open3D VoxelBlockGrid"), ("uniform", "Open3D Uniform"), ("dense", "ours dense"),
            ("sparse", "ours sparse"), ("compiled", "ours sparse compiled"))
    best, fused = {}, {}
    for _ in range(repeats):
        for method, _ in rows:
            seconds, fused[method] = fuse(method, frames, bounds, voxel, threads=threads)
            best[method] = min(best.get(method, np.inf), seconds)
    meshes = {method: extract(method, fused[method]) for method, _ in rows}
    reference = meshes["vbg"].vertices.double().numpy()
    print(f"\nBunny: 24 views 320x240, voxel {voxel * 1000:.3f} mm (1/256 of the box), truncation 3 voxels, "
          f"best of {repeats}")
    header = (f"{'method':22} {'ms/frame':>9} {'vs VBG':>7} {'vertices':>9} {'vs VBG':>7} {'gap (vox)':>10} "
              f"{'chamfer_l1_exact':>17}")
    print(header + "\n" + "-" * len(header))
    for method, label in rows:
        mesh = meshes[method]
        ms = best[method] / len(frames) * 1000
        gap = median_gap(mesh.vertices.double().numpy(), reference, voxel)
        chamfer = float(evaluate_mesh(mesh, truth)["chamfer_l1_exact"])
        print(f"{label:22} {ms:>9.1f} {best[method] / best['vbg']:>6.2f}x {len(mesh.vertices):>9,} "
              f"{len(mesh.vertices) / len(reference):>6.3f}x {gap:>10.2f} {chamfer:>17.2e}")
    print("vs VBG: ratio to VoxelBlockGrid (time < 1: faster than it); gap: median distance of the mesh's "
          f"vertices to VoxelBlockGrid's, in voxels; compiled: warm-up (compilation) {WARM_UP['compiled']:.1f} s")


# ---------------------------------------------------------------------------------- 7-Scenes


def run_kitchen(config: dict) -> dict:
    """One 7-Scenes fusion in this process; returns its measurements (vertices saved for the gaps)."""
    from neuralsurf.baselines import depth_bounds
    from neuralsurf.io import read_rgbd_folder

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 7-Scenes colour is not registered to depth
        frames = read_rgbd_folder(KITCHEN, format="7scenes", with_color=False, progress=False)
    voxel, method = config["voxel"], config["method"]
    bounds = snapped(depth_bounds(frames, margin=0.05), voxel)
    load_peak = peak_mb()
    reset_peak()
    before = current_mb()
    seconds, fused = fuse(method, frames, bounds, voxel, threads=config["threads"])
    extract_started = time.perf_counter()
    mesh = extract(method, fused)
    result = {"ms_per_frame": seconds / len(frames) * 1000, "extract_s": time.perf_counter() - extract_started,
              "vertices": len(mesh.vertices), "peak_mb": max(load_peak, peak_mb()), "fusion_mb": peak_mb() - before}
    if method in WARM_UP:
        result["warm_up_s"] = WARM_UP[method]
    if method in ("dense", "sparse", "compiled"):
        result["blocks"] = fused.n_blocks
    if method == "vbg":
        result["blocks"] = int(fused.hashmap().size())
    np.save(config["vertices"], mesh.vertices.double().numpy())
    if method == "sparse" and voxel == 0.01:
        mesh.to_trimesh().export(MESH_OUT)
    return result


def run_subprocess(config: dict) -> dict:
    command = [sys.executable, __file__, "--one", json.dumps(config)]
    out = subprocess.run(command, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"{config} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_kitchen(threads: int | str, repeats: int) -> None:
    if not KITCHEN.is_dir():
        print(f"\n7-Scenes: skipped, {KITCHEN} not found (set NEURALSURF_DATA)")
        return
    runs = []
    for voxel in (0.01, 0.02):
        cm = f"{voxel * 100:.0f} cm"
        runs += [(f"Open3D VBG {cm}", "vbg", voxel), (f"ours sparse {cm}", "sparse", voxel),
                 (f"ours compiled {cm}", "compiled", voxel)]
        if voxel == 0.02:
            runs += [(f"ours dense {cm}", "dense", voxel), (f"Open3D Uniform {cm}", "uniform", voxel)]
    print(f"\n7-Scenes redkitchen (100 frames 640x480), truncation 3 voxels, one subprocess per row and run, "
          f"best of {repeats}", flush=True)
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(repeats):  # round robin, best time: machine load hits every row alike
            for label, method, voxel in runs:
                config = {"method": method, "voxel": voxel, "threads": threads,
                          "vertices": str(Path(folder) / f"{method}_{voxel}.npy")}
                row = run_subprocess(config)
                if label not in rows or row["ms_per_frame"] < rows[label]["ms_per_frame"]:
                    rows[label] = row
                rows[label]["vertices_file"] = config["vertices"]
        header = (f"{'method':22} {'ms/frame':>9} {'vs VBG':>7} {'vertices':>10} {'vs VBG':>7} {'gap (vox)':>10} "
                  f"{'blocks':>7} {'extract s':>10} {'fusion MB':>10} {'peak MB':>8} {'warm-up s':>10}")
        print(header + "\n" + "-" * len(header))
        for label, method, voxel in runs:
            row, reference = rows[label], rows[f"Open3D VBG {voxel * 100:.0f} cm"]
            gap = median_gap(np.load(row["vertices_file"]), np.load(reference["vertices_file"]), voxel)
            blocks = f"{row['blocks']:,}" if "blocks" in row else "-"
            print(f"{label:22} {row['ms_per_frame']:>9.1f} {row['ms_per_frame'] / reference['ms_per_frame']:>6.2f}x "
                  f"{row['vertices']:>10,} {row['vertices'] / reference['vertices']:>6.3f}x {gap:>10.2f} {blocks:>7} "
                  f"{row['extract_s']:>10.1f} {row['fusion_mb']:>10.0f} {row['peak_mb']:>8.0f} "
                  f"{row.get('warm_up_s', 0):>10.1f}")
    print("gap: median distance of the mesh's vertices to VoxelBlockGrid's, in voxels; blocks: allocated; fusion MB: "
          "peak RSS during fusion + extraction minus the RSS before")
    print(f"mesh for a look: {MESH_OUT}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=None, help="our torch threads (default: TSDFVolume's)")
    parser.add_argument("--repeats", type=int, default=3, help="bunny: best of this many integrations")
    parser.add_argument("--kitchen-repeats", type=int, default=2, help="7-Scenes: best of this many runs")
    parser.add_argument("--skip-7scenes", action="store_true")
    parser.add_argument("--skip-bunny", action="store_true")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_kitchen(json.loads(args.one))))
        return
    import open3d as o3d

    print(
        f"torch {torch.__version__} (ours on {args.threads or 'auto'} thread(s)), open3d {o3d.__version__} (its own threads), "
        f"{os.cpu_count()} CPU cores, CPU only; load average {os.getloadavg()[0]:.1f} at the start"
    )
    threads = args.threads or "auto"
    if not args.skip_bunny:
        bench_bunny(args.repeats, threads)
    if not args.skip_7scenes:
        bench_kitchen(threads, args.kitchen_repeats)
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
