"""Point clouds against screened Poisson: train.py's point fit (its default, experiment=bunny_sdf: a voxel SDF solved
from the points, refined by a hash-grid MLP until held-out points stop improving, extracted near the surface only)
and Open3D's screened Poisson on the same points and normals, timed in one run.

    python benchmarks/bench_points.py bunny    # the demo's 100k points against Poisson depth 10 and 9
    python benchmarks/bench_points.py scans    # train.py data=file on the Stanford scans merged ($NEURALSURF_DATA)
    python benchmarks/bench_points.py rounds [--misregistered]  # the move's every count of rounds against Poisson
    python benchmarks/bench_points.py misregistered  # synthetic scans of the bunny out of register
    python benchmarks/bench_points.py faults   # the demo's points as files come: far away, unoriented, strays, twice
    python benchmarks/bench_points.py curves [--sizes 10000 100000 1000000 5000000] [--resolutions 128 256 512 1024]
                                             [--tables 15 17 19 21] [--widths 32 64 128]
                                             [--plot docs/images/points_scaling.png]

`bunny` and `scans` print wall and CPU seconds of fit + extraction and of Poisson, and their accuracy: exact
Chamfer-L1 and normal consistency against the bunny mesh; for the scans the mean distance from the scan points to
the mesh and from the mesh (100k surface samples) to the scan points, as fractions of the scan's bounding-box
diagonal, and the metrics against Stanford's zippered reconstruction; then both again on the scans less `UNSEEN` of
their points, the distance from the points given and from those not given to each mesh. `rounds` scores the same way
the fit of those points moved with each count of the move's smoothing rounds (`snapping.ROUNDS`), not only the count
its held-out points choose, and Poisson depth 9 (`--misregistered`: on the synthetic scans below, the true surface
scored too). `misregistered` fits scans whose true surface is known (`misregistered_scans`) with and without the move
onto the points (`extract.onto_points`), and scores them, Poisson and the true surface against the truth and by their
distances to the scan. `faults` fits (`train.py data=file`) and Poisson depth 9 the demo's 100k points written to a
file as it is and as real files come (`faulty_clouds`), scored against the bunny where it lies. `curves` runs
every case in a child process (its peak resident memory is the case's own): the fast fit of 10k to 5M points
sampled from the bunny with their normals (and the merged scans when present), and the extraction of the 100k fit
at each resolution, against Poisson depth 9 on the same points, and the fit of `MODEL_POINTS` with each hash-table
size (log2 rows a level) and each MLP width; fits and Poisson are scored by exact Chamfer-L1 against the bunny (the
scans: the zippered mesh). Threads: as the environment sets them (OMP_NUM_THREADS; else one
per core), the same for Poisson; `bunny`, `scans` and `misregistered` load the libraries before the clocks
(`load_libraries`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import neuralsurf as ns
from neuralsurf import snapping
from neuralsurf.baselines.registration.estimation import axis_angle_to_matrix
from neuralsurf.cameras import depth_to_cloud
from neuralsurf.cli import build_observations, without_feeds
from neuralsurf.geometry import (
    cloud_from_mesh,
    cloud_spacing,
    knn,
    point_to_mesh_distance,
    sample_mesh_surface,
)
from neuralsurf.sampling import held_out_split
from neuralsurf.scenes import Scene
from neuralsurf.scenes.recipes import extract_scene_mesh
from neuralsurf.scenes.scanner import scan_depth

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
OURS = "train.py (fit + extraction)"


def configured(overrides: list[str]):
    """train.py's config with these overrides (its default experiment, bunny_sdf, unless overridden)."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return without_feeds(compose(config_name="train", overrides=overrides))


