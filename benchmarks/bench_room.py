"""Rooms from depth frames, in one run: the library's room fit (`neuralsurf.rooms.fit_room`, what
`train.py experiment=room` runs: TSDF fusion at 1 cm fitted to the rays in one least-squares solve), the project's TSDF
fusion at the same voxel and Open3D's VoxelBlockGrid at the same voxel (the reference), side by side: time, peak
memory and the held-out depth scores (mean, mean over the pixels every row shows, median, completeness, the share
of readings explained within 1 cm, F-score at 1 cm, the part of the mean from surfaces in front of the reading).
One setting for both rooms: the defaults of `RoomSettings`, chosen on redkitchen and checked on livingroom1.

    python benchmarks/bench_room.py [--scenes redkitchen,livingroom1] [--frames 50] [--voxel 0.01] [--colors]
                                    [--mlp] [--maps DIR] [--scaling [--plot PNG]]

The sequences are 7-Scenes redkitchen (every 10th frame of the first 1,000), Augmented ICL-NUIM livingroom1
(Redwood layout, 211 frames) and TUM RGB-D fr1/desk, read from $NEURALSURF_DATA or the fetch cache (one that is
absent is skipped with the command that fetches it); every 10th frame is held out and the meshes are rendered from
those views. --frames takes the first N frames (a block). --voxel sets the voxel of all three rows (metres).
--colors fits with the colour images loaded and the mesh coloured, as train.py does. --mlp adds the hash-grid MLP
fitted from scratch (experiment redkitchen_depth; minutes). --maps writes each row's held-out error maps (PNG:
measured | rendered | signed error, red where the mesh lies behind the reading, blue where it stands in front).
--scaling times the room fit alone over 50, 100, 200 and all frames and over voxels of 2, 1 and 0.7 cm
(--plot: the curves as a PNG).
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from bench_bunny import CONFIGS
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import neuralsurf as ns
from neuralsurf.cameras import render_depth
from neuralsurf.evaluation.distances import held_out_error_image
from neuralsurf.evaluation.methods import tsdf
from neuralsurf.evaluation.rooms import open3d_tsdf
from neuralsurf.evaluation.runner import peak_memory_mb, reset_peak_memory
from neuralsurf.metrics import common_pixel_errors, depth_metrics, held_out_errors
from neuralsurf.rooms import RoomSettings, fit_room
from neuralsurf.scenes import extract_scene_mesh
from neuralsurf.scenes.recipes import SceneUnavailable

SCENES = ("redkitchen", "livingroom1", "tum_fr1_desk")
"""The real sequences (`python -m neuralsurf data fetch <name>` for those not in the shared data)."""

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


def error_breakdown(errors: torch.Tensor) -> str:
    """Where the held-out mean error comes from: per signed-error bin, its share of the seen pixels and its part
    of the mean |error| (metres)."""
    error = errors[torch.isfinite(errors)].double().numpy()
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


def load_scene(cfg, name: str, colors: bool):
    """Scene `name` of the evaluate config `cfg` (None, with the reason printed, when its data are absent)."""
    try:
        return instantiate(cfg.scene[name], _partial_=True)(colors=colors)
    except SceneUnavailable as error:
        print(f"\n{name}: skipped: {error}")
        return None


def bench_scene(cfg, name: str, settings: RoomSettings, colors: bool, mlp, maps: Path | None) -> None:
    """Fit and score every row on scene `name` of `cfg`, printing the table and the error breakdown."""
    scene = load_scene(cfg, name, colors)
    if scene is None:
        return
    voxel = settings.voxel
    print(f"\n{name}: {scene.description}")
    print(f"room fit: {100 * voxel:g} cm voxels, {100 * settings.truncation:g} cm truncation, rays of every "
          f"{settings.pixel_stride}th pixel, {settings.iterations} conjugate-gradient steps")
    rows = {"room fit": run("fusion + solve + mesh" + (" + colours" if colors else ""),
                            lambda: fit_room(scene.frames, settings).mesh),
            "TSDF": run(f"TSDF fusion, {100 * voxel:g} cm", tsdf, scene, room_voxel=voxel, device="cpu"),
            "Open3D VBG": run(f"Open3D VoxelBlockGrid, {100 * voxel:g} cm", open3d_tsdf, scene, voxel=voxel,
                              truncation_voxels=settings.truncation / voxel, device="cpu")}
    if mlp is not None:
        rows["neural (MLP)"] = run("MLP fit + observed extraction", mlp_fit, mlp, scene)
    held = scene.held_out
    errors = {row: held_out_errors(mesh, held) for row, (mesh, *_) in rows.items()}
    common = common_pixel_errors(errors)
    print(f"\n{'':<13} {'wall s':>7} {'CPU s':>7} {'peak MiB':>9} {'mean cm':>8} {'common cm':>10} {'median mm':>10} "
          f"{'compl.':>7} {'in 1cm':>7} {'F@1cm':>6} {'front cm':>9}")
    for row, (mesh, wall, cpu, memory) in rows.items():
        m = depth_metrics(mesh, held, errors=errors[row])
        print(f"{row:<13} {wall:7.1f} {cpu:7.1f} {memory:9.0f} {100 * m['depth_error_mean']:8.2f} "
              f"{100 * common[row]:10.2f} {1000 * m['depth_error_median']:10.2f} {m['depth_completeness']:7.3f} "
              f"{m['depth_recall_1cm']:7.3f} {m['depth_fscore_1cm']:6.3f} {100 * m['depth_error_front']:9.2f}")
    (_, fit_wall, *_), (_, tsdf_wall, *_), (_, open3d_wall, *_) = list(rows.values())[:3]
    print(f"time ratio room fit / TSDF: {fit_wall / tsdf_wall:.1f}x, / Open3D: {fit_wall / open3d_wall:.1f}x")
    for row, (mesh, *_) in rows.items():
        print(f"{row} held-out error by sign: {error_breakdown(errors[row])}")
        if maps is not None:
            rendered, _ = render_depth(mesh, held.K.cpu(), held.cam_to_world.cpu(), held.width, held.height)
            maps.mkdir(parents=True, exist_ok=True)
            path = maps / f"{name}_{row.replace(' ', '_').replace('(', '').replace(')', '').lower()}_held_out_error.png"
            held_out_error_image(rendered.numpy(), held.depth.cpu().numpy()).save(path)
            print(f"  error maps: {path}")


def scaling(cfg, name: str, settings: RoomSettings) -> list[tuple[int, float, float, float, int]]:
    """Time and peak memory of the room fit alone (no colours) over blocks of 50, 100, 200 and all frames at
    the default voxel, and over voxels of 2, 1 and 0.7 cm on all frames: (frames, voxel, wall s, peak MiB,
    observed voxels) per case."""
    scene = load_scene(cfg, name, False)
    if scene is None:
        return []
    frames = scene.frames
    print(f"\n{name} scaling ({len(frames)} fitted frames): frames, voxel cm, wall s, CPU s, peak RSS MiB, "
          f"observed voxels")
    cases = [(n, settings.voxel) for n in (50, 100, 200) if n < len(frames)] + [(len(frames), settings.voxel)]
    cases += [(len(frames), v) for v in (0.02, 0.007)]
    measured = []
    for n, voxel in cases:
        chosen = replace(settings, voxel=voxel, truncation=settings.truncation * voxel / settings.voxel)
        fitted, wall, cpu, memory = run(f"{n} frames, {100 * voxel:g} cm", fit_room, frames[:n], chosen)
        print(f"  {n:5d} {100 * voxel:6.2g} {wall:7.1f} {cpu:7.1f} {memory:8.0f} {len(fitted.field.values):10d}")
        measured.append((n, voxel, wall, memory, len(fitted.field.values)))
    return measured


def scaling_plot(measured: dict[str, list], path: Path) -> None:
    """Two log-log scatter plots side by side, a colour per room: wall time against the observed voxels, and
    peak memory against the frames fitted; each point labelled with its frames and voxel."""
    from PIL import Image

    from neuralsurf.evaluation.render import scatter_plot

    def label(n: int, voxel: float) -> str:
        return f"{n} fr, {100 * voxel:g} cm"

    time_plot = scatter_plot("room fit: wall time against observed voxels", "observed voxels", "wall s",
                             [(v, wall, room, label(n, voxel)) for room, cases in measured.items()
                              for n, voxel, wall, _, v in cases])
    memory_plot = scatter_plot("room fit: peak memory against frames", "frames fitted", "peak RSS MiB",
                               [(n, memory, room, label(n, voxel)) for room, cases in measured.items()
                                for n, voxel, _, memory, _ in cases])
    canvas = Image.new("RGB", (time_plot.width + memory_plot.width, max(time_plot.height, memory_plot.height)),
                       (255, 255, 255))
    canvas.paste(time_plot, (0, 0))
    canvas.paste(memory_plot, (time_plot.width, 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path)
    print(f"scaling plot: {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="redkitchen,livingroom1", help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames of each (default: all)")
    parser.add_argument("--voxel", type=float, default=RoomSettings.voxel, help="metres, for all three rows")
    parser.add_argument("--colors", action="store_true", help="load the colour images and colour the room fit")
    parser.add_argument("--mlp", action="store_true", help="also the MLP fitted from scratch (experiment redkitchen_depth)")
    parser.add_argument("--maps", type=Path, default=None, help="folder for the held-out error maps (PNG)")
    parser.add_argument("--scaling", action="store_true", help="time the room fit over frame counts and voxels")
    parser.add_argument("--plot", type=Path, default=None, help="with --scaling: write the curves as a PNG")
    args = parser.parse_args()
    names = args.scenes.split(",")
    if unknown := set(names) - set(SCENES):
        parser.error(f"unknown scene {min(unknown)!r}: choose from {', '.join(SCENES)}")
    defaults = RoomSettings()
    settings = replace(defaults, voxel=args.voxel, truncation=defaults.truncation * args.voxel / defaults.voxel)

    frames = [f"+scene.{name}.max_frames={args.frames}" for name in names] if args.frames else []
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=real", "device=cpu", *frames])
        mlp = compose(config_name="train", overrides=["experiment=redkitchen_depth"] +
                      ([f"data.max_frames={args.frames}"] if args.frames else [])) if args.mlp else None
    print(f"machine: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
          f"torch {torch.__version__}, CPU; load average {os.getloadavg()[0]:.1f}")
    measured = {}
    for name in names:
        if args.scaling:
            measured[name] = scaling(cfg, name, settings)
        else:
            bench_scene(cfg, name, settings, args.colors, mlp, args.maps)
    if args.scaling and args.plot is not None:
        scaling_plot(measured, args.plot)


if __name__ == "__main__":
    main()
