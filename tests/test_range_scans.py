"""Stanford range scans: .conf alignment, range-grid triangulation, scanner-facing normals."""

import math
import warnings

import numpy as np
import pytest
import torch

from neuralsurf.cameras import quaternion_to_matrix
from neuralsurf.errors import FileFormatError, NeuralsurfError
from neuralsurf.geometry import knn, point_to_mesh_distance
from neuralsurf.io import read_mesh, read_range_scan, read_range_scan_conf, read_range_scans
from neuralsurf.io.range_scans import conf_transform, triangulate_range_grid


def write_range_grid_ply(path, points, grid):
    """ASCII Cyberware-style PLY: vertices then a row-major range_grid (grid: rows x cols, -1 = empty)."""
    rows, cols = grid.shape
    lines = ["ply", "format ascii 1.0", "obj_info is_cyberware_data 1", f"obj_info num_cols {cols}",
             f"obj_info num_rows {rows}", f"element vertex {len(points)}", "property float x",
             "property float y", "property float z", f"element range_grid {rows * cols}",
             "property list uchar int vertex_indices", "end_header"]  # fmt: skip
    lines += [" ".join(f"{c:.7g}" for c in p) for p in points]
    lines += ["0" if i < 0 else f"1 {i}" for i in grid.ravel()]
    path.write_text("\n".join(lines) + "\n")


def tilted_grid_scan(rows=6, cols=7, slope=0.5, hole=(2, 3)):
    """A range grid on the plane z = slope * x (spacing 1 mm, one empty cell) and its grid."""
    grid = -np.ones((rows, cols), dtype=np.int64)
    points = []
    for r in range(rows):
        for c in range(cols):
            if (r, c) != hole:
                grid[r, c] = len(points)
                x, y = 0.001 * c, -0.001 * r  # rows go down the scanner's image
                points.append((x, y, slope * x))
    return np.array(points), grid


# ---------------------------------------------------------------------------------------------
# real data: the Stanford bunny


def test_bunny_scans_align_with_the_reconstruction(shared_data, record_property):
    folder = shared_data / "stanford_bunny"
    clouds = read_range_scans(folder / "data" / "bun.conf")
    mesh = read_mesh(folder / "reconstruction" / "bun_zipper.ply")
    assert len(clouds) == 10 and sum(len(c) for c in clouds) == 362_272
    points = torch.cat([c.points for c in clouds]).double()
    distance = point_to_mesh_distance(points, mesh)
    median = float(distance.median())
    per_scan = [float(d.median()) for d in distance.split([len(c) for c in clouds])]
    print(f"bunny: median point-to-mesh distance {median * 1e3:.3f} mm; per scan (mm) "
          + ", ".join(f"{d * 1e3:.3f}" for d in per_scan))  # fmt: skip
    record_property("bunny_median_point_to_mesh_mm", median * 1e3)
    assert median < 1e-3 and max(per_scan) < 1e-3
    # to the nearest mesh *vertex* (the repository's "about half a millimetre", set by vertex spacing)
    vertex_median = float(knn(points, mesh.vertices.double())[0].median())
    print(f"bunny: median distance to the nearest reconstruction vertex {vertex_median * 1e3:.3f} mm")
    assert 2e-4 < vertex_median < 1e-3
    # the other reading of the quaternion (R(q) instead of R(q)^T) misplaces a turned scan by centimetres
    raw = read_range_scan(folder / "data" / "bun045.ply", with_normals=False).points.double()
    transform = dict(read_range_scan_conf(folder / "data" / "bun.conf"))["bun045.ply"]
    assert torch.allclose(
        raw @ transform[:3, :3].T + transform[:3, 3], points[len(clouds[0]) : len(clouds[0]) + len(raw)]
    )
    wrong = transform[:3, :3].T
    assert float(point_to_mesh_distance(raw @ wrong.T + transform[:3, 3], mesh).median()) > 5e-3
    # normals face the scanner, hence outward: they agree with the reconstruction's face normals
    o3d = pytest.importorskip("open3d")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.float().numpy()),
        o3d.core.Tensor(mesh.faces.int().numpy().astype(np.uint32)),
    )
    sample = points[::20].float().numpy()
    face = scene.compute_closest_points(o3d.core.Tensor(sample))["primitive_ids"].numpy()
    cosine = (mesh.face_normals()[face] * torch.cat([c.normals for c in clouds])[::20]).sum(1)
    agree = float((cosine > 0).float().mean())
    print(f"bunny: normals agree with the reconstruction's for {agree:.2%} of points")
    assert (cosine > 0).float().mean() > 0.99 and cosine.median() > 0.95