def clock(function, *args, **kwargs):
    """(value, wall seconds, CPU seconds of this process) of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    value = function(*args, **kwargs)
    return value, time.perf_counter() - wall, time.process_time() - cpu


def ours(cfg, scene: Scene, extract: dict | None = None):
    """train.py's fit and extraction of `scene` under `cfg`: (mesh, fit result, wall s, CPU s)."""
    trainer = {**OmegaConf.to_container(cfg.trainer, resolve=True), "progress": False, "image_every": 0}
    observations = build_observations(cfg, scene)
    torch.manual_seed(cfg.seed)
    model = instantiate(cfg.model, _convert_="all")
    result, fit_wall, fit_cpu = clock(ns.fit, model, observations, optimizer=instantiate(cfg.optimizer), device="cpu",
                                      seed=cfg.seed, **trainer)
    options = {**OmegaConf.to_container(cfg.extract, resolve=True), "progress": False, **(extract or {})}
    mesh, extract_wall, extract_cpu = clock(extract_scene_mesh, result.field, scene, options, cfg.seed)
    return mesh, result, fit_wall + extract_wall, fit_cpu + extract_cpu


def poisson(cloud, depth: int):
    """(mesh, wall s, CPU s) of Open3D's screened Poisson at `depth` on as many threads as the fit."""
    return clock(ns.baselines.reconstruct_poisson, cloud, depth=depth, n_threads=torch.get_num_threads())


def load_libraries() -> None:
    """Load what each side loads on its first call, before any clock starts: Open3D (Poisson, the move's nearest
    faces; 0.65 s on the Xeon) and torch._dynamo (torch.optim's first optimiser; 1.0 s)."""
    import open3d  # noqa: F401
    import torch._dynamo  # noqa: F401


def line(name: str, wall: float, cpu: float, metrics: dict) -> None:
    figures = ", ".join(f"{key} {value:.4g}" for key, value in metrics.items())
    print(f"{name:<34} {wall:7.1f} s wall {cpu:7.1f} s CPU   {figures}", flush=True)


def scored_lines(runs: dict, truth) -> None:
    """A line for each of `runs` (name -> (mesh, wall s, CPU s, further figures)): its exact Chamfer-L1 and normal
    consistency against the `truth` mesh, whether it is watertight, its faces and the further figures."""
    for name, (mesh, wall, cpu, extra) in runs.items():
        metrics = ns.metrics.evaluate_mesh(mesh, truth)
        line(name, wall, cpu, {"chamfer_l1_exact": metrics["chamfer_l1_exact"],
                               "normal_consistency": metrics["normal_consistency"],
                               "watertight": ns.metrics.watertight(mesh, metrics), "faces": len(mesh.faces), **extra})


def bunny(args) -> None:
    gt = ns.scenes.bunny()
    cloud = cloud_from_mesh(gt, n=100_000, noise=0.0, seed=0)
    scene = Scene("bunny", cloud, gt)
    runs = {}
    for depth in (10, 9):
        mesh, wall, cpu = poisson(cloud, depth)
        runs[f"poisson depth {depth}"] = (mesh, wall, cpu, {})
    mesh, result, wall, cpu = ours(configured([]), scene)
    runs[OURS] = (mesh, wall, cpu, {"steps": result.steps})
    scored_lines(runs, gt)
    for depth in (10, 9):
        a, b = runs[OURS], runs[f"poisson depth {depth}"]
        print(f"time {OURS} / Poisson depth {depth}: {a[1] / b[1]:.2f}x wall, {a[2] / b[2]:.2f}x CPU")


def box_diagonal(cloud) -> float:
    """The length of the diagonal of the points' bounding box."""
    return float((cloud.points.max(0).values - cloud.points.min(0).values).double().norm())


def to_mesh(cloud, mesh):
    """Float64[Tensor, "n"]: each of `cloud`'s points' distance to `mesh`, a fraction of its bounding-box diagonal."""
    return point_to_mesh_distance(cloud.points.float(), mesh).double() / box_diagonal(cloud)


def to_points(mesh, cloud, n: int = 100_000) -> float:
    """The mean distance from `n` samples of `mesh`'s surface to `cloud`'s nearest point, a fraction of its
    bounding-box diagonal."""
    samples, _ = sample_mesh_surface(mesh, n, torch.Generator().manual_seed(0))
    return float(knn(samples.double(), cloud.points.double(), 1)[0][:, 0].mean()) / box_diagonal(cloud)


