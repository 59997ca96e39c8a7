import numpy as np
import pytest
import torch

from neuralsurf.errors import InputError
from neuralsurf.scenes import Box, Sphere
from neuralsurf.structures import Mesh, Normalization, PointCloud


def test_point_cloud_validates_its_input():
    with pytest.raises(InputError, match="empty"):
        PointCloud(torch.zeros(0, 3))
    with pytest.raises(InputError, match="NaN or inf"):
        PointCloud(torch.tensor([[0.0, 0.0, float("nan")], [1.0, 2.0, 3.0]]))
    with pytest.raises(InputError, match="NaN or inf"):
        PointCloud(torch.tensor([[0.0, 0.0, float("inf")]]))
    with pytest.raises(InputError, match=r"normals has 2 rows but there are 3 points"):
        PointCloud(torch.zeros(3, 3), normals=torch.zeros(2, 3))
    with pytest.raises(InputError, match=r"shape \(n, 3\)"):
        PointCloud(torch.zeros(4, 2))


def test_point_cloud_keeps_dtype_and_accepts_numpy():
    cloud = PointCloud(np.random.default_rng(0).random((10, 3)))
    assert cloud.points.dtype == torch.float64 and len(cloud) == 10
    assert PointCloud(torch.zeros(2, 3)).points.dtype == torch.float32


def test_select_and_with_normals():
    cloud = Sphere().sample_surface(100)
    half = cloud.select(torch.arange(50))
    assert len(half) == 50 and torch.equal(half.normals, cloud.normals[:50])
    assert cloud.with_normals(None).normals is None


def test_mesh_round_trips_through_trimesh_and_open3d_exactly():
    mesh = Sphere(center=(0.1, 0.2, 0.3)).mesh(subdivisions=3)
    colors = torch.rand(len(mesh.vertices), 3, dtype=torch.float64)
    colored = Mesh(mesh.vertices, mesh.faces, colors)
    again = Mesh.from_open3d(colored.to_open3d())
    assert torch.equal(again.vertices, mesh.vertices) and torch.equal(again.faces, mesh.faces)
    assert torch.allclose(again.vertex_colors, colors)
    via_trimesh = Mesh.from_trimesh(mesh.to_trimesh())
    assert torch.equal(via_trimesh.vertices, mesh.vertices) and torch.equal(via_trimesh.faces, mesh.faces)


def test_mesh_validates_faces_and_reports_watertightness():
    with pytest.raises(InputError, match="outside"):
        Mesh(torch.zeros(3, 3), torch.tensor([[0, 1, 3]]))
    box = Box().mesh()
    assert box.is_watertight
    assert not Mesh(box.vertices, box.faces[1:]).is_watertight
    assert not Mesh(box.vertices, box.faces[:0]).is_watertight
    assert box.face_areas().sum().item() == pytest.approx(Box().area)


def test_watertightness_agrees_with_trimesh():
    """trimesh's merge_vertices, is_watertight and is_winding_consistent as the oracle: a closed sphere, a face
    missing, a face flipped, a face doubled, the surface with its reversed copy, two copies of the surface on the
    same points (four faces on an edge once merged), a triangle soup (merged) and the soup moved by 1e-5 (not
    merged)."""
    sphere = Sphere().mesh()
    vertices, faces = sphere.vertices.double(), sphere.faces
    soup, order = vertices[faces].reshape(-1, 3), torch.arange(3 * len(faces)).reshape(-1, 3)
    noise = torch.randn(soup.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    meshes = [sphere, Mesh(vertices, faces[1:]), Mesh(vertices, torch.cat([faces[:1].flip(1), faces[1:]])),
              Mesh(vertices, torch.cat([faces, faces[:1]])), Mesh(vertices, torch.cat([faces, faces.flip(1)])),
              Mesh(torch.cat([vertices, vertices]), torch.cat([faces, faces + len(vertices)])),
              Mesh(soup, order), Mesh(soup + 1e-5 * noise, order)]
    expected = []
    for mesh in meshes:
        merged = mesh.to_trimesh()
        merged.merge_vertices()
        expected.append(bool(merged.is_watertight and merged.is_winding_consistent))
    assert [mesh.is_watertight for mesh in meshes] == expected
    assert expected == [True, False, False, False, False, False, True, False]


def test_normalization_round_trip_and_unit_box():
    points = torch.tensor([[1.0, 2.0, 3.0], [5.0, 3.0, 4.0], [2.0, 2.5, 3.5]], dtype=torch.float64)
    norm = Normalization.from_points(points)
    unit = norm.to_unit(points)
    assert norm.scale == 4.0
    assert torch.allclose(unit.max(0).values - unit.min(0).values, torch.tensor([1.0, 0.25, 0.25], dtype=torch.float64))
    assert torch.allclose(norm.to_world(unit), points)
    restored = Normalization.from_state_dict(norm.state_dict())
    assert torch.equal(restored.center, norm.center) and restored.scale == norm.scale
    with pytest.raises(InputError, match="scale"):
        Normalization.from_points(torch.ones(5, 3))


def _depth_frame_inputs():
    """A valid 8x6 depth frame at 1 m, its pinhole K and an identity pose."""
    K = torch.tensor([[5.0, 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]])
    return torch.ones(1, 6, 8), K, torch.eye(4)


@pytest.mark.parametrize("entry", [(0, 0), (1, 1), (0, 2), (1, 2)])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_depth_frames_reject_non_finite_focal_lengths_and_principal_points(entry, value):
    from neuralsurf.structures import DepthFrames

    depth, K, pose = _depth_frame_inputs()
    DepthFrames(depth, K, pose)  # the valid frame passes
    K[entry] = value
    with pytest.raises(InputError, match="NaN or inf.*focal lengths and principal points must be finite"):
        DepthFrames(depth, K, pose)


def test_check_intrinsics_rejects_nan_directly():
    from neuralsurf.structures import check_intrinsics

    K = torch.tensor([[[float("nan"), 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]]])
    with pytest.raises(InputError, match=r"K\[0\] holds NaN or inf"):
        check_intrinsics(K, 8, 6)


@pytest.mark.parametrize("bottom", [[5.0, 5.0, 0.0], [0.0, 0.0, 2.0], [0.0, 1.0, 1.0]])
def test_depth_frames_reject_a_k_whose_bottom_row_is_not_0_0_1(bottom):
    from neuralsurf.structures import DepthFrames

    depth, K, pose = _depth_frame_inputs()
    K[2] = torch.tensor(bottom)
    with pytest.raises(InputError, match=r"bottom row .* not \[0, 0, 1\]"):
        DepthFrames(depth, K, pose)


@pytest.mark.parametrize("as_numpy", [False, True])
def test_depth_frames_reject_complex_depth_without_a_cast_warning(as_numpy):
    import warnings

    from neuralsurf.structures import DepthFrames

    depth, K, pose = _depth_frame_inputs()
    complex_depth = depth.to(torch.complex64) + 0.5j
    if as_numpy:
        complex_depth = complex_depth.numpy()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # torch's "casting complex values discards the imaginary part" is not enough
        with pytest.raises(InputError, match="DepthFrames.depth is complex.*real"):
            DepthFrames(complex_depth, K, pose)
