"""The learning curve of a learned prior: completion from one depth view against the number of
training shapes, beside TSDF fusion and Poisson of the same views.

    python benchmarks/bench_learning_curve.py --out /tmp/learning_curve [--sizes 12,48,200] [--steps 600]
        [--n-test 2] [--priors deepsdf] [--plot docs/images/learning_curve.png]

Writes the procedural chairs, slatted chairs, mugs and lamps as a folder of meshes (`python -m
neuralsurf.priors folder`: the training meshes damaged as CAD meshes are, the test meshes clean so that
the completions' IoU is defined), builds its caches with train.py's data=shape_folder sizes, then for
each number of training shapes (spread evenly over the 4 classes) runs `evaluate.py suite=priors_folder
scenes=[shapes_one_view]` with `folder.n_train` set to it: the prior is trained on that many shapes
(streamed from the caches) and completes the same held-out shapes (`--n-test` per class) from the same
one-view depth images. TSDF and Poisson of those views are scored once (their input does not depend on
the training shapes). Every number comes from the evaluation runner's scoring (exact Chamfer-L1, F-score
at 1 % of the longest side, IoU where both meshes are closed: the priors' completions, not the open
TSDF and Poisson meshes); the table prints the means over the held-out shapes and, with --plot, a
bar chart of Chamfer-L1 and F@1% per size.

`--steps` and `--latent-steps` set the budget, the same for every size: the defaults took 29.6 min on
the 2-core CPU, busy (load average 4-10; the folder's caches built before), far below a converged prior
(train.py's shapes_deepsdf trains 6,000 steps), and 600 steps leave 200 shapes seen 24 times each: read
the curve as a small-budget one (docs/benchmarks.md, "The learning curve").
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

from neuralsurf.evaluation.render import bar_chart
from neuralsurf.priors.folders import FolderCollection
from neuralsurf.priors.mesh_folders import write_procedural_folder

ROOT = Path(__file__).resolve().parents[1]
BASELINES = ("tsdf", "poisson")
CLASSES = ("chair", "slat_chair", "mug", "lamp")


def evaluate(out: Path, name: str, per_class: int, methods: list[str], args) -> tuple[dict[str, dict], float]:
    """`evaluate.py suite=priors_folder` on the one-view scenes of the folder's held-out shapes with the
    priors trained on `per_class` shapes of each class; the rows by method and the wall seconds."""
    run_dir = out / name
    overrides = [
        "suite=priors_folder", f"folder.source={out / 'damaged'}", f"folder.root={out / 'cache'}",
        f"folder.n_train={per_class}", f"folder.n_test={args.n_test}", "folder.workers=0",
        "scenes=[shapes_one_view]", f"methods=[{','.join(methods)}]", f"threads={args.threads}", "render=false",
        f"seed={args.seed}", f"hydra.run.dir={run_dir}",
    ]
    for prior in args.priors:
        overrides += [f"method.{prior}.trainer.steps={args.steps}", f"method.{prior}.latent_steps={args.latent_steps}"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    started = time.perf_counter()
    subprocess.run([sys.executable, str(ROOT / "evaluate.py"), *overrides], check=True, env=env, cwd=ROOT,
                   stdout=subprocess.DEVNULL)
    seconds = time.perf_counter() - started
    rows = json.loads((run_dir / "results.json").read_text())["rows"]
    failed = [f"{row['method']}: {row.get('reason')}" for row in rows if row["status"] != "ok"]
    if failed:
        raise SystemExit(f"{run_dir}: rows not scored: {failed}")
    return {row["method"]: row for row in rows}, seconds


def summary(row: dict) -> dict[str, float]:
    """Means over the held-out shapes of a row's per-shape metrics (IoU over the shapes that have one)."""
    shapes = row["per_shape"]
    ious = [s["iou"] for s in shapes if s.get("iou") is not None and math.isfinite(s["iou"])]
    return {"chamfer": float(np.mean([s["chamfer_l1_exact"] for s in shapes])),
            "fscore": float(np.mean([s["fscore_1%"] for s in shapes])),
            "iou": float(np.mean(ious)) if ious else float("nan"), "iou_shapes": len(ious), "shapes": len(shapes),
            "seconds": float(row["seconds"])}


