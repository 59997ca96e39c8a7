"""Per class of a scene set (the test shapes of a collection): does each method beat the baselines of the
same input, by how much, and on how many shapes. The report's answer to "does the learned prior help?".

Shapes are matched by name across the rows of one scene set; a shape's class is its name less the
collection's `_<split>_<index>` suffix (`chair_test_0003` -> `chair`), "all" gathers every shape.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

BASELINES = ("tsdf", "poisson")
"""The methods every other method of a scene set is compared with, where the run has them."""

SHAPE_NAME = re.compile(r"(?P<kind>.+)_(train|val|test)_\d+")


def shape_class(name: str) -> str:
    """`chair_test_0003` -> `chair`; a name without the collection's suffix is its own class."""
    match = SHAPE_NAME.fullmatch(name)
    return match["kind"] if match else name


def _values(row: dict[str, Any], key: str) -> dict[str, float]:
    """shape name -> the row's per-shape `key` (finite values only)."""
    return {shape["shape"]: float(shape[key]) for shape in row.get("per_shape") or []
            if isinstance(shape.get(key), (int, float)) and math.isfinite(shape[key])}


def class_comparison(rows: list[dict[str, Any]], baselines: tuple[str, ...] = BASELINES) -> list[dict[str, Any]]:
    """One entry per (scene set, class, method other than the baselines): "scene", "class", "method",
    "shapes" (n), the method's mean "chamfer" (exact Chamfer-L1) and "fscore" (F@1%), and per baseline
    b of that scene set: "<b>_chamfer", "<b>_fscore" (its means on the same shapes), "<b>_ratio" (b's
    mean Chamfer over the method's: > 1 where the method is better) and "<b>_wins" (shapes where the
    method's Chamfer is lower); "best_ratio": the better baseline's mean Chamfer over the method's.
    Only shapes that every compared row scored count."""
    sets = [r for r in rows if r["status"] == "ok" and r.get("per_shape")]
    out = []
    for scene in dict.fromkeys(r["scene"] for r in sets):
        by_method = {r["method"]: r for r in sets if r["scene"] == scene}
        present = [b for b in baselines if b in by_method]
        for method in by_method:
            if method in baselines:
                continue
            chamfer = {m: _values(by_method[m], "chamfer_l1_exact") for m in [method, *present]}
            fscore = {m: _values(by_method[m], "fscore_1%") for m in [method, *present]}
            common = [s for s in chamfer[method] if all(s in chamfer[m] and s in fscore[m] for m in chamfer)]
            classes = {"all": common}
            for shape in common:
                classes.setdefault(shape_class(shape), []).append(shape)
            for name, shapes in sorted(classes.items(), key=lambda item: (item[0] == "all", item[0])):
                if not shapes:
                    continue
                entry = {"scene": scene, "class": name, "method": method, "shapes": len(shapes),
                         "chamfer": float(np.mean([chamfer[method][s] for s in shapes])),
                         "fscore": float(np.mean([fscore[method][s] for s in shapes]))}
                for b in present:
                    entry[f"{b}_chamfer"] = float(np.mean([chamfer[b][s] for s in shapes]))
                    entry[f"{b}_fscore"] = float(np.mean([fscore[b][s] for s in shapes]))
                    entry[f"{b}_ratio"] = entry[f"{b}_chamfer"] / max(entry["chamfer"], 1e-12)
                    entry[f"{b}_wins"] = sum(chamfer[method][s] < chamfer[b][s] for s in shapes)
                if present:
                    entry["best_ratio"] = min(entry[f"{b}_chamfer"] for b in present) / max(entry["chamfer"], 1e-12)
                out.append(entry)
    return out


def class_table(rows: list[dict[str, Any]],
                baselines: tuple[str, ...] = BASELINES) -> tuple[list[str], list[list[str]]]:
    """`class_comparison` as a table's header and rows of cells: per scene set, class and method, its
    exact Chamfer-L1 and F@1%, and against each baseline "ratio (k/n)": the baseline's mean Chamfer over
    the method's and the shapes the method wins, with the baseline's F@1%. No rows without scene sets."""
    entries = class_comparison(rows, baselines)
    present = [b for b in baselines if any(f"{b}_ratio" in e for e in entries)]
    header = ["scene", "class", "method", "shapes", "Chamfer-L1 exact", "F@1%"]
    for b in present:
        header += [f"{b}: Chamfer / method's (shapes won)", f"{b}: F@1%"]
    header += ["better baseline / method"] if present else []
    lines = []
    for e in entries:
        cells = [e["scene"], e["class"], e["method"], str(e["shapes"]), f"{e['chamfer']:.4g}", f"{e['fscore']:.3f}"]
        for b in present:
            cells += ([f"{e[f'{b}_ratio']:.2f}x ({e[f'{b}_wins']}/{e['shapes']})", f"{e[f'{b}_fscore']:.3f}"]
                      if f"{b}_ratio" in e else ["", ""])
        cells += [f"{e['best_ratio']:.2f}x" if "best_ratio" in e else ""] if present else []
        lines.append(cells)
    return header, lines
