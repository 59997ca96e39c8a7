"""marching: the PyTorch marching cubes against skimage's, and closed where skimage's is."""

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from neuralsurf.extract import level_set
from neuralsurf.marching import _EDGES, case_table, cube_triangles, marching_cubes_torch, merge_edge_vertices


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
    values = torus_values(81)
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


def torus_values(points: int, step: float | None = None) -> np.ndarray:
    axis = np.linspace(-1, 1, points)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    values = (np.sqrt((np.sqrt((x - 0.03) ** 2 + y**2) - 0.55) ** 2 + (z - 0.01) ** 2) - 0.2).astype(np.float32)
    return values if step is None else (np.round(values / step) * step).astype(np.float32)


def cubes_of(grid: torch.Tensor, side: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Float[Tensor, "n n n"] with n = k (side - 1) + 1 -> the k^3 cubes of `side` points that tile it
    (neighbours share a layer of points), Float[Tensor, "k^3 side side side"], and their first points."""
    cubes = grid.unfold(0, side, side - 1).unfold(1, side, side - 1).unfold(2, side, side - 1)
    k = cubes.shape[0]
    origins = torch.stack(torch.meshgrid(*[torch.arange(k) * (side - 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return cubes.reshape(-1, side, side, side), origins


def oriented_faces(faces: torch.Tensor) -> set[tuple[int, ...]]:
    """Faces as a set, each rotated to start at its lowest vertex (orientation kept)."""
    return {tuple(np.roll(face, -int(np.argmin(face)))) for face in faces.tolist()}


@pytest.mark.parametrize("step", [None, 1 / 32])
def test_cubes_marched_apart_and_merged_by_edge_give_the_whole_grids_mesh(step):
    """The torus in 5^3 cubes of 9^3 points, marched apart and merged by grid edge: the same vertices and
    faces as one call on the whole grid, closed, also with exact zeros on grid points (`step`)."""
    values = torch.from_numpy(torus_values(41, step))
    whole_vertices, whole_faces = marching_cubes_torch(values)
    cubes, origins = cubes_of(values, 9)
    vertices, faces = merge_edge_vertices(*cube_triangles(cubes, None, origins, values.shape))
    assert torch.equal(vertices, whole_vertices) and oriented_faces(faces) == oriented_faces(whole_faces)
    mesh = trimesh.Trimesh(vertices.numpy(), faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent


def test_cells_with_an_invalid_corner_get_no_faces_as_in_skimages_masked_marching():
    """Part of the torus unobserved: the marched cubes keep the vertices of skimage's masked cells (a few
    more: skimage joins the vertices of edges that meet at a grid point within float precision)."""
    values = torus_values(41)
    valid = np.ones(values.shape, dtype=bool)
    valid[:, :17] = False
    expected, expected_faces = level_set(values, 0.0, valid)
    cubes, origins = cubes_of(torch.from_numpy(values), 9)
    masks, _ = cubes_of(torch.from_numpy(valid), 9)
    vertices, faces = merge_edge_vertices(*cube_triangles(cubes, masks, origins, values.shape))
    assert 0 <= len(vertices) - len(expected) <= 0.005 * len(expected)
    assert abs(len(faces) - len(expected_faces)) <= 0.005 * len(expected_faces)
    assert cKDTree(expected).query(vertices.numpy())[0].max() < 1e-4
    assert cKDTree(vertices.numpy()).query(expected)[0].max() < 1e-4
    assert vertices[:, 1].min() >= 16


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_extract_mesh_marches_on_the_gpu_for_a_field_there():
    from neuralsurf.extract import extract_mesh

    box = torch.tensor([[-0.5] * 3, [0.5] * 3], dtype=torch.float64)
    sphere = lambda x: x.norm(dim=-1) - 0.3  # noqa: E731
    cpu = extract_mesh(sphere, 96, box, device="cpu", progress=False)
    gpu = extract_mesh(sphere, 96, box, device="cuda", progress=False)
    assert len(gpu.vertices) == len(cpu.vertices) and gpu.is_watertight
    assert cKDTree(cpu.vertices.numpy()).query(gpu.vertices.numpy())[0].max() < 1e-5
