"""Round-trips and failure modes of neuralsurf.io (point clouds and meshes)."""

from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from neuralsurf.errors import FileFormatError, InputError, NeuralsurfError
from neuralsurf.geometry import merge_duplicate_vertices
from neuralsurf.io import (
    MESH_EXTENSIONS,
    POINT_CLOUD_EXTENSIONS,
    read_mesh,
    read_point_cloud,
    write_mesh,
    write_point_cloud,
)
from neuralsurf.structures import Mesh, PointCloud

# ---------------------------------------------------------------------------------------------
# helpers


def random_cloud(n=200, dtype=torch.float32, normals=True, colors=False, seed=0) -> PointCloud:
    g = torch.Generator().manual_seed(seed)
    points = (torch.randn(n, 3, generator=g, dtype=torch.float64) * 10).to(dtype)
    unit = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    rgb = torch.randint(0, 256, (n, 3), generator=g).double() / 255  # on the 8-bit grid
    return PointCloud(points, unit.to(dtype) if normals else None, rgb.to(dtype) if colors else None)


def icosphere(dtype=torch.float64, colors=False) -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=2)
    vertices = torch.as_tensor(sphere.vertices) * 1.2345678901234567 + torch.tensor([0.1, -2.0, 3.3])
    rgb = None
    if colors:
        g = torch.Generator().manual_seed(1)
        rgb = torch.randint(0, 256, (len(vertices), 3), generator=g).double() / 255
    return Mesh(vertices.to(dtype), torch.as_tensor(sphere.faces), rgb)


def signed_volume(mesh: Mesh) -> float:
    """Sum of signed tetrahedra: positive iff the faces are oriented outwards."""
    a, b, c = mesh.vertices.double()[mesh.faces].unbind(1)
    return float((a * torch.linalg.cross(b, c, dim=-1)).sum() / 6)


def triangles(mesh: Mesh) -> torch.Tensor:
    """(f, 3, 3) corner positions: independent of vertex order."""
    return mesh.vertices.double()[mesh.faces]


def ply_header(fmt: str, properties: list[str], count: int, extra: str = "") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {count}", *properties]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


# ---------------------------------------------------------------------------------------------
# point clouds: round-trips


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("with_normals", [True, False])
@pytest.mark.parametrize("ext", POINT_CLOUD_EXTENSIONS)
def test_point_cloud_round_trip(tmp_path, ext, with_normals, dtype):
    cloud = random_cloud(dtype=dtype, normals=with_normals)
    path = tmp_path / f"cloud{ext}"
    write_point_cloud(path, cloud)
    back = read_point_cloud(path)

    assert back.has_normals == with_normals
    assert back.colors is None
    if ext in (".npy", ".ply"):  # exact, dtype kept
        assert back.points.dtype == dtype
        assert torch.equal(back.points, cloud.points)
        if with_normals:
            assert torch.equal(back.normals, cloud.normals)
    elif ext == ".xyz":  # text: parsed as float64, exact after casting back
        assert back.points.dtype == torch.float64
        assert torch.equal(back.points.to(dtype), cloud.points)
        if with_normals:
            assert torch.equal(back.normals.to(dtype), cloud.normals)
    else:  # .pcd: Open3D stores float32
        assert back.points.dtype == torch.float32
        assert torch.equal(back.points, cloud.points.float())
        if with_normals:
            assert torch.equal(back.normals, cloud.normals.float())


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_colors_survive_formats_that_store_them(tmp_path, ext):
    cloud = random_cloud(colors=True)
    write_point_cloud(tmp_path / f"c{ext}", cloud)
    back = read_point_cloud(tmp_path / f"c{ext}")
    assert back.colors is not None and back.normals is not None
    torch.testing.assert_close(back.colors, cloud.colors, rtol=0, atol=1e-6)
    torch.testing.assert_close(back.normals, cloud.normals, rtol=0, atol=0)


def test_off_grid_colors_are_quantised_to_8_bit(tmp_path):
    cloud = PointCloud(torch.zeros(2, 3), colors=torch.tensor([[0.1234, 0.5, 0.9999], [0.0, 1.0, 0.3]]))
    write_point_cloud(tmp_path / "c.ply", cloud)
    back = read_point_cloud(tmp_path / "c.ply")
    assert (back.colors - cloud.colors).abs().max() <= 0.5 / 255 + 1e-7