def scan_distances(mesh, cloud) -> dict[str, float]:
    """Mean scan -> mesh and mesh -> scan distances, fractions of the scan's bounding-box diagonal."""
    return {"scan_to_mesh": float(to_mesh(cloud, mesh).mean()), "mesh_to_scan": to_points(mesh, cloud)}


UNSEEN = 0.05
"""The share of the scans' points kept from both methods, to score them on points they were not given."""


def stanford_scene() -> Scene:
    """The Stanford range scans merged, with the zippered reconstruction ($NEURALSURF_DATA, else the fetch cache)."""
    from neuralsurf.scenes.recipes import stanford_scans

    return stanford_scans(root=os.environ.get("NEURALSURF_DATA"))


def unseen_split(cloud) -> tuple[torch.Tensor, torch.Tensor]:
    """(not given, given) Long[Tensor] indices: `UNSEEN` of `cloud`'s points (seed 1; the fit then holds out its own
    share of the rest, seed 0)."""
    return held_out_split(len(cloud), UNSEEN, seed=1)


def file_runs(cloud) -> dict:
    """Poisson depth 9 and `train.py data=file` on `cloud` written to a PLY file: name -> (mesh, wall s, CPU s,
    further figures)."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scan.ply"
        ns.io.write_point_cloud(path, cloud)
        cfg = configured(["data=file", f"data.path={path}"])
        file_scene = instantiate(cfg.data)
        runs = {"poisson depth 9": (*poisson(file_scene.cloud, 9), {})}
        mesh, result, wall, cpu = ours(cfg, file_scene)
        runs[OURS] = (mesh, wall, cpu, {"steps": result.steps})
    return runs


def scans(args) -> None:
    scene = stanford_scene()
    print(f"{len(scene.cloud)} points, normals {scene.cloud.has_normals}")
    runs = file_runs(scene.cloud)
    for name, (mesh, wall, cpu, extra) in runs.items():
        against = ns.metrics.evaluate_mesh(mesh, scene.ground_truth)
        line(name, wall, cpu, {**scan_distances(mesh, scene.cloud), "chamfer_l1_exact_zippered":
                               against["chamfer_l1_exact"], "nc_zippered": against["normal_consistency"], **extra})
    a, b = runs[OURS], runs["poisson depth 9"]
    print(f"time {OURS} / Poisson depth 9: {a[1] / b[1]:.2f}x wall, {a[2] / b[2]:.2f}x CPU")
    unseen, given = unseen_split(scene.cloud)
    print(f"{UNSEEN:.0%} of the points kept from both: scan -> mesh on the points given and on those not given")
    for name, (mesh, wall, cpu, _) in file_runs(scene.cloud.select(given)).items():
        distance = to_mesh(scene.cloud, mesh)
        line(name, wall, cpu, {"given": distance[given].mean().item(), "not_given": distance[unseen].mean().item()})


def rounds(args) -> None:
    scene = misregistered_scans() if args.misregistered else stanford_scene()
    unseen, given = unseen_split(scene.cloud)
    cloud = scene.cloud.select(given)
    cfg = configured(["data=file", "data.path=unused", "extract.onto_points=null"])
    mesh, _, _, _ = ours(cfg, Scene("given", cloud, None))
    _, kept = held_out_split(len(cloud), cfg.observation.points.held_out, cfg.seed)  # the fit's points, as the move's
    points, normals = cloud.points.float(), torch.nn.functional.normalize(cloud.normals.float(), dim=-1)
    spacing = cloud_spacing(points[kept])
    fine = snapping.subdivided(ns.Mesh(mesh.vertices.float(), mesh.faces))
    meshes = {f"moved, {count} rounds": ns.Mesh(vertices, fine.faces)
              for count, vertices in snapping.smoothed_moves(fine, points[kept], normals[kept], spacing)}
    meshes["poisson depth 9"] = poisson(cloud, 9)[0]
    if args.misregistered:
        meshes["the true surface"] = scene.ground_truth
    reference = "the true surface" if args.misregistered else "the zippered mesh"
    print(f"{UNSEEN:.0%} of the scans' points kept from both: scan -> mesh on the points given and on those not "
          f"given, mesh -> the points given; Chamfer-L1 to {reference}")
    for name, moved in meshes.items():
        distance = to_mesh(scene.cloud, moved)
        to_given = to_points(moved, cloud)
        chamfer = ns.metrics.evaluate_mesh(moved, scene.ground_truth)["chamfer_l1_exact"]
        print(f"{name:20} given {distance[given].mean():.4e}  not given {distance[unseen].mean():.4e}  "
              f"mesh -> given {to_given:.4e}  Chamfer-L1 {chamfer:.4e}", flush=True)


def misregistered_scans(views: int = 10, noise: float = 2e-4, shift: float = 2e-4, degrees: float = 0.02,
                        seed: int = 0) -> Scene:
    """The bunny (diagonal 1) seen by the depth scanner from `views` views of 400 x 300 pixels with Gaussian depth
    noise `noise`, each view's points (with their normals) then turned by `degrees` about a random axis through the
    bunny's centre and shifted by `shift` in a random direction: range scans out of register, the true surface known."""
    bunny = ns.scenes.bunny()
    frames = scan_depth(bunny, n_views=views, width=400, height=300, noise="gaussian", sigma=noise, seed=seed)
    generator = torch.Generator().manual_seed(seed + 1)
    center = bunny.vertices.double().mean(0)
    points, normals = [], []
    for i in range(len(frames)):
        view = depth_to_cloud(frames[i : i + 1], with_normals=True)
        axis, offset = torch.randn(2, 3, generator=generator, dtype=torch.float64)
        turn = torch.from_numpy(axis_angle_to_matrix((axis / axis.norm() * math.radians(degrees)).numpy()))
        points.append((view.points.double() - center) @ turn.T + center + shift * offset / offset.norm())
        normals.append(view.normals.double() @ turn.T)
    return Scene("misregistered", ns.PointCloud(torch.cat(points), torch.cat(normals)), bunny)


