"""A prior trained on damaged meshes against the same prior trained on the clean ones.

    python benchmarks/bench_real_priors.py --out /tmp/real_priors [--seed 1] [--threads 1] [--repeats 3]

The procedural chairs, mugs and lamps are written as mesh files (marching cubes at --mesh-resolution)
into two folders, one class per subfolder: `clean/` as they are, and `damaged/` where every training
mesh has the defects of CAD meshes (`priors.mesh_folders.damage_mesh`: holes, coincident duplicated sheets
facing either way, inner sheets, a share of reversed faces); the test meshes are clean in both. Each
folder becomes a `FolderCollection` (signs by winding numbers, never by ray parity).

First the labels, with no training involved: for each training cache, the share of its samples whose
side disagrees with the clean mesh's exact inside (`folders.sign_errors`: SDF samples near the
surface and in the volume, occupancy samples), per class. Then the same DeepSDF auto-decoder is
trained on each folder for the same steps from the same seed, and both complete the same clean test
shapes from 3,000 noisy points (the same clouds). One run's IoU moves by several hundredths with the
draw of sample positions and the training run alone (thin chair legs most), so every row is trained
and scored `--repeats` times, each with another draw and training seed (seed, seed + 1, ...), and the
IoUs are averaged. `--rows clean,damaged,parity` adds the damaged meshes with ray-parity signs (what a
watertight-mesh pipeline does); `resampled` the clean meshes with another draw of sample positions
(the collection's seed + 1000). Printed: the label errors, each repeat's IoU and ratio to clean, the
mean IoU of each row (per class), its ratio to clean, and the build, training and scoring times.

The defaults are sized for a 2-core CPU: 3 x 8 training and 3 x 4 test shapes, a small decoder, 3
repeats; more shapes and steps raise both IoUs. Seed 0 took 15.8 min (peak RSS 0.87 GB) with
`--threads 1` on the 2-core CPU, busy (load average 7.5, two other evaluations running): labels of
the damaged caches at most 0.2 % wrong in any class and kind of sample, IoU damaged / clean 0.726 /
0.718 = 1.012 (repeats 1.030, 1.003, 1.003); seeds 1 and 2: 1.013 and 0.999 in 15.0 and 16.2 min
(single runs 0.939-1.119). The tables are in docs/benchmarks.md ("Priors from damaged meshes").
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

from neuralsurf.geometry import mesh_contains, point_to_mesh_distance, sample_mesh_surface
from neuralsurf.io import read_mesh, write_mesh
from neuralsurf.io.npz import write_npz
from neuralsurf.priors import CollectionSDF, Shape, collection_records, deepsdf, score_completions
from neuralsurf.priors.cache import CacheRecipe, cache_path, load_cache, write_manifest
from neuralsurf.priors.folders import FolderCollection, sign_errors
from neuralsurf.priors.mesh_folders import damage_mesh
from neuralsurf.structures import Normalization
from neuralsurf.training import default_optimizer, fit


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
    parser.add_argument("--n-test", type=int, default=4, help="test shapes per class")
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
    parser.add_argument("--repeats", type=int, default=3,
                        help="train and score every row this many times, each with another draw of sample positions "
                             "and another training seed (seed, seed + 1, ...); the IoUs are averaged")
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
    clean = folder_collection(out, "clean", args)
    clean.build(progress=False)
    test_shapes = clean.test_shapes()  # the same clean meshes (and input clouds) for every prior
    rows = args.rows.split(",")
    results = {kind: {"iou": [], "chamfer_l1_exact": [], "build_s": 0.0, "train_s": 0.0, "score_s": 0.0,
                      "per_shape": []} for kind in rows}
    for repeat in range(args.repeats):
        seed = args.seed + repeat  # another draw of sample positions and another training run
        for kind in rows:
            row = results[kind]
            started = time.perf_counter()
            collection, folder = row_caches(out, kind, args, seed, repeat)
            row["build_s"] += time.perf_counter() - started
            if kind in ("clean", "damaged") and repeat == 0:
                row["sign_errors"] = label_errors(out, kind, collection)
                print_label_errors(kind, row["sign_errors"])
            torch.manual_seed(seed)
            model = deepsdf(collection.count("train"), latent_dim=args.latent_dim, width=args.width,
                            depth=args.depth, skip_layers=(args.depth // 2,))
            started = time.perf_counter()
            result = fit(model, [CollectionSDF(folder, shapes_per_batch=12, samples_per_shape=1024)],
                         steps=args.steps, normalization=Normalization(), encoding_lr=None, progress=False,
                         seed=seed, optimizer=functools.partial(default_optimizer, lr=1e-3))
            row["train_s"] += time.perf_counter() - started
            started = time.perf_counter()
            means, per_shape, _ = score_completions(result.model, test_shapes, latent_steps=args.latent_steps,
                                                    seed=args.seed)
            row["score_s"] += time.perf_counter() - started
            row["iou"].append(means["iou"])
            row["chamfer_l1_exact"].append(means.get("chamfer_l1_exact", float("nan")))
            row["per_shape"].append(per_shape)
            ratio = f"  ratio to clean {means['iou'] / results['clean']['iou'][-1]:.3f}" if (
                kind != "clean" and "clean" in results) else ""
            print(f"repeat {repeat} {kind:9s} IoU {means['iou']:.3f}  Chamfer-L1 "
                  f"{means.get('chamfer_l1_exact', float('nan')):.4f}{ratio}", flush=True)
    print()
    paired, left_out = paired_means(results)
    shapes = f"{args.repeats} repeat(s) x {len(test_shapes) - left_out} test shapes" + (
        f" ({left_out} without an IoU in some row left out)" if left_out else "")
    for kind, row in results.items():
        print(f"{kind:9s} mean IoU {np.mean(paired[kind]):.3f} over {shapes} (by class: {class_means(row['per_shape'])})  "
              f"Chamfer-L1 {np.mean(row['chamfer_l1_exact']):.4f}  "
              f"time: build {row['build_s']:.0f} s, train {row['train_s']:.0f} s, score {row['score_s']:.0f} s")
    for kind in results:
        if kind != "clean" and "clean" in results:
            each = ", ".join(f"{a / b:.3f}" for a, b in zip(paired[kind], paired["clean"]))
            print(f"IoU {kind} / clean = {np.mean(paired[kind]):.3f} / {np.mean(paired['clean']):.3f} = "
                  f"{np.mean(paired[kind]) / np.mean(paired['clean']):.3f} (each repeat: {each})")
    name = f"bench_real_priors_{args.rows.replace(',', '_')}.json"
    (out / name).write_text(json.dumps({"args": vars(args), **results}, indent=1))


def row_caches(out: Path, kind: str, args, seed: int, repeat: int) -> tuple[FolderCollection, Path]:
    """The collection of a row and its built caches, with sample positions drawn from `seed`."""
    suffix = f"_{repeat}" if repeat else ""
    if kind == "parity":  # the damaged folder with ray-parity signs: the watertight-mesh recipe
        collection = folder_collection(out, "damaged", args, seed=seed)
        return collection, parity_caches(collection, out / f"parity_cache{suffix}", args.n_sdf, seed)
    if kind == "resampled":
        collection = folder_collection(out, "clean", args, root=f"resampled_cache{suffix}", seed=seed + 1000)
    else:
        collection = folder_collection(out, kind, args, root=f"{kind}_cache{suffix}", seed=seed)
    return collection, collection.build(progress=False)


def label_errors(out: Path, kind: str, collection: FolderCollection) -> dict[str, dict[str, list[float]]]:
    """Per class, per kind of sample (`folders.sign_errors`): the share of each training shape's cached
    labels that disagree with its clean mesh's exact inside, in the frame the cache was built in."""
    errors: dict[str, dict[str, list[float]]] = {}
    for record, entry in zip(collection.records("train"), collection.sources("train")):
        frame = Normalization.from_points(read_mesh(entry.path).vertices.double())
        clean = read_mesh(out / "clean" / record.kind / f"{entry.name}.ply")
        shares = sign_errors(load_cache(cache_path(collection.folder, record)), frame.mesh_to_unit(clean),
                             collection.recipe)
        for key, share in shares.items():
            errors.setdefault(record.kind, {}).setdefault(key, []).append(share)
    return errors


