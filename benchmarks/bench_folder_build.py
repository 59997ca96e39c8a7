"""Building a folder of damaged CAD-like meshes: seconds a mesh, and the labels against the clean meshes
and against the exact winding number.

    python benchmarks/bench_folder_build.py --out /tmp/folder_build [--n-train 50 --n-test 10] [--shards 2]

Writes the procedural chairs, slatted chairs, mugs and lamps as a damaged mesh folder and its clean twin
(`priors.mesh_folders.write_procedural_folder`, marching cubes at --mesh-resolution, defects drawn per
shape), then builds the folder's caches with train.py's data=shape_folder sizes (100,000 SDF and 2 x
50,000 occupancy samples a shape) in --shards separate processes (`python -m neuralsurf.priors
build-folder --shard k --shards n`, the jobs a cluster would run), and builds it a second time (every
shape a cache hit). Printed: wall seconds a mesh and CPU seconds a mesh (the jobs' own), the faces;
the labels' share that disagrees with the clean mesh's exact inside (`folders.sign_errors`, per class);
and, on --exact-shapes shapes, --exact-points samples each, the labels against the exact sum of every
triangle's solid angle over the cached surface (`winding_number(approximate=False)`), with the time of
both on those points.

    python benchmarks/bench_folder_build.py --single chair:80,mug:72,slat_chair:120

times one damaged shape's whole cache (`folders.mesh_samples`, the same sizes) in this process instead,
CPU and wall seconds, for one shape of each class at the given marching-cubes resolution (about 50,000
faces at these).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from neuralsurf.io import read_mesh
from neuralsurf.priors.cache import CacheRecipe, cache_path, load_cache
from neuralsurf.priors.folders import FolderCollection, mesh_samples, sign_errors
from neuralsurf.priors.mesh_folders import cad_damage, damage_mesh, write_procedural_folder
from neuralsurf.priors.procedural import Shape, collection_records
from neuralsurf.structures import Mesh, Normalization
from neuralsurf.winding import MeshWinding, winding_number


def build(source: Path, root: Path, shards: int) -> tuple[float, float]:
    """Build the folder's caches in `shards` processes at once; (wall s, CPU s of the processes)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    command = [sys.executable, "-m", "neuralsurf.priors", "build-folder", "--source", str(source), "--root", str(root),
               "--shards", str(shards)]
    jobs = [subprocess.Popen(command + ["--shard", str(k)]) for k in range(shards)]
    if any(job.wait() for job in jobs):
        raise SystemExit("a build job failed")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.perf_counter() - started, (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)


