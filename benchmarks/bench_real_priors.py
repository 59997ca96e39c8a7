"""A prior trained on damaged meshes against the same prior trained on the clean ones.

    python benchmarks/bench_real_priors.py --out /tmp/real_priors [--seed 1] [--threads 1]

The procedural chairs, mugs and lamps are written as mesh files (marching cubes at --mesh-resolution)
into two folders, one class per subfolder: `clean/` as they are, and `damaged/` where every training
mesh has the defects of CAD meshes (`winding.damage_mesh`: holes, coincident duplicated sheets
facing either way, inner sheets, a share of reversed faces); the test meshes are clean in both. Each
folder becomes a `FolderCollection` (signs by winding numbers, never by ray parity), the same DeepSDF
auto-decoder is trained on each for the same steps from the same seed, and both complete the same
clean test shapes from 3,000 noisy points. `--rows clean,damaged,parity` adds the damaged meshes with
ray-parity signs (what a watertight-mesh pipeline does); `resampled` the clean meshes with another draw of
sample positions (the collection's seed + 1000): how far the ratio moves when nothing but the draw
changes, as the damaged folder's draw differs from the clean one's. Printed: mean IoU of each and its ratio to clean,
with the build and training times. The defaults are sized for a 2-core CPU (about 15 minutes): 3 x 8
training and 3 x 2 test shapes, a small decoder; more shapes and steps raise both IoUs.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import torch

from neuralsurf.geometry import mesh_contains, point_to_mesh_distance, sample_mesh_surface
from neuralsurf.io import read_mesh, write_mesh
from neuralsurf.io.npz import write_npz
from neuralsurf.priors import CollectionSDF, Shape, collection_records, deepsdf, score_completions
from neuralsurf.priors.cache import CacheRecipe, write_manifest
from neuralsurf.priors.folders import FolderCollection
from neuralsurf.structures import Normalization
from neuralsurf.training import default_optimizer, fit
from neuralsurf.winding import damage_mesh


def write_folders(out: Path, classes: list[str], n_train: int, n_test: int, resolution: int, seed: int,
                  damage: dict) -> dict:
    """clean/<class>/<name>.ply and damaged/<class>/<name>.ply with train.lst / test.lst; returns counts."""
    watertight = {"clean": 0, "damaged": 0}
    for record in collection_records(tuple(classes), n_train, 0, n_test, seed):
        mesh = Shape.from_record(record).mesh(resolution)
        damaged = damage_mesh(mesh, **damage, seed=record.index).mesh if record.split == "train" else mesh
        for kind, version in (("clean", mesh), ("damaged", damaged)):
            folder = out / kind / record.kind
            write_mesh(folder / f"{record.name}.ply", version)
            with open(folder / f"{record.split}.lst", "a") as lst:
                lst.write(record.name + "\n")
            watertight[kind] += int(record.split == "train" and version.is_watertight)
    return watertight


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="/tmp/neuralsurf_real_priors")
    parser.add_argument("--classes", default="chair,mug,lamp")
    parser.add_argument("--n-train", type=int, default=8, help="training shapes per class")
    parser.add_argument("--n-test", type=int, default=2, help="test shapes per class")
    parser.add_argument("--mesh-resolution", type=int, default=48)
    parser.add_argument("--n-sdf", type=int, default=20_000, help="SDF samples per shape")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--depth", type=int, default=4)
    parser.add_argument("--latent-dim", type=int, default=16)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--latent-steps", type=int, default=150)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--holes", type=int, default=3, help="holes cut into each damaged training mesh")
    parser.add_argument("--hole-radius", type=float, default=0.04, help="their radius (the longest side is 1)")
    parser.add_argument("--flipped", type=float, default=0.3, help="share of reversed faces")
    parser.add_argument("--rows", default="clean,damaged",
                        help="priors to train: clean, damaged, parity (the damaged meshes with ray-parity signs), "
                             "resampled (the clean meshes, another draw of samples)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    classes = args.classes.split(",")
    if not (out / "clean").is_dir():
        damage = {"holes": args.holes, "radius": args.hole_radius, "duplicated": 2, "inner": 2, "inset": 0.01,
                  "flipped": args.flipped}
        watertight = write_folders(out, classes, args.n_train, args.n_test, args.mesh_resolution, args.seed, damage)
        print(f"training meshes watertight: clean {watertight['clean']}, damaged {watertight['damaged']} of "
              f"{args.n_train * len(classes)}", flush=True)
    results = {}
    clean = folder_collection(out, "clean", args)
    clean.build(progress=False)
    test_shapes = clean.test_shapes()  # the same clean meshes for every prior
    for kind in args.rows.split(","):
        started = time.perf_counter()
        if kind == "parity":  # the damaged folder with ray-parity signs: the watertight-mesh recipe
            collection = folder_collection(out, "damaged", args)
            folder = parity_caches(collection, out / "parity_cache", args.n_sdf, args.seed)
        elif kind == "resampled":
            collection = folder_collection(out, "clean", args, root="resampled_cache", seed=args.seed + 1000)
            folder = collection.build(progress=False)
        else:
            collection = folder_collection(out, kind, args)
            folder = collection.build(progress=False)
        built = time.perf_counter() - started
        torch.manual_seed(args.seed)
        model = deepsdf(collection.count("train"), latent_dim=args.latent_dim, width=args.width, depth=args.depth,
                        skip_layers=(args.depth // 2,))
        started = time.perf_counter()
        result = fit(model, [CollectionSDF(folder, shapes_per_batch=12, samples_per_shape=1024)],
                     steps=args.steps, normalization=Normalization(), encoding_lr=None, progress=False, seed=args.seed,
                     optimizer=functools.partial(default_optimizer, lr=1e-3))
        trained = time.perf_counter() - started
        means, per_shape, _ = score_completions(result.model, test_shapes, latent_steps=args.latent_steps,
                                                seed=args.seed)
        results[kind] = {"iou": means["iou"], "chamfer_l1_exact": means.get("chamfer_l1_exact"),
                         "build_s": built, "train_s": trained, "per_shape": per_shape}
        print(f"{kind:8s} IoU {means['iou']:.3f}  Chamfer-L1 {means.get('chamfer_l1_exact', float('nan')):.4f}  "
              f"(build {built:.0f} s, {args.steps} steps {trained:.0f} s, {collection.count('train')} train, "
              f"{len(test_shapes)} test shapes)", flush=True)
    print()
    for kind in results:
        if kind != "clean" and "clean" in results:
            print(f"IoU {kind} / clean = {results[kind]['iou']:.3f} / {results['clean']['iou']:.3f} = "
                  f"{results[kind]['iou'] / results['clean']['iou']:.3f}")
    name = f"bench_real_priors_{args.rows.replace(',', '_')}.json"
    (out / name).write_text(json.dumps({"args": vars(args), **results}, indent=1))


def folder_collection(out: Path, kind: str, args, root: str | None = None, seed: int | None = None) -> FolderCollection:
    return FolderCollection(str(out / kind), n_sdf=args.n_sdf, n_occ=1_000, n_surface=10_000,
                            root=str(out / (root or f"{kind}_cache")), workers=args.workers,
                            seed=args.seed if seed is None else seed)


def parity_caches(collection: FolderCollection, out: Path, n_sdf: int, seed: int) -> Path:
    """SDF caches of the collection's training meshes as a watertight-mesh pipeline makes them: samples
    near the whole mesh (inner sheets included), sign by ray parity (`geometry.mesh_contains`),
    no orientation repair. Only what `CollectionSDF` reads, and the manifest."""
    recipe = CacheRecipe(n_sdf=n_sdf)
    for record, entry in zip(collection.records("train"), collection.sources("train")):
        path = out / record.split / f"{record.name}.npz"
        if path.is_file():
            continue
        mesh = read_mesh(entry.path)
        mesh = Normalization.from_points(mesh.vertices).mesh_to_unit(mesh)
        generator = torch.Generator().manual_seed(seed + record.index)
        n_volume = round(n_sdf * recipe.volume_fraction)
        surface, _ = sample_mesh_surface(mesh, n_sdf - n_volume, generator)
        sigmas = torch.tensor(recipe.near_sigmas, dtype=torch.float64)[torch.arange(len(surface)) % 2]
        near = surface + sigmas[:, None] * torch.randn(surface.shape, dtype=torch.float64, generator=generator)
        volume = (2 * torch.rand(n_volume, 3, dtype=torch.float64, generator=generator) - 1) * (0.5 + recipe.padding)
        points = torch.cat([near, volume])
        distance = point_to_mesh_distance(points, mesh)
        values = torch.where(mesh_contains(points, mesh), -distance, distance)
        write_npz(path, {"sdf_points": points.float().numpy(), "sdf_values": values.float().numpy()})
    write_manifest(out, collection.records("train"), recipe)
    return out

if __name__ == "__main__":
    main()