def plot(path: Path, results: dict, sizes: list[int], priors: list[str]) -> None:
    """Bar charts of Chamfer-L1 and F@1% per number of training shapes (the baselines' bars repeat)."""
    groups = [f"{size} shapes" for size in sizes]
    series = [*priors, *BASELINES]
    charts = []
    for key, title in (("chamfer", "one view: exact Chamfer-L1 (lower is better)"),
                       ("fscore", "one view: F@1% (higher is better)")):
        values = {(f"{size} shapes", method): results[str(size)][method][key]
                  for size in sizes for method in series}
        charts.append(bar_chart(title, groups, series, values))
    image = Image.new("RGB", (max(c.width for c in charts), sum(c.height for c in charts)), "white")
    for i, chart in enumerate(charts):
        image.paste(chart, (0, sum(c.height for c in charts[:i])))
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="/tmp/neuralsurf_learning_curve")
    parser.add_argument("--sizes", default="12,48,200", help="training shapes, multiples of the 4 classes")
    parser.add_argument("--n-test", type=int, default=2, help="held-out shapes per class")
    parser.add_argument("--priors", default="deepsdf", help="deepsdf and/or occupancy_network, comma-separated")
    parser.add_argument("--steps", type=int, default=600, help="training steps of each prior")
    parser.add_argument("--latent-steps", type=int, default=60, help="DeepSDF's latent fit per view")
    parser.add_argument("--mesh-resolution", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plot", default=None, help="write the bar charts to this PNG")
    args = parser.parse_args()
    args.priors = args.priors.split(",")
    sizes = [int(s) for s in args.sizes.split(",")]
    if any(size % len(CLASSES) or size < len(CLASSES) for size in sizes):
        raise SystemExit(f"--sizes must be multiples of {len(CLASSES)} (shapes spread evenly over the classes)")
    out = Path(args.out)
    started = time.perf_counter()
    counts = write_procedural_folder(out, CLASSES, max(sizes) // len(CLASSES), args.n_test, args.mesh_resolution,
                                     args.seed, damage_test=False)
    collection = FolderCollection(str(out / "damaged"), n_test=args.n_test, root=str(out / "cache"), workers=2,
                                  seed=args.seed)
    collection.build(progress=False)
    print(f"folder: {counts['written']} meshes written, {counts['kept']} kept; {collection.description}; "
          f"{time.perf_counter() - started:.0f} s", flush=True)

    results: dict[str, dict] = {}
    for index, size in enumerate(sizes):
        methods = args.priors + (list(BASELINES) if index == 0 else [])
        rows, seconds = evaluate(out, f"eval_{size}", size // len(CLASSES), methods, args)
        results[str(size)] = {method: summary(row) for method, row in rows.items()}
        if index:  # the baselines' input is the same views whatever the training shapes
            results[str(size)].update({m: results[str(sizes[0])][m] for m in BASELINES})
        line = "  ".join(f"{m} Chamfer {v['chamfer']:.4f} F@1% {v['fscore']:.3f}" + (
            f" IoU {v['iou']:.3f} ({v['iou_shapes']} shapes)" if m in args.priors else "")
            for m, v in results[str(size)].items())
        print(f"{size:4d} training shapes ({seconds:.0f} s): {line}  load average {os.getloadavg()[0]:.1f}",
              flush=True)

    print()
    header = "| training shapes | " + " | ".join(
        f"{p} IoU | {p} Chamfer-L1 | {p} F@1%" for p in args.priors) + " | TSDF Chamfer-L1 | TSDF F@1% | " \
        "Poisson Chamfer-L1 | Poisson F@1% | " + " | ".join(f"better baseline / {p} (Chamfer)" for p in args.priors) + " |"
    print(header)
    print("|" + "---|" * header.count(" | ") + "---|")
    for size in sizes:
        result = results[str(size)]
        better = min(result[b]["chamfer"] for b in BASELINES)
        cells = [str(size)]
        for p in args.priors:
            cells += [f"{result[p]['iou']:.3f}", f"{result[p]['chamfer']:.4f}", f"{result[p]['fscore']:.3f}"]
        for b in BASELINES:
            cells += [f"{result[b]['chamfer']:.4f}", f"{result[b]['fscore']:.3f}"]
        cells += [f"{better / result[p]['chamfer']:.2f}x" for p in args.priors]
        print("| " + " | ".join(cells) + " |")
    print(f"\n{args.n_test * len(CLASSES)} held-out shapes; {args.steps} training steps, {args.latent_steps} latent "
          f"steps; total {time.perf_counter() - started:.0f} s (load average {os.getloadavg()[0]:.1f})")
    (out / "learning_curve.json").write_text(json.dumps({"args": vars(args), "results": results}, indent=1))
    if args.plot:
        plot(Path(args.plot), results, sizes, args.priors)
        print(f"plot: {args.plot}")


if __name__ == "__main__":
    main()
