"""Mesh export: vertex normals and colours in .ply, .obj and .glb, read back by trimesh and Open3D;
train.py's `extract.format`, evaluate.py's `mesh_format`."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from neuralsurf.errors import ConfigError
from neuralsurf.extract import extract_mesh
from neuralsurf.geometry import vertex_normals
from neuralsurf.io import read_mesh, write_mesh
from neuralsurf.io.meshes import mesh_format
from neuralsurf.structures import Mesh

ROOT = Path(__file__).resolve().parents[1]


def sdf_sphere(radius: float = 0.4) -> Mesh:
    """Marching cubes of an exact sphere SDF (negative inside): the orientation every method's mesh has."""
    return extract_mesh(lambda x: x.norm(dim=-1) - radius, resolution=32, bounds=[[-0.5] * 3, [0.5] * 3],
                        coarse_to_fine=False, progress=False)


def colored(mesh: Mesh) -> Mesh:
    g = torch.Generator().manual_seed(0)
    rgb = torch.randint(0, 256, (len(mesh.vertices), 3), generator=g).double() / 255  # on the 8-bit grid
    return Mesh(mesh.vertices, mesh.faces, rgb)


def trimesh_normals(path: Path) -> np.ndarray:
    """The vertex normals stored in a file, as trimesh reads them (not recomputed)."""
    (loaded,) = trimesh.load_scene(str(path), process=False).geometry.values()
    assert "vertex_normals" in loaded._cache.cache, f"{path.name} holds no vertex normals"
    return np.asarray(loaded.vertex_normals)


def test_vertex_normals_of_an_sdf_sphere_point_outward_with_unit_length():
    mesh = sdf_sphere()
    vertices = mesh.vertices.double().numpy()
    normals = vertex_normals(vertices, mesh.faces.numpy())
    radial = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert (normals * radial).sum(1).mean() > 0.99 and (normals * radial).sum(1).min() > 0.9


def test_vertex_normals_weight_faces_by_area_and_leave_unused_vertices_zero():
    # a big and a small triangle at right angles share vertex 0; vertex 5 belongs to no face
    vertices = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 1], [0, 1, 0], [9, 9, 9]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 3, 4]])  # normals +z (area 8) and -x (area 0.5)
    normals = vertex_normals(vertices, faces)
    expected = np.array([-0.5, 0, 8]) / np.linalg.norm([-0.5, 0, 8])
    assert np.allclose(normals[0], expected) and np.allclose(normals[1], [0, 0, 1])
    assert np.array_equal(normals[5], [0, 0, 0])


@pytest.mark.parametrize("ext", [".ply", ".obj", ".glb"])
def test_stored_normals_of_a_sphere_point_outward_and_colours_survive(tmp_path, ext):
    mesh = colored(sdf_sphere())
    path = tmp_path / f"sphere{ext}"
    write_mesh(path, mesh)
    normals = trimesh_normals(path)
    back = read_mesh(path)
    assert torch.equal(back.faces, mesh.faces)
    torch.testing.assert_close(back.vertices.float(), mesh.vertices.float(), rtol=0, atol=0)
    radial = back.vertices.numpy() / np.linalg.norm(back.vertices.numpy(), axis=1, keepdims=True)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert (normals * radial).sum(1).mean() > 0.99
    torch.testing.assert_close(back.vertex_colors.double(), mesh.vertex_colors.double(), rtol=0, atol=1e-6)


def test_ply_normals_are_vertex_properties(tmp_path):
    plyfile = pytest.importorskip("plyfile")
    mesh = sdf_sphere()
    write_mesh(tmp_path / "m.ply", mesh)
    vertex = plyfile.PlyData.read(str(tmp_path / "m.ply"))["vertex"]
    assert [p.name for p in vertex.properties] == ["x", "y", "z", "nx", "ny", "nz"]
    stored = np.stack([vertex[a] for a in ("nx", "ny", "nz")], 1)
    assert np.array_equal(stored, vertex_normals(mesh.vertices.numpy(), mesh.faces.numpy()))


