"""Shape-collection folders: meshes by class subfolder, and Occupancy Networks' preprocessed layout."""

import numpy as np
import pytest
import torch
import trimesh

from neuralsurf.errors import FileFormatError, InputError
from neuralsurf.io import read_mesh
from neuralsurf.io.shape_folders import (
    folder_layout,
    list_mesh_folder,
    list_occupancy_folder,
    read_occupancy_shape,
    unpack_occupancies,
)


def write_mesh_folder(root):
    box, ball = trimesh.creation.box((1.0, 0.5, 0.25)), trimesh.creation.icosphere(1)
    (root / "chair").mkdir(parents=True)
    box.export(root / "chair" / "a.obj")
    ball.export(root / "chair" / "b.PLY")
    box.export(root / "chair" / "notes.txt", file_type="off")  # not a mesh extension: ignored
    (root / "cup" / "c1" / "models").mkdir(parents=True)
    ball.export(root / "cup" / "c1" / "models" / "model_normalized.obj")  # ShapeNet-like shape folder
    box.export(root / "cup" / "d.off")
    box.export(root / "cup" / "e.glb")
    (root / "cup" / "train.lst").write_text("c1\nd\n")
    (root / "cup" / "test.lst").write_text("e\n")
    return box, ball


def test_mesh_folder_lists_classes_shapes_and_splits(tmp_path):
    box, ball = write_mesh_folder(tmp_path)
    entries = list_mesh_folder(tmp_path)
    assert [(e.category, e.name, e.split) for e in entries] == [
        ("chair", "a", None), ("chair", "b", None), ("cup", "c1", "train"), ("cup", "d", "train"),
        ("cup", "e", "test")]
    assert entries[2].path.name == "model_normalized.obj"
    assert folder_layout(tmp_path) == "meshes"
    for entry in entries:  # each entry reads back as the mesh written
        mesh = read_mesh(entry.path)
        expected = ball if entry.name in ("b", "c1") else box
        assert np.allclose(sorted(mesh.vertices.numpy().tolist()), sorted(np.asarray(expected.vertices).tolist()))


def test_mesh_folder_errors_name_the_problem(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        list_mesh_folder(tmp_path / "absent")
    with pytest.raises(InputError, match="no class subfolders"):
        list_mesh_folder(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.warns(UserWarning, match="holds no meshes"), pytest.raises(InputError, match="holds no meshes"):
        list_mesh_folder(tmp_path)
    (tmp_path / "mug" / "m" / "parts").mkdir(parents=True)
    trimesh.creation.box().export(tmp_path / "mug" / "m" / "one.obj")
    trimesh.creation.box().export(tmp_path / "mug" / "m" / "parts" / "two.obj")
    (tmp_path / "empty").rmdir()
    with pytest.raises(InputError, match="must hold one mesh"):
        list_mesh_folder(tmp_path)


def test_split_lists_warn_about_missing_and_unlisted_shapes(tmp_path):
    (tmp_path / "lamp").mkdir()
    for name in ("p", "q"):
        trimesh.creation.box().export(tmp_path / "lamp" / f"{name}.obj")
    (tmp_path / "lamp" / "train.lst").write_text("p\nghost\n")
    with pytest.warns(UserWarning) as record:
        entries = list_mesh_folder(tmp_path)
    messages = " ".join(str(w.message) for w in record)
    assert "missing" in messages and "'ghost'" in messages and "in no .lst file" in messages and "'q'" in messages
    assert [(e.name, e.split) for e in entries] == [("p", "train")]
    (tmp_path / "lamp" / "test.lst").write_text("p\n")
    with pytest.raises(InputError, match="both train.lst and test.lst"):
        list_mesh_folder(tmp_path)


def write_occupancy_shape(folder, n=1001, seed=0, packed=True):
    """A sphere of radius 0.4 in Occupancy Networks' files: float16 points, packed occupancies."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.55, 0.55, (n, 3)).astype(np.float16)
    inside = np.linalg.norm(points.astype(np.float64), axis=1) < 0.4
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    folder.mkdir(parents=True)
    np.savez(folder / "points.npz", points=points, occupancies=np.packbits(inside) if packed else inside,
             loc=np.zeros(3), scale=np.float64(1))
    np.savez(folder / "pointcloud.npz", points=(0.4 * normals).astype(np.float16),
             normals=normals.astype(np.float16), loc=np.zeros(3), scale=np.float64(1))
    return points, inside


def test_occupancy_layout_reads_packed_and_plain_occupancies(tmp_path):
    points, inside = write_occupancy_shape(tmp_path / "02691156" / "s1")
    assert points.dtype == np.float16  # as Occupancy Networks store them
    write_occupancy_shape(tmp_path / "02691156" / "s2", seed=1, packed=False)
    (tmp_path / "02691156" / "val.lst").write_text("s2\n")
    (tmp_path / "02691156" / "train.lst").write_text("s1\n")
    assert folder_layout(tmp_path) == "occupancy"
    entries = list_occupancy_folder(tmp_path)
    assert [(e.category, e.name, e.split) for e in entries] == [("02691156", "s1", "train"), ("02691156", "s2", "val")]
    shape = read_occupancy_shape(entries[0].path)
    assert shape.points.dtype == torch.float32 and shape.occupancies.dtype == torch.bool
    assert torch.equal(shape.occupancies, torch.from_numpy(inside))
    assert torch.equal(shape.occupancies, shape.points.double().norm(dim=1) < 0.4)  # the sphere oracle
    assert torch.allclose(shape.surface.double().norm(dim=1), torch.full((500,), 0.4, dtype=torch.float64), atol=1e-3)
    second = read_occupancy_shape(entries[1].path)
    assert torch.equal(second.occupancies, second.points.double().norm(dim=1) < 0.4)


def test_occupancy_files_that_do_not_fit_are_named(tmp_path):
    folder = tmp_path / "c" / "s"
    write_occupancy_shape(folder)
    np.savez(folder / "points.npz", points=np.zeros((10, 3)), occupancies=np.zeros(3, np.uint8))
    with pytest.raises(FileFormatError, match="3 occupancies .* for 10 points"):
        read_occupancy_shape(folder)
    np.savez(folder / "points.npz", points=np.zeros((10, 3)))
    with pytest.raises(FileFormatError, match="lacks \\['occupancies'\\]"):
        read_occupancy_shape(folder)
    (folder / "pointcloud.npz").unlink()
    np.savez(folder / "points.npz", points=np.zeros((10, 3)), occupancies=np.zeros(10, bool))
    with pytest.raises(FileFormatError, match="pointcloud.npz not found"):
        read_occupancy_shape(folder)
    with pytest.raises(InputError, match="not Occupancy Networks' layout"), pytest.warns(UserWarning):
        list_occupancy_folder(tmp_path / "c" / "s" / "..")
    assert unpack_occupancies(np.packbits([1, 0, 1]), 3).tolist() == [True, False, True]