def single(shapes: str) -> None:
    """Time one damaged shape's cache per `class:resolution` in this process."""
    recipe = FolderCollection(".").recipe
    for item in shapes.split(","):
        kind, resolution = item.split(":")
        record = collection_records((kind,), 1, 0, 0)[0]
        mesh = damage_mesh(Shape.from_record(record).mesh(int(resolution)), **cad_damage(record)).mesh
        mesh = Normalization.from_points(mesh.vertices.double()).mesh_to_unit(Mesh(mesh.vertices.double(), mesh.faces))
        mesh_samples(mesh, CacheRecipe(n_sdf=100, n_occ=50, n_surface=20))  # imports and first calls
        cpu, wall = time.process_time(), time.perf_counter()
        mesh_samples(mesh, recipe)
        print(f"{record.name} at {resolution}^3, {len(mesh.faces)} faces: {time.process_time() - cpu:.2f} s CPU, "
              f"{time.perf_counter() - wall:.2f} s wall (load average {os.getloadavg()[0]:.1f})", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="/tmp/neuralsurf_folder_build")
    parser.add_argument("--classes", default="chair,slat_chair,mug,lamp")
    parser.add_argument("--n-train", type=int, default=50)
    parser.add_argument("--n-test", type=int, default=10)
    parser.add_argument("--mesh-resolution", type=int, default=64)
    parser.add_argument("--shards", type=int, default=2)
    parser.add_argument("--exact-shapes", type=int, default=8)
    parser.add_argument("--exact-points", type=int, default=1000)
    parser.add_argument("--single", default=None, help="class:resolution,...: time single shapes' caches instead")
    args = parser.parse_args()
    if args.single:
        return single(args.single)
    out = Path(args.out)
    classes = tuple(args.classes.split(","))
    started = time.perf_counter()
    counts = write_procedural_folder(out, classes, args.n_train, args.n_test, args.mesh_resolution)
    print(f"folder: {counts['written']} meshes written, {counts['kept']} kept ({time.perf_counter() - started:.0f} s)",
          flush=True)
    source, root = out / "damaged", out / "cache"
    collection = FolderCollection(str(source), root=str(root))
    records = collection.records()
    faces = [len(read_mesh(e.path).faces) for e in collection.sources()]
    print(f"{len(records)} meshes, faces {min(faces)}-{max(faces)} (median {int(np.median(faces))})", flush=True)
    wall, cpu = build(source, root, args.shards)
    print(f"build: {wall:.0f} s wall in {args.shards} jobs, {wall / len(records):.2f} s wall a mesh, "
          f"{cpu / len(records):.2f} s CPU a mesh (load average {os.getloadavg()[0]:.1f})", flush=True)
    again, _ = build(source, root, 1)
    print(f"second build: {again:.1f} s (every shape a cache hit)", flush=True)

    errors: dict[str, dict[str, list[float]]] = {}
    for record, entry in zip(records, collection.sources()):
        frame = Normalization.from_points(read_mesh(entry.path).vertices.double())
        clean = read_mesh(out / "clean" / record.kind / f"{entry.name}.ply")
        shares = sign_errors(load_cache(cache_path(root, record)), frame.mesh_to_unit(clean), collection.recipe)
        for key, share in shares.items():
            errors.setdefault(record.kind, {}).setdefault(key, []).append(share)
    for kind, shares in errors.items():
        text = ", ".join(f"{key} {100 * np.mean(v):.3f}% (max {100 * np.max(v):.3f}%)" for key, v in shares.items())
        print(f"labels of {kind} against the clean meshes, wrong: {text}", flush=True)

    generator = torch.Generator().manual_seed(0)
    wrong, total, ours_s, exact_s = 0, 0, 0.0, 0.0
    for record in records[:: max(1, len(records) // args.exact_shapes)][: args.exact_shapes]:
        arrays = load_cache(cache_path(root, record))
        surface = Mesh(torch.from_numpy(arrays["mesh_vertices"]).double(), torch.from_numpy(arrays["mesh_faces"]))
        points = torch.cat([torch.from_numpy(arrays[k]) for k in ("sdf_points", "occ_uniform_points", "occ_near_points")])
        labels = torch.cat([torch.from_numpy(arrays["sdf_values"]) < 0, torch.from_numpy(arrays["occ_uniform_inside"]),
                            torch.from_numpy(arrays["occ_near_inside"])])
        pick = torch.randperm(len(points), generator=generator)[: args.exact_points]
        t = time.perf_counter()
        MeshWinding(surface).inside(points[pick].double())
        ours_s += time.perf_counter() - t
        t = time.perf_counter()
        exact = winding_number(points[pick].double(), surface, approximate=False)
        exact_s += time.perf_counter() - t
        clear = (exact - 0.5).abs() > 1e-4  # float32 rounding of the exact sum
        wrong += int((labels[pick] != (exact >= 0.5))[clear].sum())
        total += int(clear.sum())
        print(f"  {record.name}: {len(surface.faces)} faces, {int((labels[pick] != (exact >= 0.5))[clear].sum())} of "
              f"{int(clear.sum())} labels differ from the exact winding number", flush=True)
    print(f"labels against the exact winding number: {wrong} of {total} differ; on those points ours {ours_s:.2f} s, "
          f"the exact sum {exact_s:.1f} s ({exact_s / max(ours_s, 1e-9):.0f}x)")


if __name__ == "__main__":
    main()
