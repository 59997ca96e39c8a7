"""The bunny fitted by the hash-grid MLP alone (experiment=bunny_mlp), end to end: fit steps/s, extraction time
(dense vs coarse-to-fine) and peak memory, with Open3D's screened Poisson on the same 100k oriented points as the
reference, in one run (train.py's default, which refines a start, against Poisson: bench_points.py).

    python benchmarks/bench_bunny.py [--steps 1500] [--device auto] [--resolutions 256 512]

Peak memory is the process's resident set high-water mark, reset before each phase (Linux), and
on CUDA the allocator's peak.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import neuralsurf as ns

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def reset_peak_memory() -> None:
    """Reset the RSS high-water mark (Linux clear_refs) and CUDA's peak counter."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()


def peak_memory_mib() -> str:
    rss = next((int(line.split()[1]) / 1024 for line in Path("/proc/self/status").read_text().splitlines()
                if line.startswith("VmHWM")), float("nan"))
    cuda = f", CUDA {torch.cuda.max_memory_allocated() / 2**20:.0f} MiB" if torch.cuda.is_available() else ""
    return f"RSS {rss:.0f} MiB{cuda}"


def timed(label: str, rows: list, function, *args, **kwargs):
    reset_peak_memory()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    started = time.perf_counter()
    value = function(*args, **kwargs)
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    seconds = time.perf_counter() - started
    rows.append((label, seconds, peak_memory_mib()))
    print(f"{label:<42} {seconds:8.2f} s   {rows[-1][2]}", flush=True)
    return value, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=None, help="fit steps (default: the experiment's)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--skip-dense-512", action="store_true", help="dense 512^3 takes minutes on a CPU")
    args = parser.parse_args()

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=bunny_mlp"])
    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    trainer.update(steps=args.steps or trainer["steps"], progress=False, image_every=0)
    device = ns.training.resolve_device(args.device)
    print(f"machine: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
          f"torch {torch.__version__}, device {device}"
          + (f" ({torch.cuda.get_device_name()})" if device.type == "cuda" else ""))

    rows: list = []
    gt = ns.scenes.bunny()
    cloud = ns.geometry.cloud_from_mesh(gt, n=100_000, noise=0.0, seed=0)
    observation = instantiate(cfg.observation.points, _convert_="all")(ns.scenes.Scene("bunny", cloud, gt))
    if device.type == "cuda":  # the CUDA context and kernel loading, once per process: not the fit's
        timed("CUDA warm-up: a 20-step fit", rows, ns.fit, instantiate(cfg.model, _convert_="all"), observation,
              optimizer=instantiate(cfg.optimizer), device=device, **{**trainer, "steps": 20})
    torch.manual_seed(0)
    model = instantiate(cfg.model, _convert_="all")
    result, fit_seconds = timed(f"fit, {trainer['steps']} steps", rows, ns.fit, model, observation,
                                optimizer=instantiate(cfg.optimizer), device=device, **trainer)
    print(f"  -> {result.steps / fit_seconds:.2f} steps/s overall (sampling included); "
          f"{result.history['steps_per_s'][-1]:.2f} steps/s in the last logging window")

    extract = OmegaConf.to_container(cfg.extract)  # the experiment's chunks, as train.py extracts
    extract = {k: v for k, v in extract.items()
               if k not in ("resolution", "coarse_to_fine", "near_distance", "onto_points")}
    meshes = {}
    for resolution in args.resolutions:
        for coarse_to_fine in (False, True):
            if resolution >= 512 and not coarse_to_fine and args.skip_dense_512:
                continue
            mode = "coarse-to-fine" if coarse_to_fine else "dense"
            meshes[resolution, mode], _ = timed(f"extract {resolution}^3 {mode}", rows, ns.extract_mesh,
                                                result.field, resolution=resolution, coarse_to_fine=coarse_to_fine,
                                                **extract)
    for resolution in args.resolutions:
        dense = next((s for label, s, _ in rows if label == f"extract {resolution}^3 dense"), None)
        fine = next(s for label, s, _ in rows if label == f"extract {resolution}^3 coarse-to-fine")
        if dense:
            print(f"  -> {resolution}^3: coarse-to-fine is {dense / fine:.1f}x faster than dense")

    mesh = meshes[args.resolutions[0], "coarse-to-fine"]
    metrics, _ = timed("metrics (100k samples)", rows, ns.metrics.evaluate_mesh, mesh, gt)

    import open3d as o3d

    (poisson, _), poisson_seconds = timed(
        "reference: Open3D screened Poisson, depth 9", rows,
        o3d.geometry.TriangleMesh.create_from_point_cloud_poisson, cloud.to_open3d(), depth=9)
    reference = ns.metrics.evaluate_mesh(ns.Mesh.from_open3d(poisson), gt)
    total = fit_seconds + next(s for label, s, _ in rows if label == f"extract {args.resolutions[0]}^3 coarse-to-fine")
    print(f"\nneural (fit + extract {args.resolutions[0]}^3): {total:.1f} s, exact Chamfer-L1 "
          f"{metrics['chamfer_l1_exact']:.3e}, F@0.5% {metrics['fscore_0.5%']:.4f}, watertight {mesh.is_watertight}")
    print(f"Open3D Poisson:                  {poisson_seconds:.1f} s, exact Chamfer-L1 "
          f"{reference['chamfer_l1_exact']:.3e}, F@0.5% {reference['fscore_0.5%']:.4f}")
    print(f"time ratio neural / Poisson: {total / poisson_seconds:.1f}x")


if __name__ == "__main__":
    main()
