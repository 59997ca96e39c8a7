"""Real rooms from depth frames: the neural voxel fit (method neural_voxels: TSDF fusion at half the tsdf method's
voxel as the start of a sparse voxel SDF, fitted to the rays in one least-squares solve and meshed on its observed
voxels) against TSDF fusion of the same frames (the tsdf method), in one run: time, peak memory, held-out depth
error (mean, median) and completeness, side by side. "TSDF fine" is TSDF fusion at the voxel fit's own voxel
(what the fit starts from): the fit's own part is the difference between it and the neural row.

    python benchmarks/bench_room.py [--scenes redkitchen,tum_fr1_desk] [--frames 50] [--mlp] [--maps DIR]

The sequences are 7-Scenes redkitchen and TUM RGB-D fr1/desk, read from $NEURALSURF_DATA or the fetch cache
(`python -m neuralsurf data fetch <name>`; one that is absent is skipped with that command); every 10th frame is
held out and the meshes are rendered from those views. --frames takes the first N frames (a block of the
sequence). --mlp adds the hash-grid MLP fitted from scratch (experiment redkitchen_depth, meshed where frames
observed a surface: `neuralsurf.observations.observed`; minutes). --maps writes each method's per-pixel error maps
of the held-out views as PNGs (measured | rendered | signed error: red where the mesh lies behind the reading,
blue where it stands in front, black where it shows nothing) and prints where the error comes from (shares of
the mean by signed error).
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
import torch._dynamo
from bench_bunny import CONFIGS
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import neuralsurf as ns
from neuralsurf.evaluation.distances import held_out_error_image
from neuralsurf.evaluation.methods import extract_scene_mesh, tsdf
from neuralsurf.evaluation.runner import peak_memory_mb, reset_peak_memory
from neuralsurf.geometry import render_depth
from neuralsurf.scenes.recipes import SceneUnavailable

SCENES = ("redkitchen", "tum_fr1_desk")
"""The real sequences: 7-Scenes redkitchen and TUM RGB-D fr1/desk (`python -m neuralsurf data fetch <name>`)."""

BINS = (-np.inf, -0.5, -0.05, -0.02, 0.02, 0.05, 0.5, np.inf)
"""Signed error bins (rendered - measured, metres) of the error breakdown."""


def run(label: str, function, *args, **kwargs):
    """(value, wall seconds, CPU seconds of this process, peak RSS MiB) of function(*args, **kwargs)."""
    reset_peak_memory()
    wall, cpu = time.perf_counter(), time.process_time()
    value = function(*args, **kwargs)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"  {label:<44} {wall:8.1f} s wall, {cpu:8.1f} s CPU", flush=True)
    return value, wall, cpu, peak_memory_mb()[0]


def error_breakdown(rendered: torch.Tensor, measured: torch.Tensor) -> str:
    """Where the held-out mean error comes from: per signed-error bin, its share of the seen pixels and
    its part of the mean |error| (metres)."""
    seen = (measured > 0) & (rendered > 0)
    error = (rendered - measured)[seen].double().numpy()
    parts = []
    for low, high in itertools.pairwise(BINS):
        inside = (error >= low) & (error < high)
        parts.append(f"[{low:g}, {high:g}) m: {inside.mean():.3f} of pixels, {np.abs(error[inside]).sum() / len(error):.4f} m")
    return "; ".join(parts)


def mlp_fit(cfg, scene):
    """The hash-grid MLP of `cfg` (experiment redkitchen_depth) fitted to the scene's rays from scratch, meshed
    where the frames observed a surface."""
    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    trainer.update(progress=False, image_every=0, mesh_every=0)
    torch.manual_seed(0)
    model = instantiate(cfg.model, _convert_="all")
    observation = instantiate(cfg.observation.rays, _convert_="all")(scene)
    result = ns.fit(model, observation, optimizer=instantiate(cfg.optimizer), device="cpu", **trainer)
    return extract_scene_mesh(result.field, scene, OmegaConf.to_container(cfg.extract, resolve=True))


def bench_scene(cfg, name: str, mlp, maps: Path | None) -> None:
    """Fit and score every method on scene `name` of `cfg`, printing the table and the error breakdown."""
    try:
        scene = instantiate(cfg.scene[name], _partial_=True)()
    except SceneUnavailable as error:
        print(f"\n{name}: skipped: {error}")
        return
    print(f"\n{name}: {scene.description}")
    method = OmegaConf.to_container(cfg.method.neural_voxels, resolve=True)
    voxels = instantiate(cfg.method.neural_voxels, _partial_=True, _convert_="all")
    print(f"neural voxels: 1/{1 / method['voxel_fraction']:.0f} of the box, rays of every {method['pixel_stride']}th "
          f"pixel, {method['iterations']} conjugate-gradient steps")
    rows = {"neural (voxels)": run("voxel fusion + solve + extraction", voxels, scene),
            "TSDF": run("TSDF fusion, 1/256 voxels", tsdf, scene, device="cpu")}
    fine = {"voxel_fraction": method["voxel_fraction"], "margin_fraction": method["margin_fraction"]}
    rows["TSDF fine"] = run(f"TSDF fusion, the voxels' start (1/{1 / fine['voxel_fraction']:.0f})", tsdf, scene,
                            device="cpu", **fine)
    if mlp is not None:
        rows["neural (MLP)"] = run("MLP fit + observed extraction", mlp_fit, mlp, scene)
    held = scene.held_out
    print(f"\n{'':<16} {'wall s':>8} {'CPU s':>8} {'peak MiB':>9} {'mean cm':>8} {'median mm':>10} {'compl.':>7}")
    for row, (mesh, wall, cpu, memory) in rows.items():
        metrics = ns.metrics.depth_metrics(mesh, held)
        print(f"{row:<16} {wall:8.1f} {cpu:8.1f} {memory:9.0f} {100 * metrics['depth_error_mean']:8.2f} "
              f"{1000 * metrics['depth_error_median']:10.2f} {metrics['depth_completeness']:7.3f}")
    (_, neural_wall, neural_cpu, _), (_, tsdf_wall, tsdf_cpu, _) = list(rows.values())[:2]
    print(f"time ratio neural / TSDF: {neural_wall / tsdf_wall:.1f}x wall, {neural_cpu / tsdf_cpu:.1f}x CPU")
    for row, (mesh, *_) in rows.items():
        rendered, _ = render_depth(mesh, held.K.cpu(), held.cam_to_world.cpu(), held.width, held.height)
        print(f"{row} held-out error by sign: {error_breakdown(rendered, held.depth.cpu())}")
        if maps is not None:
            maps.mkdir(parents=True, exist_ok=True)
            path = maps / f"{name}_{row.replace(' (', '_').rstrip(')').lower()}_held_out_error.png"
            held_out_error_image(rendered.numpy(), held.depth.cpu().numpy()).save(path)
            print(f"  error maps: {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames of each (default: all)")
    parser.add_argument("--mlp", action="store_true", help="also the MLP fitted from scratch (experiment redkitchen_depth)")
    parser.add_argument("--maps", type=Path, default=None, help="folder for the held-out error maps (PNG)")
    args = parser.parse_args()
    names = args.scenes.split(",")
    if unknown := set(names) - set(SCENES):
        parser.error(f"unknown scene {min(unknown)!r}: choose from {', '.join(SCENES)}")

    frames = [f"+scene.{name}.max_frames={args.frames}" for name in names] if args.frames else []
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=real", "device=cpu", *frames])
        mlp = compose(config_name="train", overrides=["experiment=redkitchen_depth"] +
                      ([f"data.max_frames={args.frames}"] if args.frames else [])) if args.mlp else None
    print(f"machine: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
          f"torch {torch.__version__}, CPU; load average {os.getloadavg()[0]:.1f}")
    for name in names:
        bench_scene(cfg, name, mlp, args.maps)


if __name__ == "__main__":
    main()