@pytest.mark.parametrize("ext", [".xyz", ".npy"])
def test_dropping_colors_warns(tmp_path, ext):
    with pytest.warns(UserWarning, match="colours"):
        write_point_cloud(tmp_path / f"c{ext}", random_cloud(colors=True))
    assert read_point_cloud(tmp_path / f"c{ext}").colors is None


def test_out_of_range_colors_warn_when_clipped(tmp_path):
    cloud = PointCloud(torch.zeros(1, 3), colors=torch.tensor([[1.5, -0.2, 0.5]]))
    with pytest.warns(UserWarning, match="clipped"):
        write_point_cloud(tmp_path / "c.ply", cloud)
    back = read_point_cloud(tmp_path / "c.ply")
    torch.testing.assert_close(back.colors, torch.tensor([[1.0, 0.0, 128 / 255]]))


def test_ascii_ply_with_colors_faces_and_extra_properties(tmp_path):
    header = ply_header(
        "ascii",
        ["property float x", "property float y", "property float z",
         "property float nx", "property float ny", "property float nz",
         "property uchar red", "property uchar green", "property uchar blue", "property uchar alpha"],
        count=3,
        extra="element face 1\nproperty list uchar int vertex_indices\n",
    )  # fmt: skip
    body = b"0 0 0 0 0 1 255 0 0 255\n1.5 0 0 0 0 1 0 255 0 255\n0 2.25 0 0 0 1 0 0 51 10\n3 0 1 2\n"
    (tmp_path / "a.ply").write_bytes(header + body)
    with pytest.warns(UserWarning, match="alpha"), pytest.warns(UserWarning, match="face"):
        cloud = read_point_cloud(tmp_path / "a.ply")
    assert cloud.points.dtype == torch.float32
    torch.testing.assert_close(cloud.points, torch.tensor([[0, 0, 0], [1.5, 0, 0], [0, 2.25, 0]]))
    torch.testing.assert_close(cloud.normals, torch.tensor([[0.0, 0, 1]]).expand(3, 3))
    torch.testing.assert_close(cloud.colors, torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 0.2]]))


def test_big_endian_float64_ply_keeps_float64(tmp_path):
    points = np.random.default_rng(0).normal(size=(5, 3))
    table = np.empty(5, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8")])
    table["x"], table["y"], table["z"] = points.T
    header = ply_header("binary_big_endian", [f"property double {a}" for a in "xyz"], count=5)
    (tmp_path / "b.ply").write_bytes(header + table.tobytes())
    cloud = read_point_cloud(tmp_path / "b.ply")
    assert cloud.points.dtype == torch.float64
    assert np.array_equal(cloud.points.numpy(), points)


def test_xyz_with_comments(tmp_path):
    (tmp_path / "c.xyz").write_text("# scanner export\n1 2 3\n  4 5 6   # trailing comment\n\n7 8 9\n")
    cloud = read_point_cloud(tmp_path / "c.xyz")
    assert cloud.points.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert cloud.normals is None


def test_pcd_float64_fields_keep_float64(tmp_path):
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 8 8 8 4\nTYPE F F F F\n"
        "COUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
    )
    (tmp_path / "d.pcd").write_text(header + "0.1234567890123456 2 3 7\n4 5 6 8\n")
    with pytest.warns(UserWarning, match="intensity"):
        cloud = read_point_cloud(tmp_path / "d.pcd")
    assert cloud.points.dtype == torch.float64
    assert cloud.points[0, 0].item() == 0.1234567890123456


def test_extension_is_case_insensitive_and_parents_are_created(tmp_path):
    path = tmp_path / "new" / "deeper" / "CLOUD.NPY"
    cloud = random_cloud()
    write_point_cloud(path, cloud)
    assert path.is_file() and not path.with_name("CLOUD.NPY.npy").exists()
    assert torch.equal(read_point_cloud(str(path)).points, cloud.points)


# ---------------------------------------------------------------------------------------------
# point clouds: failures


def test_missing_point_cloud_file_names_the_path(tmp_path):
    with pytest.raises(FileFormatError, match="not found.*nowhere.ply"):
        read_point_cloud(tmp_path / "nowhere.ply")


