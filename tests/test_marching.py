"""marching: the PyTorch marching cubes against skimage's, and closed where skimage's is."""

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from neuralsurf.marching import _EDGES, case_table, marching_cubes_torch


def test_every_case_uses_exactly_its_sign_changing_edges():
    """Each case's triangles use exactly the edges whose corners differ; only the two uniform cases have
    none."""
    table, counts = case_table()
    for case in range(256):
        triangles = table[case, : counts[case]].tolist()
        inside = [case >> c & 1 for c in range(8)]
        crossed = {e for e, (a, b) in enumerate(_EDGES) if inside[a] != inside[b]}
        assert {e for t in triangles for e in t} == crossed
        assert (counts[case] == 0) == (case in (0, 255))


def test_a_torus_gives_skimages_vertices_and_a_closed_outward_mesh():
    axis = np.linspace(-1, 1, 81)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    values = (np.sqrt((np.sqrt((x - 0.03) ** 2 + y**2) - 0.55) ** 2 + (z - 0.01) ** 2) - 0.2).astype(np.float32)
    expected_vertices, expected_faces, _, _ = marching_cubes(values, 0.0)
    vertices, faces = marching_cubes_torch(torch.from_numpy(values), 0.0)
    assert len(vertices) == len(expected_vertices) and len(faces) == len(expected_faces)
    assert cKDTree(expected_vertices).query(vertices.numpy())[0].max() < 1e-4
    mesh = trimesh.Trimesh(vertices.numpy(), faces.numpy(), process=False)
    reference = trimesh.Trimesh(expected_vertices, expected_faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(reference.volume, rel=1e-3) and mesh.volume > 0


def test_noise_full_of_ambiguous_cells_still_gives_a_closed_manifold():
    """Random values make every ambiguous face and cube case appear: two cells sharing a face must cut
    it alike, and no fan diagonal may be drawn by both (a mesh edge with four triangles)."""
    noise = np.random.default_rng(1).standard_normal((30, 30, 30))
    values = np.pad(noise, 1, constant_values=5.0).astype(np.float32)  # closed: above the level outside
    vertices, faces = marching_cubes_torch(torch.from_numpy(values), 0.0)
    mesh = trimesh.Trimesh(vertices.numpy(), faces.numpy(), process=False)
    assert len(faces) > 50_000 and mesh.is_watertight and mesh.is_winding_consistent


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_extract_mesh_marches_on_the_gpu_for_a_field_there():
    from neuralsurf.extract import extract_mesh

    box = torch.tensor([[-0.5] * 3, [0.5] * 3], dtype=torch.float64)
    sphere = lambda x: x.norm(dim=-1) - 0.3  # noqa: E731
    cpu = extract_mesh(sphere, 96, box, device="cpu", progress=False)
    gpu = extract_mesh(sphere, 96, box, device="cuda", progress=False)
    assert len(gpu.vertices) == len(cpu.vertices) and gpu.is_watertight
    assert cKDTree(cpu.vertices.numpy()).query(gpu.vertices.numpy())[0].max() < 1e-5
