"""Learned shape priors end to end on the CPU: build a procedural collection, train a DeepSDF
auto-decoder and an Occupancy Network over it, and score both on held-out test shapes.

    python benchmarks/bench_priors.py --out /tmp/shapes_bench --minutes-deepsdf 6 --minutes-onet 6

Rows (means over the test split; per-shape values in <out>/bench_priors.json):
- cloud: 3,000 noisy surface points (Gaussian, --noise) of each test shape. DeepSDF: latent fit under
  the frozen decoder (PointSamples: surface and near-surface terms + code prior). OccNet: one forward
  pass of the encoder.
- one_view: one synthetic depth view of each test shape. DeepSDF: latent fit to the depth rays
  (DepthRays: surface, band, free space + code prior). OccNet: encoder on the back-projected view.
  Either completion is then held to what the view saw (`priors.refine_to_view`; `--no-refine`: the
  prior's field as it is).
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
from pathlib import Path

import numpy as np
import torch

from neuralsurf.baselines import reconstruct_poisson
from neuralsurf.errors import NeuralsurfError
from neuralsurf.geometry import noisy_cloud
from neuralsurf.metrics import evaluate_mesh
from neuralsurf.models import SDFMLP, AutoDecoder, CBNDecoder, LatentCodes, OccupancyNetwork, PointNetEncoder
from neuralsurf.priors import ShapeCollection, complete_cloud, complete_view, extract_unit, shapes_one_view
from neuralsurf.priors.observations import CollectionOccupancy, CollectionSDF
from neuralsurf.structures import Mesh, Normalization
from neuralsurf.training import default_optimizer, fit

KEYS = ("iou", "chamfer_l1_exact", "normal_consistency", "fscore_1%", "pred_watertight")


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
        mesh = field_or_mesh if isinstance(field_or_mesh, Mesh) else extract_unit(field_or_mesh, resolution)
        metrics = evaluate_mesh(mesh, gt, n_samples=20_000)
    except NeuralsurfError as error:  # no surface: the worst score, counted
        print(f"    no mesh: {str(error)[:80]}", flush=True)
        return {"iou": 0.0, "chamfer_l1_exact": math.nan, "normal_consistency": math.nan, "fscore_1%": 0.0,
                "pred_watertight": 0.0}
    return {key: float(metrics[key]) for key in KEYS}


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
    parser.add_argument("--no-refine", action="store_true", help="one-view completions without the refinement")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    threads = torch.get_num_threads()
    out = Path(args.out)

    started = time.perf_counter()
    collection = ShapeCollection(tuple(args.classes.split(",")), args.n_train, 0, args.n_test, args.seed,
                                 root=str(out), workers=args.workers)
    collection.build(progress=False)
    n_train, n_test = collection.count("train"), collection.count("test")
    print(f"collection: {n_train} train and {n_test} test shapes, {time.perf_counter() - started:.0f} s; "
          f"torch threads {threads}", flush=True)

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

    views = shapes_one_view(collection, seed=args.seed).scenes  # one depth view per test shape
    for i, (shape, view) in enumerate(zip(collection.test_shapes(), views)):
        cloud = noisy_cloud(shape.surface, 3000, args.noise, args.seed + i)
        for name, prior in (("deepsdf", deepsdf), ("occupancy_network", onet)):
            t = time.perf_counter()
            field = complete_cloud(prior, cloud, latent_steps=args.latent_steps, seed=args.seed)
            add(f"cloud/{name}", shape.name, score(field, shape.mesh, args.resolution), time.perf_counter() - t)
        for name, prior in (("deepsdf", deepsdf), ("occupancy_network", onet)):
            t = time.perf_counter()
            field = complete_view(prior, view.frames, view.cloud.points, latent_steps=args.latent_steps, seed=args.seed,
                                  **({"refine": None} if args.no_refine else {}))
            add(f"one_view/{name}", shape.name, score(field, shape.mesh, args.resolution), time.perf_counter() - t)
        t = time.perf_counter()
        try:
            mesh = reconstruct_poisson(view.cloud, depth=7)
            add("one_view/poisson", shape.name, score(mesh, shape.mesh, args.resolution), time.perf_counter() - t)
        except NeuralsurfError as error:
            print(f"  poisson failed on {shape.name}: {error}", flush=True)

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