@pytest.mark.parametrize("call", [read_point_cloud, lambda p: write_point_cloud(p, random_cloud())])
def test_unknown_point_cloud_extension_lists_supported(tmp_path, call):
    (tmp_path / "cloud.las").write_bytes(b"x")
    with pytest.raises(FileFormatError, match=r"\.las.*\.ply, \.xyz, \.npy, \.pcd"):
        call(tmp_path / "cloud.las")


@pytest.mark.parametrize(
    ("name", "data", "reason"),
    [
        ("t.ply", ply_header("binary_little_endian", [f"property float {a}" for a in "xyz"], 3) + bytes(20),
         "truncated"),
        ("n.ply", b"not a ply file at all", "start with 'ply'"),
        ("h.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
        ("r.xyz", b"0 0 0\n1 1\n", "columns"),
        ("w.xyz", b"a b c\n", "convert"),
        ("k.xyz", b"1 2 3 4\n", "4 columns"),
        ("g.npy", b"garbage", "NUMPY header"),
        ("g.pcd", b"hello\n", "PCD header lacks"),
    ],
)  # fmt: skip
def test_corrupt_point_cloud_files_raise_file_format_error(tmp_path, name, data, reason):
    (tmp_path / name).write_bytes(data)
    with pytest.raises(FileFormatError, match=reason):
        read_point_cloud(tmp_path / name)


def test_wrong_npy_shape_and_truncated_pcd(tmp_path):
    np.save(tmp_path / "s.npy", np.zeros((4, 4)))
    with pytest.raises(FileFormatError, match=r"shape \(n, 3\)"):
        read_point_cloud(tmp_path / "s.npy")
    write_point_cloud(tmp_path / "t.pcd", random_cloud())
    data = (tmp_path / "t.pcd").read_bytes()
    (tmp_path / "t.pcd").write_bytes(data[:-50])
    with pytest.raises(FileFormatError, match="truncated"):
        read_point_cloud(tmp_path / "t.pcd")


@pytest.mark.parametrize(
    ("name", "data"),
    [
        ("e.xyz", b"# only a comment\n"),
        ("e.ply", ply_header("ascii", [f"property float {a}" for a in "xyz"], 0)),
        ("e.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\n"
                  b"HEIGHT 1\nPOINTS 0\nDATA ascii\n"),
    ],
)  # fmt: skip
def test_file_with_zero_points_raises_input_error(tmp_path, name, data):
    (tmp_path / name).write_bytes(data)
    with pytest.raises(InputError, match="no points") as info:
        read_point_cloud(tmp_path / name)
    assert type(info.value) is InputError  # not a format problem: the file is valid but empty


def test_empty_npy_raises_input_error(tmp_path):
    np.save(tmp_path / "e.npy", np.zeros((0, 3)))
    with pytest.raises(InputError, match="no points"):
        read_point_cloud(tmp_path / "e.npy")


@pytest.mark.parametrize("ext", [".xyz", ".npy", ".ply"])
def test_non_finite_coordinates_name_the_file(tmp_path, ext):
    points = np.array([[0.0, 0, 0], [np.nan, 1, 1], [2, np.inf, 2]])
    path = tmp_path / f"bad{ext}"
    if ext == ".xyz":
        np.savetxt(path, points)
    elif ext == ".npy":
        np.save(path, points)
    else:
        header = ply_header("binary_little_endian", [f"property double {a}" for a in "xyz"], 3)
        path.write_bytes(header + points.astype("<f8").tobytes())
    with pytest.raises(InputError, match=rf"bad\{ext}.*NaN or inf \(2 rows\)"):
        read_point_cloud(path)


def test_write_point_cloud_rejects_other_types(tmp_path):
    with pytest.raises(InputError, match="needs a PointCloud"):
        write_point_cloud(tmp_path / "c.ply", np.zeros((3, 3)))


# ---------------------------------------------------------------------------------------------
# meshes: round-trips


@pytest.mark.parametrize("ext", MESH_EXTENSIONS)
def test_mesh_round_trip(tmp_path, ext):
    mesh = icosphere()
    write_mesh(tmp_path / f"m{ext}", mesh)
    back = read_mesh(tmp_path / f"m{ext}")

    assert back.vertices.dtype == torch.float64
    assert back.vertices.shape == mesh.vertices.shape and back.faces.shape == mesh.faces.shape
    assert back.is_watertight
    exact = ext in (".ply", ".obj", ".off")  # .stl and .glb store float32
    torch.testing.assert_close(triangles(back), triangles(mesh), rtol=0, atol=0 if exact else 1e-6)
    if ext != ".stl":  # .stl is a triangle soup: vertex order is that of first use
        assert torch.equal(back.faces, mesh.faces)
    assert signed_volume(back) == pytest.approx(signed_volume(mesh), rel=1e-6)
    assert signed_volume(back) > 0  # faces still point outwards


@pytest.mark.parametrize("ext", [".ply", ".obj", ".glb"])
def test_mesh_vertex_colors_survive(tmp_path, ext):
    mesh = icosphere(colors=True)
    write_mesh(tmp_path / f"m{ext}", mesh)
    back = read_mesh(tmp_path / f"m{ext}")
    assert back.vertex_colors is not None
    torch.testing.assert_close(back.vertex_colors, mesh.vertex_colors, rtol=0, atol=1e-6)


@pytest.mark.parametrize("ext", [".off", ".stl"])
def test_mesh_vertex_colors_dropped_with_warning(tmp_path, ext):
    with pytest.warns(UserWarning, match="vertex colours"):
        write_mesh(tmp_path / f"m{ext}", icosphere(colors=True))
    assert read_mesh(tmp_path / f"m{ext}").vertex_colors is None


def test_float32_mesh_round_trips_exactly_through_text(tmp_path):
    mesh = icosphere(dtype=torch.float32)
    for ext in (".obj", ".off", ".ply"):
        write_mesh(tmp_path / f"m{ext}", mesh)
        assert torch.equal(read_mesh(tmp_path / f"m{ext}").vertices.float(), mesh.vertices), ext


def test_glb_scene_is_concatenated_with_transforms_and_orientation(tmp_path):
    scene = trimesh.Scene()
    box = trimesh.creation.box(extents=(1, 1, 1))
    scene.add_geometry(box, node_name="a", transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])  # flips winding: the loader must flip the faces back
    scene.add_geometry(box, node_name="b", transform=mirror)
    (tmp_path / "s.glb").write_bytes(scene.export(file_type="glb"))
    mesh = read_mesh(tmp_path / "s.glb")
    assert len(mesh.faces) == 2 * len(box.faces)
    torch.testing.assert_close(mesh.bounds, torch.tensor([[-0.5, -0.5, -0.5], [5.5, 0.5, 0.5]]).double())
    assert signed_volume(mesh) == pytest.approx(2.0)
    assert mesh.is_watertight