def misregistered(args) -> None:
    scene = misregistered_scans()
    print(f"{len(scene.cloud)} points")
    runs = {"poisson depth 9": (*poisson(scene.cloud, 9), {})}
    for name, overrides in ((OURS, []), (f"{OURS}, not moved", ["extract.onto_points=null"])):
        mesh, result, wall, cpu = ours(configured(overrides), scene)
        runs[name] = (mesh, wall, cpu, {"steps": result.steps})
    runs["the true surface"] = (scene.ground_truth, math.nan, math.nan, {})
    scored_lines({name: (mesh, wall, cpu, {**scan_distances(mesh, scene.cloud), **extra})
                  for name, (mesh, wall, cpu, extra) in runs.items()}, scene.ground_truth)


FAR = torch.tensor([412_345.0, 5_012_345.0, 100.0], dtype=torch.float64)
"""A georeferenced origin (UTM metres), where float32 rounds coordinates by up to 0.25."""


def faulty_clouds(cloud) -> dict:
    """Name -> (cloud, offset of its truth): the bunny's `cloud` as files come from the field: as it is, far from the
    origin (`FAR`), with half its normals flipped (saved unoriented), with 30 stray points in a box three times its
    size, and saved twice."""
    g = torch.Generator().manual_seed(3)
    points, normals = cloud.points.double(), cloud.normals.double()
    flips = torch.where(torch.rand(len(points), 1, generator=g) < 0.5, -1.0, 1.0).double()
    low, high = points.min(0).values, points.max(0).values
    stray = (low + high) / 2 + (torch.rand(30, 3, generator=g, dtype=torch.float64) - 0.5) * 3 * (high - low).max()
    stray_normals = torch.nn.functional.normalize(torch.randn(30, 3, generator=g, dtype=torch.float64), dim=1)
    origin = torch.zeros(3, dtype=torch.float64)
    return {"as it is": (ns.PointCloud(points, normals), origin),
            "far from the origin": (ns.PointCloud(points + FAR, normals), FAR),
            "normals unoriented": (ns.PointCloud(points, flips * normals), origin),
            "30 stray points": (ns.PointCloud(torch.cat([points, stray]), torch.cat([normals, stray_normals])), origin),
            "saved twice": (ns.PointCloud(points.repeat(2, 1), normals.repeat(2, 1)), origin)}


