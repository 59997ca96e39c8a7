"""Build a procedural shape collection's caches: `python -m neuralsurf.priors build --out <dir> ...`
(the defaults are those of train.py's data=shapes: `python train.py experiment=shapes_deepsdf
data.root=<dir>` then trains on it).

Interrupt it at any time and run the same command again: shapes already cached are skipped.
"""

from __future__ import annotations

import argparse
import sys
import time

from neuralsurf.priors.cache import CacheRecipe, build_collection
from neuralsurf.priors.procedural import SHAPE_CLASSES, collection_records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m neuralsurf.priors", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    build = commands.add_parser("build", help="write per-shape npz caches and collection.json")
    build.add_argument("--out", required=True, help="output folder (created; reused to resume)")
    build.add_argument("--classes", default=",".join(SHAPE_CLASSES), help="comma-separated shape classes")
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
    args = parser.parse_args(argv)

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
