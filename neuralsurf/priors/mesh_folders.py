"""Procedural shape collections written as folders of mesh files, damaged as CAD meshes are: test
collections for `FolderCollection` that the project can ship and rebuild from a seed.

`write_procedural_folder(out, ...)` writes `<out>/damaged/<class>/<name>.ply` (the folder layout of
`io.shape_folders`, with `train.lst` / `test.lst`) and the same shapes undamaged under
`<out>/clean/<class>/`, the reference for the labels (`folders.sign_errors`). Each mesh is the
marching cubes of a procedural shape (`procedural.SHAPE_CLASSES`: chairs, slatted chairs with thin
slats, legs and stretchers, mugs with handles, lamps), damaged by `winding.damage_mesh` with defects
drawn per shape (`cad_damage`): holes, coincident duplicated sheets facing either way, inner sheets and
reversed faces. Writing is resumable: meshes already there are kept.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from neuralsurf.errors import ConfigError
from neuralsurf.io.meshes import write_mesh
from neuralsurf.priors.procedural import Shape, ShapeRecord, collection_records
from neuralsurf.winding import damage_mesh


def cad_damage(record: ShapeRecord) -> dict:
    """`winding.damage_mesh` options drawn from a shape's seed: 1-4 holes of radius 0.02-0.05 (the
    longest side is 1), 0-2 duplicated and 0-2 inner sheets (0.01 below the surface), 0-30 % of the
    faces reversed."""
    rng = np.random.default_rng(record.seed ^ 0x5EED)
    return {"holes": int(rng.integers(1, 5)), "radius": float(rng.uniform(0.02, 0.05)),
            "duplicated": int(rng.integers(0, 3)), "inner": int(rng.integers(0, 3)), "inset": 0.01,
            "flipped": float(rng.uniform(0.0, 0.3)), "seed": int(rng.integers(2**31))}


def write_procedural_folder(out: str | Path, classes: tuple[str, ...] = ("chair", "slat_chair", "mug", "lamp"),
                            n_train: int = 40, n_test: int = 10, resolution: int = 64, seed: int = 0,
                            damage_test: bool = True) -> dict[str, int]:
    """Write the damaged folder and its clean twin (see the module docstring).

    Args:
        out: the folder that receives `damaged/` and `clean/`.
        classes, n_train, n_test, seed: the shapes (`procedural.collection_records`).
        resolution: marching cubes of each shape over the padded unit cube (64: 10k-40k faces).
        damage_test: damage the test meshes too (False: only the training meshes).
    Returns:
        {"written": meshes written now, "kept": meshes already there}.
    """
    if resolution < 16:
        raise ConfigError(f"write_procedural_folder: resolution must be >= 16, got {resolution}")
    out, counts = Path(out), {"written": 0, "kept": 0}
    records = collection_records(tuple(classes), n_train, 0, n_test, seed)
    for record in records:
        damaged_path = out / "damaged" / record.kind / f"{record.name}.ply"
        clean_path = out / "clean" / record.kind / f"{record.name}.ply"
        if damaged_path.is_file() and clean_path.is_file():
            counts["kept"] += 1
            continue
        mesh = Shape.from_record(record).mesh(resolution)
        damaged = damage_mesh(mesh, **cad_damage(record)).mesh if damage_test or record.split == "train" else mesh
        for path, version in ((clean_path, mesh), (damaged_path, damaged)):  # whole files or none
            temporary = path.with_name(f".{path.stem}.tmp{path.suffix}")
            write_mesh(temporary, version)
            os.replace(temporary, path)
        counts["written"] += 1
    for kind in classes:
        for split in ("train", "test"):
            names = "".join(f"{r.name}\n" for r in records if r.kind == kind and r.split == split)
            for version in ("damaged", "clean"):
                (out / version / kind / f"{split}.lst").write_text(names)
    return counts
