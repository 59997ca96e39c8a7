"""Learned shape priors end to end on the CPU: build a procedural collection, train a DeepSDF
auto-decoder and an Occupancy Network over it, and score both on held-out test shapes.

    python benchmarks/bench_priors.py --out /tmp/shapes_bench --minutes-deepsdf 6 --minutes-onet 6

Rows (means over the test split; per-shape values in <out>/bench_priors.json):
- cloud: 3,000 noisy surface points (Gaussian, --noise) of each test shape. DeepSDF: latent fit under
  the frozen decoder (PointSamples: surface and near-surface terms + code prior). OccNet: one forward
  pass of the encoder.
- one_view: one synthetic depth view of each test shape. DeepSDF: latent fit to the depth rays
  (DepthRays: surface, band, free space + code prior). OccNet: encoder on the back-projected view.
  Poisson on the same back-projected view (normals oriented to the camera) for comparison.
Metrics from `neuralsurf.metrics.evaluate_mesh` against the cached ground-truth mesh: IoU, exact
Chamfer-L1, normal consistency, F-score at 1 %, watertightness.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from neuralsurf.errors import NeuralsurfError
from neuralsurf.extract import extract_mesh
from neuralsurf.metrics import evaluate_mesh
from neuralsurf.models import SDFMLP, AutoDecoder, CBNDecoder, LatentCodes, OccupancyNetwork, PointNetEncoder
from neuralsurf.observations import DepthRays, PointSamples
from neuralsurf.observations.collection import CollectionOccupancy, CollectionSDF
from neuralsurf.shapes import collection_records
from neuralsurf.shapes.cache import CacheRecipe, build_collection, cache_path, load_cache
from neuralsurf.shapes.completion import reconstruct_latent
from neuralsurf.structures import Mesh, Normalization, PointCloud
from neuralsurf.training import default_optimizer, fit

KEYS = ("iou", "chamfer_l1_exact", "normal_consistency", "fscore_1%", "pred_watertight")
BOUNDS = np.array([[-0.55] * 3, [0.55] * 3])


def train_for(model, observation, minutes: float, max_steps: int, lr: float, label: str):
    """Fit for about `minutes`: a short timing run sets the number of steps."""
    probe = 20
    started = time.perf_counter()
    fit(model, observation, steps=probe, normalization=Normalization(), encoding_lr=None, progress=False,
        optimizer=functools.partial(default_optimizer, lr=lr))
    per_step = (time.perf_counter() - started) / probe
    steps = int(min(max_steps, max(probe, minutes * 60 / per_step)))
    print(f"{label}: {per_step * 1000:.0f} ms/step -> {steps} steps", flush=True)
    started = time.perf_counter()
    result = fit(model, observation, steps=steps, normalization=Normalization(), encoding_lr=None, progress=False,
                 optimizer=functools.partial(default_optimizer, lr=lr), log_every=max(1, steps // 10))
    key = next(k for k in result.history if k.endswith(("/sdf", "/occupancy")))
    print(f"{label}: {steps} steps in {time.perf_counter() - started:.0f} s, {key} "
          f"{result.history[key][0]:.4f} -> {result.history[key][-1]:.4f}", flush=True)
    return result.model, steps, time.perf_counter() - started


def score(field_or_mesh, gt: Mesh, resolution: int) -> dict[str, float]:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = field_or_mesh if isinstance(field_or_mesh, Mesh) else extract_mesh(
                field_or_mesh, resolution=resolution, bounds=BOUNDS)
            metrics = evaluate_mesh(mesh, gt, n_samples=20_000)
    except NeuralsurfError as error:  # no surface: the worst score, counted
        print(f"    no mesh: {str(error)[:80]}", flush=True)
        return {"iou": 0.0, "chamfer_l1_exact": math.nan, "normal_consistency": math.nan, "fscore_1%": 0.0,
                "pred_watertight": 0.0}
    return {key: float(metrics[key]) for key in KEYS}


def one_view(gt: Mesh, seed: int, width: int, height: int, noise: float):
    from neuralsurf.geometry import backproject_depth
    from neuralsurf.scenes.scanner import look_at, scan_depth

    rng = np.random.default_rng(seed)
    azimuth, elevation = rng.uniform(0, 2 * math.pi), rng.uniform(0.2, 0.6)
    eye = 1.6 * np.array([math.cos(azimuth) * math.cos(elevation), math.sin(elevation),
                          math.sin(azimuth) * math.cos(elevation)])
    pose = look_at(eye, (0.0, 0.0, 0.0))
    frames = scan_depth(gt, cam_to_world=pose[None], width=width, height=height, fov_deg=50.0,
                        noise="gaussian" if noise > 0 else "none", sigma=noise if noise > 0 else None, seed=seed)
    points = backproject_depth(frames)[frames.depth > 0]
    return frames, points, torch.as_tensor(eye, dtype=torch.float64)


def poisson_one_view(points: torch.Tensor, eye: torch.Tensor) -> Mesh:
    from neuralsurf.baselines.poisson import reconstruct_poisson
    from neuralsurf.geometry import estimate_normals, orient_normals

    normals = orient_normals(points, estimate_normals(points, 30), 30, method="camera", camera=eye.to(points))
    return reconstruct_poisson(PointCloud(points.double(), normals.double()), depth=7)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="/tmp/neuralsurf_shapes_bench")
    parser.add_argument("--classes", default="chair,mug,lamp")
    parser.add_argument("--n-train", type=int, default=16, help="training shapes per class")
    parser.add_argument("--n-test", type=int, default=2, help="test shapes per class")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--minutes-deepsdf", type=float, default=6.0)
    parser.add_argument("--minutes-onet", type=float, default=6.0)
    parser.add_argument("--latent-dim", type=int, default=32)
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--latent-steps", type=int, default=150)
    parser.add_argument("--noise", type=float, default=0.005, help="noise of the 3,000-point clouds (unit frame)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    threads = torch.get_num_threads()
    out = Path(args.out)

    started = time.perf_counter()
    records = collection_records(tuple(args.classes.split(",")), args.n_train, 0, args.n_test, args.seed)
    recipe = CacheRecipe(n_sdf=100_000, n_occ=50_000, n_surface=20_000, mesh_resolution=128)
    counts = build_collection(out, records, recipe, workers=args.workers, progress=False)
    n_train = sum(r.split == "train" for r in records)
    print(f"collection: {len(records)} shapes ({n_train} train, {len(records) - n_train} test), {counts}, "
          f"{time.perf_counter() - started:.0f} s; torch threads {threads}", flush=True)

    decoder = SDFMLP(width=args.width, depth=6, skip_layers=(3,), latent_dim=args.latent_dim, init_radius=0.25)
    deepsdf = AutoDecoder(decoder, LatentCodes(n_train, args.latent_dim))
    deepsdf, deepsdf_steps, deepsdf_s = train_for(
        deepsdf, CollectionSDF(out, shapes_per_batch=8, samples_per_shape=1024), args.minutes_deepsdf, 20_000,
        1e-3, "deepsdf")
    onet = OccupancyNetwork(PointNetEncoder(64, 64), CBNDecoder(64, 128, blocks=4))
    onet, onet_steps, onet_s = train_for(
        onet, CollectionOccupancy(out, shapes_per_batch=8, query_points=1024, cloud_points=1000, partial=0.5),
        args.minutes_onet, 20_000, 1e-3, "occupancy_network")
    onet.eval()

    rows: dict[str, dict[str, list[float]]] = {}
    per_shape = []

    def add(row: str, name: str, metrics: dict[str, float], seconds: float) -> None:
        rows.setdefault(row, {k: [] for k in (*KEYS, "seconds")})
        for key, value in {**metrics, "seconds": seconds}.items():
            rows[row][key].append(value)
        per_shape.append({"row": row, "shape": name, **metrics, "seconds": seconds})
        print(f"  {row:28s} {name:16s} iou {metrics['iou']:.3f} chamfer_l1_exact {metrics['chamfer_l1_exact']:.4f} "
              f"({seconds:.1f} s)", flush=True)

    for record in [r for r in records if r.split == "test"]:
        arrays = load_cache(cache_path(out, record))
        gt = Mesh(torch.from_numpy(arrays["mesh_vertices"]).double(), torch.from_numpy(arrays["mesh_faces"]))
        generator = torch.Generator().manual_seed(args.seed)
        pick = torch.randperm(len(arrays["surface_points"]), generator=generator)[:3000]
        cloud = torch.from_numpy(arrays["surface_points"])[pick]
        cloud = cloud + args.noise * torch.randn(cloud.shape, generator=generator)

        t = time.perf_counter()
        points = PointSamples(PointCloud(cloud), weights={"surface": 1.0, "sdf": 1.0}, normals="estimate",
                              batch_size=2048, n_near=60_000, n_free=15_000)
        fitted = reconstruct_latent(deepsdf.decoder, [points], steps=args.latent_steps, lr=1e-2)
        add("cloud/deepsdf", record.name, score(fitted.field, gt, args.resolution), time.perf_counter() - t)
        t = time.perf_counter()
        add("cloud/occupancy_network", record.name, score(onet.field_from_cloud(cloud), gt, args.resolution),
            time.perf_counter() - t)

        frames, view_points, eye = one_view(gt, args.seed + record.index, 160, 120, noise=0.001)
        t = time.perf_counter()
        rays = DepthRays(frames, noise_model="constant", sigma=0.002, n_rays=1024)
        fitted = reconstruct_latent(deepsdf.decoder, [rays], steps=args.latent_steps, lr=1e-2)
        add("one_view/deepsdf", record.name, score(fitted.field, gt, args.resolution), time.perf_counter() - t)
        t = time.perf_counter()
        subset = view_points[torch.randperm(len(view_points), generator=generator)[:3000]]
        add("one_view/occupancy_network", record.name, score(onet.field_from_cloud(subset), gt, args.resolution),
            time.perf_counter() - t)
        t = time.perf_counter()
        try:
            mesh = poisson_one_view(view_points, eye)
            add("one_view/poisson", record.name, score(mesh, gt, args.resolution), time.perf_counter() - t)
        except NeuralsurfError as error:
            print(f"  poisson failed on {record.name}: {error}", flush=True)

    n_test = len(records) - n_train
    print(f"\n{n_test} test shapes ({args.classes}), trained on {n_train} "
          f"shapes: deepsdf {deepsdf_steps} steps / {deepsdf_s:.0f} s, occupancy_network {onet_steps} steps / "
          f"{onet_s:.0f} s, {threads} torch threads")
    print(f"{'row':28s} " + " ".join(f"{k:>18s}" for k in (*KEYS, "seconds")))
    for row, values in rows.items():
        means = [np.mean([v for v in values[k] if not math.isnan(v)] or [math.nan]) for k in (*KEYS, "seconds")]
        print(f"{row:28s} " + " ".join(f"{m:18.4f}" for m in means))
    (out / "bench_priors.json").write_text(json.dumps({"args": vars(args), "deepsdf_steps": deepsdf_steps,
                                                       "onet_steps": onet_steps, "per_shape": per_shape}, indent=1))
    print(f"total {time.perf_counter() - started:.0f} s; per-shape values in {out / 'bench_priors.json'}")


if __name__ == "__main__":
    main()
