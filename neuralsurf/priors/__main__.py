"""Shape collections from the command line (the defaults are those of train.py's data configs):

- `python -m neuralsurf.priors build --out <dir> ...`: a procedural collection's caches
  (`python train.py experiment=shapes_deepsdf data.root=<dir>` then trains on it);
- `python -m neuralsurf.priors folder --out <dir> ...`: procedural shapes written as a folder of
  damaged mesh files, and their clean twins (`priors.mesh_folders`);
- `python -m neuralsurf.priors build-folder --source <dir> [--shard k --shards n] ...`: the caches of a
  folder of meshes (`FolderCollection`, train.py's data=shape_folder with data.source=<dir>), or part k
  of n of them, so that n jobs build a folder at once (the last to finish writes collection.json).

Interrupt any of them and run the same command again: what is there already is kept.
"""

from __future__ import annotations

import argparse
import sys
import time

from neuralsurf.priors.cache import CacheRecipe, build_collection
from neuralsurf.priors.folders import FolderCollection, shard_part
from neuralsurf.priors.mesh_folders import write_procedural_folder
from neuralsurf.priors.procedural import SHAPE_CLASSES, collection_records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m neuralsurf.priors", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    build = commands.add_parser("build", help="write per-shape npz caches and collection.json")
    build.add_argument("--out", required=True, help="output folder (created; reused to resume)")
    build.add_argument("--classes", default="chair,mug,lamp",
                       help=f"comma-separated shape classes of {', '.join(SHAPE_CLASSES)}")
    build.add_argument("--n-train", type=int, default=64, help="training shapes per class")
    build.add_argument("--n-val", type=int, default=0, help="validation shapes per class")
    build.add_argument("--n-test", type=int, default=8, help="test shapes per class")
    build.add_argument("--seed", type=int, default=0, help="collection seed (splits draw disjoint streams)")
    build.add_argument("--workers", type=int, default=2, help="processes (0: this one)")
    # the defaults of train.py's data=shapes, so that data.root=<out> finds this collection
    build.add_argument("--n-sdf", type=int, default=100_000, help="SDF samples per shape")
    build.add_argument("--n-occ", type=int, default=50_000, help="occupancy points per kind per shape")
    build.add_argument("--n-surface", type=int, default=20_000, help="surface samples per shape")
    defaults = CacheRecipe()
    build.add_argument("--mesh-resolution", type=int, default=defaults.mesh_resolution,
                       help="marching-cubes resolution of the ground-truth meshes")
    folder = commands.add_parser("folder", help="write procedural shapes as damaged mesh files, and clean twins")
    folder.add_argument("--out", required=True, help="receives damaged/<class>/*.ply and clean/<class>/*.ply")
    folder.add_argument("--classes", default="chair,slat_chair,mug,lamp", help="comma-separated shape classes")
    folder.add_argument("--n-train", type=int, default=40, help="training shapes per class")
    folder.add_argument("--n-test", type=int, default=10, help="test shapes per class")
    folder.add_argument("--mesh-resolution", type=int, default=64, help="marching-cubes resolution of each mesh")
    folder.add_argument("--seed", type=int, default=0)
    folder.add_argument("--clean-test", action="store_true", help="leave the test meshes undamaged")
    source = commands.add_parser("build-folder", help="build the caches of a folder of meshes (FolderCollection)")
    source.add_argument("--source", required=True, help="<source>/<class>/<shape>.obj|ply|off|stl|glb")
    source.add_argument("--shard", type=int, default=0, help="build part SHARD of SHARDS (0-based)")
    source.add_argument("--shards", type=int, default=1, help="parts that separate jobs build")
    source.add_argument("--workers", type=int, default=0, help="processes of this job (0: this one)")
    source.add_argument("--root", default=None, help="cache folder (default: the one train.py's data=shape_folder "
                                                     "uses for these settings)")
    source.add_argument("--n-sdf", type=int, default=100_000, help="SDF samples per shape")
    source.add_argument("--n-occ", type=int, default=50_000, help="occupancy points per kind per shape")
    source.add_argument("--n-surface", type=int, default=20_000, help="surface samples per shape")
    source.add_argument("--test-fraction", type=float, default=0.2)
    source.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    started = time.perf_counter()
    if args.command == "folder":
        counts = write_procedural_folder(args.out, tuple(c for c in args.classes.split(",") if c), args.n_train,
                                         args.n_test, args.mesh_resolution, args.seed, not args.clean_test)
        print(f"{args.out}: {counts['written']} meshes written, {counts['kept']} already there "
              f"({time.perf_counter() - started:.1f} s)")
        return 0
    if args.command == "build-folder":
        collection = FolderCollection(args.source, n_sdf=args.n_sdf, n_occ=args.n_occ, n_surface=args.n_surface,
                                      test_fraction=args.test_fraction, seed=args.seed, root=args.root,
                                      workers=args.workers)
        part = shard_part(collection.records(), args.shard, args.shards)
        before = sum(collection.is_cached(r) for r in part)
        out = collection.build(shard=args.shard, shards=args.shards)
        elapsed = time.perf_counter() - started
        built = len(part) - before
        per_shape = f", {elapsed / built:.2f} s a shape" if built else ""
        done = all(collection.is_cached(r) for r in collection.records())
        print(f"{collection.description}; part {args.shard} of {args.shards}: {built} of its {len(part)} shapes built"
              f"{per_shape}, {before} already cached ({elapsed:.1f} s); caches in {out}"
              + ("" if done else "; collection.json once every part is built"))
        return 0
    records = collection_records(tuple(c for c in args.classes.split(",") if c), args.n_train, args.n_val,
                                 args.n_test, args.seed)
    recipe = CacheRecipe(n_sdf=args.n_sdf, n_occ=args.n_occ, n_surface=args.n_surface,
                         mesh_resolution=args.mesh_resolution)
    started = time.perf_counter()
    counts = build_collection(args.out, records, recipe, workers=args.workers)
    print(f"{len(records)} shapes in {args.out}: {counts['built']} built, {counts['cached']} already cached "
          f"({time.perf_counter() - started:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
