"""Procedural shape collections written as folders of mesh files, damaged as CAD meshes are: test
collections for `FolderCollection` that the project can ship and rebuild from a seed.

`write_procedural_folder(out, ...)` writes `<out>/damaged/<class>/<name>.ply` (the folder layout of
`io.shape_folders`, with `train.lst` / `test.lst`) and the same shapes undamaged under
`<out>/clean/<class>/`, the reference for the labels (`folders.sign_errors`). Each mesh is the
marching cubes of a procedural shape (`procedural.SHAPE_CLASSES`: chairs, slatted chairs with thin
slats, legs and stretchers, mugs with handles, lamps), damaged by `damage_mesh` with defects
drawn per shape (`cad_damage`): holes, coincident duplicated sheets facing either way, inner sheets and
reversed faces (`damage_mesh`, also the tests' and benchmarks' way to damage a clean mesh where its
labels are known). Writing is resumable: meshes already there are kept.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import vertex_normals
from neuralsurf.io.meshes import write_mesh
from neuralsurf.priors.procedural import Shape, ShapeRecord, collection_records
from neuralsurf.structures import Mesh


@dataclass(frozen=True)
class DamagedMesh:
    """A mesh with CAD-like defects, and where they are."""

    mesh: Mesh
    centres: Tensor
    """Float[Tensor, "k 3"]: centre of each damaged region."""
    radii: Tensor
    """Float[Tensor, "k"]: each region's radius; away from every ball the surface is the clean one."""

    def away(self, points: Tensor, factor: float = 2.0) -> Tensor:
        """Bool[Tensor, "n"]: points farther than `factor` radii from every damaged region."""
        if len(self.radii) == 0:
            return torch.ones(len(points), dtype=torch.bool, device=points.device)
        distance = torch.cdist(points.double(), self.centres.double().to(points.device))
        return (distance > factor * self.radii.double().to(points.device)).all(1)


def _region(vertices: Tensor, faces: Tensor, centre: Tensor, radius: float) -> Tensor:
    """Bool[Tensor, "f"]: faces with a corner within `radius` of `centre`."""
    return ((vertices[faces] - centre).norm(dim=-1) < radius).any(1)


def damage_mesh(mesh: Mesh, *, holes: int = 3, duplicated: int = 2, inner: int = 2, flipped: float = 0.1,
                radius: float = 0.05, inset: float = 0.01, seed: int = 0) -> DamagedMesh:
    """A clean, closed mesh damaged as CAD meshes are, for testing signs against the clean mesh.

    - `holes` balls of `radius` (a fraction of the longest side) whose faces are deleted (open boundaries);
    - `duplicated` regions copied as a separate, coincident sheet, half of them facing the other way;
    - `inner` regions copied `inset` (a fraction of the longest side) inside along the vertex normals,
      as a separate sheet facing either way (internal faces); keep `inset` below half the thinnest wall;
    - a fraction `flipped` of all faces (sheets included) reversed one by one.

    Only holes and inner sheets change the surface; the returned regions cover holes, duplicated and
    inner sheets (reversed faces are everywhere and `orient_outward` repairs them).
    """
    if mesh.is_empty:
        raise InputError("damage_mesh needs a mesh with faces, got an empty mesh")
    if not (0 <= flipped <= 1 and radius > 0 and inset >= 0):
        raise ConfigError(f"damage_mesh needs 0 <= flipped <= 1, radius > 0 and inset >= 0, got flipped={flipped}, "
                          f"radius={radius}, inset={inset}")
    generator = torch.Generator().manual_seed(seed)
    vertices = mesh.vertices.detach().cpu().double()
    faces = mesh.faces.cpu().clone()
    extent = float((vertices.max(0).values - vertices.min(0).values).max())
    r = radius * extent
    normals = torch.from_numpy(vertex_normals(vertices.numpy(), faces.numpy()))
    centres = vertices[torch.randint(len(vertices), (holes + duplicated + inner,), generator=generator)]
    keep = torch.ones(len(faces), dtype=torch.bool)
    for centre in centres[:holes]:
        keep &= ~_region(vertices, faces, centre, r)
    out_vertices, out_faces, offset = [vertices], [faces[keep]], len(vertices)
    for i, centre in enumerate(centres[holes:]):
        used, local = torch.unique(faces[_region(vertices, faces, centre, r)], return_inverse=True)
        sheet = local.reshape(-1, 3) + offset
        if i < duplicated:  # coincident copy, every other one facing inward
            out_vertices.append(vertices[used])
            reverse = i % 2 == 1
        else:  # inner sheet: moved inside along the normals, facing either way
            out_vertices.append(vertices[used] - inset * extent * normals[used])
            reverse = bool(torch.rand(1, generator=generator) < 0.5)
        out_faces.append(sheet.flip(1) if reverse else sheet)
        offset += len(used)
    faces = torch.cat(out_faces)
    turn = torch.rand(len(faces), generator=generator) < flipped
    faces[turn] = faces[turn].flip(1)
    damaged = Mesh(torch.cat(out_vertices).to(mesh.vertices), faces.to(mesh.faces.device))
    return DamagedMesh(damaged, centres.to(mesh.vertices), torch.full((len(centres),), r).to(mesh.vertices))


def cad_damage(record: ShapeRecord) -> dict:
    """`damage_mesh` options drawn from a shape's seed: 1-4 holes of radius 0.02-0.05 (the
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