def faults(args) -> None:
    bunny = ns.scenes.bunny()
    for case, (cloud, offset) in faulty_clouds(cloud_from_mesh(bunny, n=100_000, noise=0.0, seed=0)).items():
        truth = ns.Mesh(bunny.vertices.double() + offset, bunny.faces)
        print(f"{case}: {len(cloud)} points", flush=True)
        scored_lines(file_runs(cloud), truth)


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def sampled_cloud(n: int):
    """(n points of the bunny's surface with their normals, the bunny); for n = 0 (the scans merged, Stanford's
    zippered reconstruction)."""
    if n == 0:
        scene = stanford_scene()
        return scene.cloud, scene.ground_truth
    bunny = ns.scenes.bunny()
    points, normals = sample_mesh_surface(bunny, n, torch.Generator().manual_seed(0))
    return ns.PointCloud(points.float(), normals.float()), bunny


MODEL_POINTS = 10_000
"""`curves` fits its model sizes to this many points, where the MLP refines the start longest."""


def one_case(kind: str, n: int, resolution: int, overrides: list[str] | None = None) -> dict:
    """A child's case: the fit (and default extraction) of n points (`model`: with train.py `overrides` of the model),
    Poisson depth 9 on them (both scored after the timing and the peak memory are read), or the extraction of the
    n-point fit at `resolution` (timed alone)."""
    cloud, truth = sampled_cloud(n)
    before = peak_rss_mib()

    def exact_chamfer(mesh) -> float:
        return ns.metrics.evaluate_mesh(mesh, truth)["chamfer_l1_exact"]

    if kind == "poisson":
        mesh, wall, cpu = poisson(cloud, 9)
        peak = peak_rss_mib()
        return {"wall": wall, "cpu": cpu, "peak_mib": peak, "input_mib": before, "chamfer": exact_chamfer(mesh)}
    cfg = configured(["data=file", "data.path=unused", *(overrides or [])])
    scene = Scene("cloud", cloud, None)
    if kind in ("fit", "model"):
        mesh, result, wall, cpu = ours(cfg, scene)
        peak = peak_rss_mib()
        trained = sum(p.numel() for p in result.field.parameters() if p.requires_grad)
        return {"wall": wall, "cpu": cpu, "peak_mib": peak, "input_mib": before, "steps": result.steps,
                "parameters": trained, "faces": len(mesh.faces), "chamfer": exact_chamfer(mesh)}
    _, result, _, _ = ours(cfg, scene)
    Path("/proc/self/clear_refs").write_text("5")  # the extraction's own peak from here (Linux)
    mesh, wall, cpu = clock(ns.extract_mesh, result.field, resolution=resolution, sparse=True, progress=False,
                            chunk_size=cfg.extract.chunk_size)
    status = Path("/proc/self/status").read_text().splitlines()
    peak = next(int(s.split()[1]) / 1024 for s in status if s.startswith("VmHWM"))
    return {"wall": wall, "cpu": cpu, "peak_mib": peak, "faces": len(mesh.faces)}


def curves(args) -> None:
    cases = [("fit", n, 0, []) for n in args.sizes] + [("poisson", n, 0, []) for n in args.sizes]
    if os.environ.get("NEURALSURF_DATA"):
        cases += [("fit", 0, 0, []), ("poisson", 0, 0, [])]
    cases += [("extract", 100_000, r, []) for r in args.resolutions]
    cases += [("model", MODEL_POINTS, 0, [f"model.encoding.log2_table_size={t}"]) for t in args.tables]
    cases += [("model", MODEL_POINTS, 0, [f"model.width={w}"]) for w in args.widths]
    measured = []
    print("case, points (0: the scans merged), resolution, wall s, CPU s, peak RSS MiB, details", flush=True)
    for kind, n, resolution, overrides in cases:
        child = subprocess.run([sys.executable, __file__, "one", kind, str(n), str(resolution), *overrides],
                               capture_output=True, text=True, check=False)
        if child.returncode:
            print(f"{kind} {n} {resolution} {overrides}: failed\n{child.stderr[-2000:]}", flush=True)
            continue
        result = {**json.loads(child.stdout.strip().splitlines()[-1]), **({"model": overrides[0]} if overrides else {})}
        measured.append((kind, n, resolution, result))
        print(f"{kind:8} {n:8d} {resolution:5d} {result['wall']:8.1f} {result['cpu']:8.1f} {result['peak_mib']:8.0f}  "
              f"{json.dumps({k: v for k, v in result.items() if k not in ('wall', 'cpu', 'peak_mib')})}", flush=True)
    if args.plot is not None:
        plot(measured, args.plot)