def test_obj_with_texture_seams_is_merged_watertight(tmp_path):
    # a tetrahedron whose faces use different UVs at shared vertices: trimesh splits them
    obj = (
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
        "vt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\n"
        "f 1/1 3/2 2/3\nf 1/4 2/1 4/2\nf 1/3 4/4 3/1\nf 2/2 3/3 4/4\n"
    )
    (tmp_path / "t.obj").write_text(obj)
    with pytest.warns(UserWarning, match="texture"):
        mesh = read_mesh(tmp_path / "t.obj")
    assert mesh.vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    assert mesh.is_watertight
    assert signed_volume(mesh) == pytest.approx(1 / 6)


def test_merge_duplicate_vertices_against_reference():
    soup = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 1],
                     [0, 0, 0], [0, 0, 1], [0, 1, 0], [1, 0, 0], [0, 1, 0], [-0.0, 0, 1]], float)  # fmt: skip
    faces = np.arange(12).reshape(4, 3)
    vertices, merged, _ = merge_duplicate_vertices(soup, faces)
    assert vertices.tolist() == [[0, 0, 0], [0, 1, 0], [1, 0, 0], [0, 0, 1]]  # first-use order
    assert np.array_equal(vertices[merged], soup[faces])  # same triangles, same winding
    colors = np.linspace(0, 1, 36).reshape(12, 3)  # distinct colours: nothing may merge
    assert len(merge_duplicate_vertices(soup, faces, colors)[0]) == 12


