"""Depth maps to a surface: the neural fit from rays (experiment bunny_depth) against TSDF fusion of the
same frames, in one run: time, peak memory and accuracy, as ratios.

    python benchmarks/bench_depth.py [--steps N] [--device auto] [--views 24]

On a GPU the fit and TSDF run there; without one the script says it ran on the CPU.
"""

from __future__ import annotations

import argparse
import platform

import torch
from bench_bunny import CONFIGS, timed
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import neuralsurf as ns
from neuralsurf.cli import without_feeds
from neuralsurf.evaluation.methods import tsdf


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=None, help="fit steps (default: the experiment's)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--views", type=int, default=24)
    args = parser.parse_args()

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["experiment=bunny_depth", f"data.n_views={args.views}"])
    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    trainer.update(steps=args.steps or trainer["steps"], progress=False, image_every=0)
    device = ns.training.resolve_device(args.device)
    print(f"machine: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
          f"torch {torch.__version__}, device {device}"
          + (f" ({torch.cuda.get_device_name()})" if device.type == "cuda" else " (no GPU: CPU figures)"))

    rows: list = []
    scene = instantiate(without_feeds(cfg).data)
    print(scene.description)
    torch.manual_seed(0)
    model = instantiate(cfg.model, _convert_="all")
    observation = instantiate(cfg.observation.rays, _convert_="all")(scene)
    result, fit_seconds = timed(f"neural fit from rays, {trainer['steps']} steps", rows, ns.fit, model, observation,
                                optimizer=instantiate(cfg.optimizer), device=device, **trainer)
    extract = {k: v for k, v in OmegaConf.to_container(cfg.extract, resolve=True).items()
               if k not in ("near_distance", "onto_points")}
    mesh, extract_seconds = timed("extract 256^3 coarse-to-fine", rows, ns.extract_mesh, result.field, **extract)
    fused, tsdf_seconds = timed("reference: TSDF fusion, 1/256 voxels", rows, tsdf, scene, device=str(device))
    neural = ns.metrics.evaluate_mesh(mesh, scene.ground_truth)
    reference = ns.metrics.evaluate_mesh(fused, scene.ground_truth)
    total = fit_seconds + extract_seconds
    for name, metrics, seconds, m in (("neural (rays)", neural, total, mesh), ("TSDF", reference, tsdf_seconds, fused)):
        print(f"{name:<14} {seconds:8.1f} s, exact Chamfer-L1 {metrics['chamfer_l1_exact']:.3e}, "
              f"normal consistency {metrics['normal_consistency']:.4f}, watertight {m.is_watertight}")
    print(f"time ratio neural / TSDF: {total / tsdf_seconds:.1f}x; Chamfer ratio "
          f"{neural['chamfer_l1_exact'] / reference['chamfer_l1_exact']:.2f}")


if __name__ == "__main__":
    main()