def plot(measured: list, path: Path) -> None:
    """Wall time, peak memory and accuracy against points (fit, Poisson), time and memory against resolution
    (extraction), and time, memory and accuracy against the model's trained parameters (hash table, MLP width),
    log-log, four panels a row."""
    from PIL import Image

    from neuralsurf.evaluation.render import scatter_plot

    series = {"fit": "train.py", "poisson": "Poisson depth 9"}

    def against_points(key: str) -> list:
        return [(n, result[key], series[kind], f"{n // 1000}k") for kind, n, _, result in measured
                if kind in series and n]

    extraction = [(res, result[key], name, f"{res}") for kind, _, res, result in measured if kind == "extract"
                  for key, name in (("wall", "wall s"), ("peak_mib", "peak RSS MiB"))]

    def against_parameters(key: str) -> list:  # the hash table's size or the MLP's width changed
        return [(result["parameters"], result[key], *(("hash table", "2^" + value) if "table" in setting else
                                                     ("MLP width", value)))
                for kind, _, _, result in measured if kind == "model"
                for setting, value in [result["model"].split("=")]]

    panels = [scatter_plot("time against points", "points", "wall s", against_points("wall")),
              scatter_plot("peak memory against points", "points", "peak RSS MiB", against_points("peak_mib")),
              scatter_plot("accuracy against points", "points", "exact Chamfer-L1 to the bunny",
                           against_points("chamfer")),
              scatter_plot("extraction of the 100k fit (sparse)", "cells per side", "wall s | MiB", extraction),
              scatter_plot(f"time against model size ({MODEL_POINTS // 1000}k points)", "trained parameters",
                           "wall s", against_parameters("wall")),
              scatter_plot(f"peak memory against model size ({MODEL_POINTS // 1000}k points)", "trained parameters",
                           "peak RSS MiB", against_parameters("peak_mib")),
              scatter_plot(f"accuracy against model size ({MODEL_POINTS // 1000}k points)", "trained parameters",
                           "exact Chamfer-L1 to the bunny", against_parameters("chamfer"))]
    columns = 4
    width, height = max(p.width for p in panels), max(p.height for p in panels)
    canvas = Image.new("RGB", (columns * width, -(-len(panels) // columns) * height), (255, 255, 255))
    for i, panel in enumerate(panels):
        canvas.paste(panel, (i % columns * width, i // columns * height))
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path)
    print(f"plot: {path}")


def main() -> None:
    if len(sys.argv) >= 5 and sys.argv[1] == "one":
        print(json.dumps(one_case(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5:])))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["bunny", "scans", "rounds", "misregistered", "faults", "curves"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000, 5_000_000])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512, 1024])
    parser.add_argument("--tables", type=int, nargs="+", default=[15, 17, 19, 21], help="log2 hash-table sizes")
    parser.add_argument("--widths", type=int, nargs="+", default=[32, 64, 128], help="MLP widths")
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--misregistered", action="store_true", help="rounds: on the synthetic scans (the truth known)")
    args = parser.parse_args()
    if args.what != "curves":  # each of its cases runs in a process of its own, loading what it calls
        load_libraries()
    {"bunny": bunny, "scans": scans, "rounds": rounds, "misregistered": misregistered, "faults": faults,
     "curves": curves}[args.what](args)


if __name__ == "__main__":
    main()