def test_bunny_conf_lists_the_ten_scans(shared_data):
    scans = read_range_scan_conf(shared_data / "stanford_bunny" / "data" / "bun.conf")
    assert [name for name, _ in scans][:3] == ["bun000.ply", "bun045.ply", "bun090.ply"]
    assert torch.equal(scans[0][1], torch.eye(4, dtype=torch.float64))  # bun000 defines the frame
    rotation = scans[2][1][:3, :3]  # bun090: a quarter turn about +y
    assert torch.allclose(rotation.T @ rotation, torch.eye(3, dtype=torch.float64), atol=1e-9)
    assert abs(math.degrees(math.acos((float(rotation.trace()) - 1) / 2)) - 90) < 0.5


# ---------------------------------------------------------------------------------------------
# .conf parsing


def test_conf_quaternion_order_and_direction(tmp_path):
    s = math.sqrt(0.5)
    conf = tmp_path / "scans.conf"
    conf.write_text(
        "# a comment\ncamera 0 0 -1 0 0 0 1\n\nbmesh a.ply 0 0 0 0 0 0 1\n"
        f"bmesh b.ply 1 2 3 0 0 {s} {s}\n"  # qk, qr: a quarter turn about z
    )
    (name_a, a), (name_b, b) = read_range_scan_conf(conf)
    assert (name_a, name_b) == ("a.ply", "b.ply")
    assert torch.equal(a, torch.eye(4, dtype=torch.float64))
    # scan -> world is R(q)^T p + t: the scan's +x lands on world -y, then moves by t
    assert torch.allclose(
        b @ torch.tensor([1.0, 0, 0, 1], dtype=torch.float64),
        torch.tensor([1.0, 1, 3, 1], dtype=torch.float64),
    )
    assert np.allclose(quaternion_to_matrix([0, 0, s, s]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert np.allclose(
        conf_transform([0, 0, 0], [0, 0, 2 * s, 2 * s])[:3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]]
    )


@pytest.mark.parametrize(
    "line, match",
    [
        ("bmesh a.ply 0 0 0 0 0 1", "line 2: cannot parse"),  # 6 numbers
        ("bmesh a.ply 0 0 zero 0 0 0 1", "line 2: cannot parse"),
        ("bmesh 0 0 0 0 0 0 1", "line 2: cannot parse"),  # no file name
        ("scan a.ply 0 0 0 0 0 0 1", "line 2: unknown keyword 'scan'"),
        ("bmesh a.ply 0 0 0 0 0 0 0", "line 2: the quaternion is zero"),
    ],
)
def test_conf_errors_name_the_line(tmp_path, line, match):
    conf = tmp_path / "bad.conf"
    conf.write_text(f"camera 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(FileFormatError, match=match):
        read_range_scan_conf(conf)


def test_missing_files(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        read_range_scans(tmp_path / "nothing.conf")
    (tmp_path / "empty.conf").write_text("camera 0 0 0 0 0 0 1\n")
    with pytest.raises(FileFormatError, match="lists no scans"):
        read_range_scan_conf(tmp_path / "empty.conf")
    (tmp_path / "one.conf").write_text("bmesh missing.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(NeuralsurfError, match="missing.ply"):
        read_range_scans(tmp_path / "one.conf")


# ---------------------------------------------------------------------------------------------
# scans: triangles and normals


def test_range_grid_triangles_share_one_winding_and_skip_holes_and_jumps():
    points, grid = tilted_grid_scan()
    triangles = triangulate_range_grid(grid, points)
    # 5 x 6 quads: 4 touch the hole and give 1 triangle each, the 26 others give 2
    assert len(triangles) == 26 * 2 + 4
    corners = points[triangles]
    cross_z = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])[:, 2]
    assert (np.sign(cross_z) == np.sign(cross_z[0])).all()
    jumped = points.copy()
    jumped[grid[0, 0], 2] += 0.05  # a spike: the quad at the corner would have a 5 cm edge
    assert len(triangulate_range_grid(grid, jumped)) == len(triangles) - 1


def test_scan_normals_face_the_scanner_and_follow_the_conf(tmp_path):
    points, grid = tilted_grid_scan(slope=0.5)
    write_range_grid_ply(tmp_path / "plane.ply", points, grid)
    expected = np.array([-0.5, 0.0, 1.0]) / math.sqrt(1.25)  # plane z = x / 2, towards +z
    scan = read_range_scan(tmp_path / "plane.ply")
    assert len(scan) == len(points)
    assert np.allclose(scan.normals.numpy(), expected, atol=1e-5)
    # rotated into the world with the points
    s = math.sqrt(0.5)
    (tmp_path / "plane.conf").write_text(f"bmesh plane.ply 0.1 0 0 {s} 0 0 {s}\n")  # about x
    (aligned,) = read_range_scans(tmp_path / "plane.conf")
    transform = read_range_scan_conf(tmp_path / "plane.conf")[0][1].float()
    assert torch.allclose(aligned.points, scan.points @ transform[:3, :3].T + transform[:3, 3], atol=1e-6)
    assert torch.allclose(aligned.normals, scan.normals @ transform[:3, :3].T, atol=1e-6)


def test_faces_are_flipped_towards_the_scanner_and_loose_points_get_pca_normals(tmp_path):
    points, grid = tilted_grid_scan(slope=0.0, hole=(-1, -1))
    faces = triangulate_range_grid(grid, points)[:, ::-1]  # wound away from the scanner
    lines = ["ply", "format ascii 1.0", f"element vertex {len(points) + 3}", "property float x",
             "property float y", "property float z", f"element face {len(faces)}",
             "property list uchar int vertex_indices", "end_header"]  # fmt: skip
    lonely = [(0.1, 0.0, 0.0), (0.1, 0.001, 0.0), (0.101, 0.0, 0.0)]  # far from the sheet, no triangle
    lines += [" ".join(f"{c:.7g}" for c in p) for p in [*points, *lonely]]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    (tmp_path / "faces.ply").write_text("\n".join(lines) + "\n")
    scan = read_range_scan(tmp_path / "faces.ply")
    assert torch.allclose(scan.normals, torch.tensor([0.0, 0.0, 1.0]).expand(len(scan), 3), atol=1e-5)
    # without triangles every normal is estimated and still faces +z
    header = [
        f"element vertex {len(points)}" if line.startswith("element vertex") else line for line in lines[:6]
    ]
    (tmp_path / "cloud.ply").write_text(
        "\n".join(header + ["end_header"] + lines[9 : 9 + len(points)]) + "\n"
    )
    assert torch.allclose(
        read_range_scan(tmp_path / "cloud.ply").normals[:, 2], torch.ones(len(points)), atol=1e-5
    )
    assert read_range_scan(tmp_path / "cloud.ply", with_normals=False).normals is None


def test_corrupt_range_grid(tmp_path):
    points, grid = tilted_grid_scan()
    write_range_grid_ply(tmp_path / "scan.ply", points, grid)
    text = (tmp_path / "scan.ply").read_text()
    (tmp_path / "bad_index.ply").write_text(text.replace("\n1 0\n", f"\n1 {len(points) + 5}\n", 1))
    with pytest.raises(FileFormatError, match="bad_index.ply.*outside"):
        read_range_scan(tmp_path / "bad_index.ply")
    (tmp_path / "bad_shape.ply").write_text(text.replace("obj_info num_rows 6", "obj_info num_rows 5"))
    with pytest.raises(FileFormatError, match="5 rows x 7 cols"):
        read_range_scan(tmp_path / "bad_shape.ply")


def test_scan_frames_back_project_onto_the_reconstruction(shared_data):
    """Each scan rendered as a depth image from its scanner's side: its pixels back-project (through
    the frame's pose into the .conf frame) onto bun_zipper.ply, as the raw scan points do."""
    from neuralsurf.cameras import depth_to_cloud
    from neuralsurf.io import read_range_scan_frames

    folder = shared_data / "stanford_bunny"
    frames = read_range_scan_frames(folder / "data" / "bun.conf", pixel_size=5e-4)
    assert len(frames) == 10 and frames.height == frames.width
    assert ((frames.depth > 0).flatten(1).sum(1) > 30_000).all()  # every scan is seen
    cloud = depth_to_cloud(frames, with_normals=False)
    distance = point_to_mesh_distance(cloud.points.double(), read_mesh(folder / "reconstruction" / "bun_zipper.ply"))
    assert float(distance.median()) < 1e-4  # 0.055 mm at 0.25 mm pixels


def test_scan_frames_need_triangles_and_positive_sizes(tmp_path):
    points, _ = tilted_grid_scan()
    (tmp_path / "scan.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        % len(points) + "\n".join(" ".join(map(str, p)) for p in points) + "\n")
    (tmp_path / "a.conf").write_text("bmesh scan.ply 0 0 0 0 0 0 1\n")
    from neuralsurf.io import read_range_scan_frames

    with pytest.raises(FileFormatError, match="no triangles"):
        read_range_scan_frames(tmp_path / "a.conf")
    with pytest.raises(NeuralsurfError, match="pixel_size"):
        read_range_scan_frames(tmp_path / "a.conf", pixel_size=0)


# ---------------------------------------------------------------------------------------------
# .conf `mesh` lines (a reference mesh, optional) and quaternions


def _tetrahedron():
    from neuralsurf.structures import Mesh

    vertices = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    return Mesh(vertices, torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


def test_conf_mesh_lines_are_read_into_the_common_frame(tmp_path):
    from neuralsurf.io import read_range_scan_meshes, write_mesh

    s = math.sqrt(0.5)
    points, grid = tilted_grid_scan()
    write_range_grid_ply(tmp_path / "scan.ply", points, grid)
    write_mesh(tmp_path / "reference.ply", _tetrahedron())
    conf = tmp_path / "scans.conf"
    conf.write_text(f"camera 0 0 -1 0 0 0 1\nbmesh scan.ply 0 0 0 0 0 0 1\nmesh reference.ply 1 2 3 0 0 {s} {s}\n")
    assert [name for name, _ in read_range_scan_conf(conf)] == ["scan.ply"]  # the mesh is not a scan
    assert len(read_range_scans(conf)) == 1
    (mesh,) = read_range_scan_meshes(conf)
    # the bmesh convention: world = R(q)^T p + t, a quarter turn about z then (1, 2, 3)
    expected = _tetrahedron().vertices @ torch.tensor([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]], dtype=torch.float64).T
    assert torch.allclose(mesh.vertices.double(), expected + torch.tensor([1.0, 2, 3], dtype=torch.float64))
    assert torch.equal(mesh.faces, _tetrahedron().faces)


def test_an_absent_reference_mesh_warns_and_the_scans_still_load(tmp_path):
    from neuralsurf.io import read_range_scan_meshes

    points, grid = tilted_grid_scan()
    write_range_grid_ply(tmp_path / "scan.ply", points, grid)
    conf = tmp_path / "scans.conf"
    conf.write_text("bmesh scan.ply 0 0 0 0 0 0 1\nmesh zipper.ply 0 0 0 0 0 0 1\n")
    with pytest.warns(UserWarning, match=r"line 2 lists the reference mesh 'zipper.ply', which is not in"):
        clouds = read_range_scans(conf)
    assert len(clouds) == 1 and len(clouds[0]) == len(points)
    with pytest.warns(UserWarning, match="zipper.ply"):
        assert read_range_scan_meshes(conf) == []


@pytest.mark.parametrize(
    "line, match",
    [("mesh 0 0 0 0 0 0 1", "line 2: cannot parse"), ("mesh m.ply 0 0 0 0 0 0 0", "line 2: the quaternion is zero")],
)
def test_malformed_conf_mesh_lines_name_the_line(tmp_path, line, match):
    conf = tmp_path / "bad.conf"
    conf.write_text(f"bmesh a.ply 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(FileFormatError, match=match):
        read_range_scan_conf(conf)


def test_quaternion_to_matrix_matches_the_hamilton_formula():
    """scipy's Rotation against the textbook matrix of a unit (x, y, z, w) quaternion, and it normalises."""
    rng = np.random.default_rng(0)
    for q in rng.normal(size=(20, 4)) * rng.uniform(0.1, 10, size=(20, 1)):
        x, y, z, w = q / np.linalg.norm(q)
        reference = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])  # fmt: skip
        assert np.allclose(quaternion_to_matrix(q), reference, atol=1e-12)


def test_binary_range_grid_scans_are_triangulated_like_ascii_ones(tmp_path):
    """plyfile reads the range_grid lists of binary scans, which were skipped (PCA normals) before."""
    points, grid = tilted_grid_scan()
    write_range_grid_ply(tmp_path / "ascii.ply", points, grid)
    rows, cols = grid.shape
    header = (
        f"ply\nformat binary_little_endian 1.0\nobj_info num_cols {cols}\nobj_info num_rows {rows}\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element range_grid {rows * cols}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    cells = b"".join(b"\x00" if i < 0 else b"\x01" + np.array([i], "<i4").tobytes() for i in grid.ravel())
    (tmp_path / "binary.ply").write_bytes(header + points.astype("<f4").tobytes() + cells)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "binary range_grid not read" warning any more
        binary = read_range_scan(tmp_path / "binary.ply")
    ascii_ = read_range_scan(tmp_path / "ascii.ply")
    assert torch.equal(binary.points, ascii_.points)
    torch.testing.assert_close(binary.normals, ascii_.normals)
    expected = torch.tensor([-0.5, 0.0, 1.0]) / math.sqrt(1.25)  # the plane z = 0.5 x, facing +z
    torch.testing.assert_close(binary.normals, expected.expand_as(binary.normals), atol=1e-5, rtol=0)