def print_label_errors(kind: str, errors: dict[str, dict[str, list[float]]]) -> None:
    for category, shares in errors.items():
        text = ", ".join(f"{key} {100 * np.mean(v):.3f}% (max {100 * np.max(v):.3f}%)" for key, v in shares.items())
        print(f"labels of {kind} {category} training caches against the clean meshes, wrong: {text}", flush=True)


def paired_means(results: dict) -> tuple[dict[str, list[float]], int]:
    """Each row's mean IoU in each repeat over the test shapes that have an IoU (both meshes closed) in
    every row and repeat, so that rows are compared on the same shapes; and how many were left out."""
    names = [shape["shape"] for shape in next(iter(results.values()))["per_shape"][0]]
    scored = [{shape["shape"] for shape in run if math.isfinite(shape["iou"])}
              for row in results.values() for run in row["per_shape"]]
    valid = set(names).intersection(*scored)
    means = {kind: [float(np.mean([shape["iou"] for shape in run if shape["shape"] in valid])) for run in row["per_shape"]]
             for kind, row in results.items()}
    return means, len(names) - len(valid)


def class_means(per_shape: list[list[dict]]) -> str:
    by_class: dict[str, list[float]] = {}
    for rows in per_shape:
        for row in rows:
            by_class.setdefault(row["shape"].split("_")[0], []).append(row["iou"])
    return " / ".join(f"{c} {np.nanmean(v):.3f}" + (f" ({np.isnan(v).sum()} without IoU)" if np.isnan(v).any() else "")
                      for c, v in by_class.items())


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
        surface, _ = sample_mesh_surface(mesh, n_sdf - recipe.n_volume, generator)
        sigmas = torch.tensor(recipe.near_sigmas, dtype=torch.float64)[torch.arange(len(surface)) % 2]
        near = surface + sigmas[:, None] * torch.randn(surface.shape, dtype=torch.float64, generator=generator)
        volume = (2 * torch.rand(recipe.n_volume, 3, dtype=torch.float64, generator=generator) - 1) * (0.5 + recipe.padding)
        points = torch.cat([near, volume])
        distance = point_to_mesh_distance(points, mesh)
        values = torch.where(mesh_contains(points, mesh), -distance, distance)
        write_npz(path, {"sdf_points": points.float().numpy(), "sdf_values": values.float().numpy()})
    write_manifest(out, collection.records("train"), recipe)
    return out


if __name__ == "__main__":
    main()