@pytest.mark.parametrize("ext", [".glb", ".ply", ".obj"])
def test_open3d_reads_the_same_vertices_faces_normals_and_colours(tmp_path, ext):
    o3d = pytest.importorskip("open3d")
    mesh = colored(sdf_sphere())
    path = tmp_path / f"m{ext}"
    write_mesh(path, mesh)
    back = o3d.io.read_triangle_mesh(str(path))
    vertices, faces = np.asarray(back.vertices), np.asarray(back.triangles)
    # the same triangles; Open3D may renumber vertices (it splits or merges at its own will)
    assert len(faces) == len(mesh.faces)
    assert np.allclose(vertices[faces], mesh.vertices.float().double().numpy()[mesh.faces.numpy()], rtol=0, atol=1e-7)
    assert back.has_vertex_normals() and back.has_vertex_colors()
    radial = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    assert (np.asarray(back.vertex_normals) * radial).sum(1).mean() > 0.99
    expected = mesh.vertex_colors.numpy()[mesh.faces.numpy()]
    assert np.allclose(np.asarray(back.vertex_colors)[faces], expected, atol=1e-6)


def test_glb_read_by_open3d_tensor_io(tmp_path):
    o3d = pytest.importorskip("open3d")
    mesh = sdf_sphere()
    write_mesh(tmp_path / "m.glb", mesh)
    back = o3d.t.io.read_triangle_mesh(str(tmp_path / "m.glb"))
    vertices = back.vertex.positions.numpy().astype(np.float64)
    faces = back.triangle.indices.numpy()
    assert len(faces) == len(mesh.faces)
    assert np.allclose(vertices[faces], mesh.vertices.float().double().numpy()[mesh.faces.numpy()], rtol=0, atol=1e-7)


def test_mesh_format_names_the_choices():
    assert [mesh_format(name) for name in ("ply", "GLB", ".obj")] == [".ply", ".glb", ".obj"]
    with pytest.raises(ConfigError, match=r"unknown mesh format 'fbx'; choose one of ply, obj, off, stl, glb"):
        mesh_format("fbx")


TINY = ["experiment=sphere_sdf", "trainer.steps=2", "extract.resolution=32", "trainer.progress=false", "device=cpu"]


def train(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "train.py"), *TINY, f"hydra.run.dir={run_dir}", *overrides],
                          check=False, capture_output=True, text=True, cwd=ROOT, timeout=600)


@pytest.mark.subprocess
@pytest.mark.slow
def test_train_writes_the_extract_format(tmp_path):
    o3d = pytest.importorskip("open3d")
    done = train(tmp_path / "run", "extract.format=glb")
    assert done.returncode == 0, done.stderr[-3000:]
    path = tmp_path / "run" / "mesh.glb"
    assert path.is_file() and not (tmp_path / "run" / "mesh.ply").exists()
    mesh = read_mesh(path)
    back = o3d.io.read_triangle_mesh(str(path))
    vertices, faces = np.asarray(back.vertices), np.asarray(back.triangles)
    assert len(faces) == len(mesh.faces) > 100
    assert np.allclose(vertices[faces], mesh.vertices.numpy()[mesh.faces.numpy()], rtol=0, atol=1e-7)
    assert (np.linalg.norm(trimesh_normals(path), axis=1) > 0.999).all()


@pytest.mark.subprocess
def test_train_refuses_an_unknown_format_before_fitting(tmp_path):
    done = train(tmp_path / "run", "extract.format=fbx")
    assert done.returncode != 0
    assert "unknown mesh format 'fbx'; choose one of ply, obj, off, stl, glb" in done.stderr + done.stdout
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_evaluate_saves_meshes_in_mesh_format(tmp_path):
    from neuralsurf.evaluation import run_benchmark
    from neuralsurf.scenes import Scene
    from neuralsurf.structures import PointCloud

    gt = sdf_sphere()
    scene = Scene(name="ball", cloud=PointCloud(gt.vertices), description="a ball", ground_truth=gt)
    rows = run_benchmark({"ball": lambda: scene}, {"same": lambda: (lambda s, **kw: s.ground_truth)}, tmp_path,
                         n_samples=500, render=False, mesh_format="obj", log=lambda line: None)
    assert rows[0]["status"] == "ok", rows[0]["reason"]
    assert rows[0]["mesh"] == str(Path("meshes") / "ball__same.obj")
    assert torch.equal(read_mesh(tmp_path / rows[0]["mesh"]).faces, gt.faces)
    with pytest.raises(ConfigError, match="choose one of ply"):
        run_benchmark({"ball": lambda: scene}, {"same": lambda: (lambda s, **kw: s.ground_truth)}, tmp_path,
                      mesh_format="3ds", log=lambda line: None)