def test_bunny_obj_loads_watertight_with_file_counts():
    spec = find_spec("pymeshlab")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("pymeshlab (sample bunny) not installed: pip install 'neuralsurf[data]'")
    path = Path(next(iter(spec.submodule_search_locations))) / "tests" / "sample_meshes" / "bunny.obj"
    mesh = read_mesh(path)
    assert mesh.vertices.shape == (28088, 3) and mesh.faces.shape == (56172, 3)
    assert mesh.vertices.dtype == torch.float64
    assert mesh.is_watertight
    assert signed_volume(mesh) > 0
    with path.open() as file:
        first = [float(x) for x in next(line for line in file if line.startswith("v ")).split()[1:]]
    assert mesh.vertices[0].tolist() == first  # file order kept


# ---------------------------------------------------------------------------------------------
# meshes: failures


def test_missing_mesh_file_names_the_path(tmp_path):
    with pytest.raises(FileFormatError, match="not found.*ghost.obj"):
        read_mesh(tmp_path / "ghost.obj")


def test_unknown_mesh_extension_lists_supported(tmp_path):
    with pytest.raises(FileFormatError, match=r"\.3ds.*\.ply, \.obj, \.off, \.stl, \.glb"):
        write_mesh(tmp_path / "m.3ds", icosphere())
    with pytest.raises(FileFormatError, match=r"\.xyz.*\.obj"):
        read_mesh(tmp_path / "m.xyz")


@pytest.mark.parametrize(
    ("name", "data", "reason"),
    [
        ("c.ply", b"garbage that is not a ply", "ply"),
        ("c.glb", bytes(range(200)), "header"),
        ("c.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "out of bounds"),
        ("c.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n", "reshape"),
    ],
)
def test_corrupt_mesh_files_raise_file_format_error(tmp_path, name, data, reason):
    (tmp_path / name).write_bytes(data)
    with pytest.raises(FileFormatError, match=reason):
        read_mesh(tmp_path / name)


def test_mesh_without_triangles_raises_input_error(tmp_path):
    (tmp_path / "e.obj").write_text("# nothing here\n")
    with pytest.raises(InputError, match="no triangles"):
        read_mesh(tmp_path / "e.obj")
    write_point_cloud(tmp_path / "p.ply", random_cloud(normals=False))
    with pytest.raises(InputError, match="read_point_cloud"):
        read_mesh(tmp_path / "p.ply")


def test_non_finite_mesh_vertices_name_the_file(tmp_path):
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match=r"nan\.obj.*NaN"):
        read_mesh(tmp_path / "nan.obj")


def test_every_io_error_is_a_neuralsurf_error(tmp_path):
    for call in (read_mesh, read_point_cloud):
        with pytest.raises(NeuralsurfError):
            call(tmp_path / "missing.ply")


@pytest.mark.parametrize("ext", POINT_CLOUD_EXTENSIONS)
def test_writing_a_point_cloud_under_a_file_names_the_file(tmp_path, ext):
    (tmp_path / "a_file").write_text("not a folder")
    for target in (tmp_path / "a_file" / f"x{ext}", tmp_path / "a_file" / "deeper" / f"x{ext}"):
        with pytest.raises(FileFormatError, match=r"a_file' is a file, not a folder"):
            write_point_cloud(target, random_cloud())
    assert (tmp_path / "a_file").read_text() == "not a folder"  # left as it was


@pytest.mark.parametrize("ext", MESH_EXTENSIONS)
def test_writing_a_mesh_under_a_file_or_onto_a_folder_is_a_file_format_error(tmp_path, ext):
    (tmp_path / "a_file").write_text("not a folder")
    with pytest.raises(FileFormatError, match=r"a_file' is a file, not a folder"):
        write_mesh(tmp_path / "a_file" / f"m{ext}", icosphere())
    (tmp_path / f"folder{ext}").mkdir()
    with pytest.raises(FileFormatError, match=r"it is a folder; pass a file name inside it"):
        write_mesh(tmp_path / f"folder{ext}", icosphere())


# ---------------------------------------------------------------------------------------------
# PLY through plyfile: any element order, list properties before the vertices


def _faces_first_ply(fmt: str) -> bytes:
    """A quad and a triangle (face element first), then 4 float vertices with a uchar colour."""
    header = (
        f"ply\nformat {fmt} 1.0\ncomment faces come first\nelement face 2\n"
        "property list uchar int vertex_indices\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    ).encode()
    points = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], dtype=np.float32)
    if fmt == "ascii":
        body = "4 0 1 2 3\n3 0 1 3\n" + "".join(" ".join(f"{v:g}" for v in p) + " 255 0 51\n" for p in points)
        return header + body.encode()
    faces = np.array([4, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0], dtype=np.uint8).tobytes()
    faces += np.array([3], np.uint8).tobytes() + np.array([0, 1, 3], "<i4").tobytes()
    vertex = np.empty(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "u1", (3,))])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    vertex["rgb"] = [255, 0, 51]
    return header + faces + vertex.tobytes()


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_with_a_list_element_before_the_vertices_is_read(tmp_path, fmt):
    (tmp_path / "f.ply").write_bytes(_faces_first_ply(fmt))
    with pytest.warns(UserWarning, match=r"PLY elements \['face'\] are not kept"):
        cloud = read_point_cloud(tmp_path / "f.ply")
    assert cloud.points.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]]
    torch.testing.assert_close(cloud.colors, torch.tensor([[1.0, 0.0, 0.2]]).expand(4, 3))


def test_written_ply_is_read_by_plyfile_itself(tmp_path):
    plyfile = pytest.importorskip("plyfile")
    mesh = icosphere(colors=True)
    write_mesh(tmp_path / "m.ply", mesh)
    ply = plyfile.PlyData.read(str(tmp_path / "m.ply"))
    assert [e.name for e in ply.elements] == ["vertex", "face"] and not ply.text
    assert np.array_equal(np.stack([ply["vertex"][a] for a in "xyz"], 1), mesh.vertices.numpy())
    assert np.array_equal(np.stack(list(ply["face"]["vertex_indices"])), mesh.faces.numpy())


def test_ply_header_declaring_more_vertices_than_the_file_holds_is_refused_quickly(tmp_path):
    header = ply_header("binary_little_endian", [f"property float {a}" for a in "xyz"], 10**11)
    (tmp_path / "huge.ply").write_bytes(header + bytes(120))
    with pytest.raises(FileFormatError, match=r"huge\.ply.*fewer than the 100000000000 rows of 'vertex'.*truncated"):
        read_point_cloud(tmp_path / "huge.ply")


@pytest.mark.parametrize(
    ("header", "reason"),
    [
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty floot x\nend_header\n", "field type 'floot'"),
        (b"ply\nformat fancy 1.0\nelement vertex 1\nproperty float x\nend_header\n", "format 'fancy'"),
    ],
)
def test_malformed_ply_headers_name_the_file_and_the_line(tmp_path, header, reason):
    (tmp_path / "bad.ply").write_bytes(header + b"0\n")
    with pytest.raises(FileFormatError, match=rf"bad\.ply.*PLY header does not parse: line \d: .*{reason}"):
        read_point_cloud(tmp_path / "bad.ply")


def test_npz_spans_read_rows_in_place_and_refuse_crafted_headers(tmp_path):
    import io
    import zipfile

    from neuralsurf.io.npz import npy_span, npz_spans, write_npz

    points = np.arange(60, dtype=np.float32).reshape(20, 3)
    path = write_npz(tmp_path / "a.npz", {"points": points, "labels": np.arange(20) % 2 == 0})
    spans = npz_spans(path, ("points", "labels"))
    rows = np.array([[3, 0], [19, 3]])
    assert np.array_equal(spans["points"].rows(rows), points[rows])
    assert np.array_equal(spans["labels"].rows(rows), rows % 2 == 0)
    np.save(tmp_path / "b.npy", points)
    assert np.array_equal(npy_span(tmp_path / "b.npy").rows(np.array([5, 1])), points[[5, 1]])

    header = io.BytesIO()  # an array header that claims a million rows over 12 bytes of data
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (10**6, 3)})
    with zipfile.ZipFile(tmp_path / "crafted.npz", "w") as archive:
        archive.writestr("points.npy", header.getvalue() + points[0].tobytes())
    with pytest.raises(FileFormatError, match="declares shape .1000000, 3.* more than its"):
        npz_spans(tmp_path / "crafted.npz", ("points",))
    (tmp_path / "short.npy").write_bytes(header.getvalue() + points[0].tobytes())
    with pytest.raises(FileFormatError, match="truncated"):
        npy_span(tmp_path / "short.npy")
