"""extract: marching cubes of fields against analytic oracles and a single dense skimage call."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from neuralsurf.errors import ConfigError, ExtractionError, InputError
from neuralsurf.extract import (
    extract_mesh,
    field_slice,
    level_set,
    make_grid,
    marching_cubes,
    off_level,
    slice_image,
)
from neuralsurf.scenes.analytic import Box, Sphere, Torus
from neuralsurf.structures import Mesh

UNIT_BOX = torch.tensor([[-0.5] * 3, [0.5] * 3], dtype=torch.float64)
ALIGNED_BOX = Box(half_extents=(0.25, 0.1875, 0.3125))
"""Faces on grid planes at resolutions 64 and 128 in UNIT_BOX: exact zeros at grid points, vertices
rounded onto grid points, the case where blocks cannot be welded by edge and are merged instead."""


def wavy(x: torch.Tensor) -> torch.Tensor:
    """Not an SDF any more, but |grad| <= 1.4: coarse-to-fine must still be exact."""
    return Sphere(center=(0.02, -0.01, 0.03)).sdf(x) + 0.02 * torch.sin(20 * x[..., 0])


FIELDS = {
    "sphere": Sphere(center=(0.05, -0.03, 0.02)).sdf,
    "torus": Torus(center=(0.02, 0.01, -0.03)).sdf,
    "box": Box(center=(0.013, 0.021, -0.017)).sdf,
    "aligned_box": ALIGNED_BOX.sdf,
    "wavy": wavy,
    "two_spheres": lambda x: torch.minimum(
        Sphere((-0.203, 0.001, 0.002), 0.1537).sdf(x), Sphere((0.2213, 0.0471, 0.003), 0.1011).sdf(x)
    ),
}


def signed_volume(mesh: Mesh) -> float:
    a, b, c = mesh.vertices.double()[mesh.faces].unbind(1)
    return float((a * torch.linalg.cross(b, c)).sum() / 6)


def area(mesh: Mesh) -> float:
    return float(mesh.face_areas().double().sum())


def reference_mesh(field, resolution: int, bounds, level: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """The slow, obviously-correct version: every grid point in one batch, one skimage call."""
    from skimage.measure import marching_cubes as skimage_marching_cubes

    grid = make_grid(bounds, resolution)
    index = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1).reshape(-1, 3)
    volume = field(torch.from_numpy(grid.world(index))).numpy().reshape(grid.shape)
    verts, faces, _, _ = skimage_marching_cubes(off_level(torch.from_numpy(volume), level).numpy(), level)
    return grid.origin + verts.astype(np.float64) * grid.spacing, faces.astype(np.int64), grid.spacing


def canonical_faces(faces: np.ndarray) -> np.ndarray:
    """Rotate each triangle to start at its smallest index (orientation kept), then sort rows."""
    first = np.argmin(faces, axis=1)
    rows = np.arange(len(faces))
    rotated = np.stack([faces[rows, (first + i) % 3] for i in range(3)], 1)
    return rotated[np.lexsort(rotated.T[::-1])]


def assert_identical(a: Mesh, b: Mesh) -> None:
    """Same faces; vertices equal up to float32 rounding of the field (batch layout changes the last bit)."""
    assert torch.equal(a.faces, b.faces)
    assert torch.allclose(a.vertices, b.vertices, atol=1e-5, rtol=0)


class Counting:
    """A field that counts the points it is asked about."""

    def __init__(self, field):
        self.field, self.points = field, 0

    def __call__(self, x):
        self.points += x.shape[0]
        return self.field(x)


# ------------------------------------------------------------------------------ accuracy


def test_sphere_area_volume_and_orientation():
    sphere = Sphere(center=(0.05, -0.03, 0.02))
    mesh = extract_mesh(sphere.sdf, 128, UNIT_BOX)
    assert area(mesh) == pytest.approx(sphere.area, rel=0.01)
    assert signed_volume(mesh) == pytest.approx(sphere.volume, rel=0.01)  # > 0: outward faces
    assert mesh.is_watertight
    centroids = mesh.vertices.double()[mesh.faces].mean(1)
    outward = (mesh.face_normals().double() * (centroids - torch.tensor(sphere.center).double())).sum(1)
    assert (outward > 0).all()


def test_torus_area_volume():
    torus = Torus(center=(0.02, 0.01, -0.03))
    mesh = extract_mesh(torus.sdf, 128, UNIT_BOX)
    assert area(mesh) == pytest.approx(torus.area, rel=0.01)
    assert signed_volume(mesh) == pytest.approx(torus.volume, rel=0.01)
    assert mesh.is_watertight


def test_box_area_volume():
    mesh = extract_mesh(ALIGNED_BOX.sdf, 64, UNIT_BOX)  # faces on grid planes: exact
    assert area(mesh) == pytest.approx(ALIGNED_BOX.area, rel=1e-4)
    assert signed_volume(mesh) == pytest.approx(ALIGNED_BOX.volume, rel=1e-4)
    assert mesh.is_watertight
    box = Box(center=(0.013, 0.021, -0.017))  # off the grid: marching cubes bevels the 12 edges by O(h)
    mesh = extract_mesh(box.sdf, 128, UNIT_BOX)
    assert signed_volume(mesh) == pytest.approx(box.volume, rel=0.01)
    assert area(mesh) == pytest.approx(box.area, rel=0.02)
    assert mesh.is_watertight


def test_output_in_world_frame():
    sphere = Sphere(center=(1.0, -2.0, 0.5), radius=0.3)
    bounds = torch.tensor([[0.55, -2.45, 0.1], [1.6, -1.6, 0.95]], dtype=torch.float64)  # not centred
    mesh = extract_mesh(sphere.sdf, 96, bounds)
    spacing = make_grid(bounds, 96).spacing
    radii = (mesh.vertices.double() - torch.tensor(sphere.center, dtype=torch.float64)).norm(dim=1)
    assert (radii - sphere.radius).abs().max() < 0.02 * spacing
    expected = torch.tensor([[0.7, -2.3, 0.2], [1.3, -1.7, 0.8]], dtype=torch.float64)
    assert torch.allclose(mesh.bounds.double(), expected, atol=0.02 * spacing)
    assert mesh.is_watertight and signed_volume(mesh) > 0


FAR = torch.tensor([412_345.0, 5_012_345.0, 100.0], dtype=torch.float64)
"""A georeferenced origin (metres, UTM): float32 rounds coordinates there by up to 0.25."""


@pytest.mark.parametrize("mode", [{"coarse_to_fine": False}, {}, {"sparse": True}])
def test_a_surface_far_from_the_origin_is_extracted_in_float64_as_at_the_origin(mode):
    near = Sphere(center=(0.013, -0.021, 0.017), radius=0.3)
    far = Sphere(center=tuple((FAR + torch.tensor(near.center, dtype=torch.float64)).tolist()), radius=0.3)
    seen = []

    def far_sdf(x):
        seen.append(x.dtype)
        return far.sdf(x)

    expected = extract_mesh(near.sdf, 64, UNIT_BOX, progress=False, **mode)
    mesh = extract_mesh(far_sdf, 64, UNIT_BOX + FAR, progress=False, **mode)
    assert set(seen) == {torch.float64} and mesh.vertices.dtype == torch.float64 and expected.vertices.dtype == torch.float32
    assert mesh.is_watertight and torch.equal(mesh.faces, expected.faces)
    assert torch.allclose(mesh.vertices - FAR, expected.vertices.double(), atol=1e-5)  # float32 rounding near 0
    radii = (mesh.vertices - torch.tensor(far.center, dtype=torch.float64)).norm(dim=1)
    assert (radii - far.radius).abs().max() < 0.02 * make_grid(UNIT_BOX, 64).spacing


def test_level_selects_an_offset_surface(sphere):
    mesh = extract_mesh(sphere.sdf, 96, UNIT_BOX, level=0.05)
    radii = mesh.vertices.double().norm(dim=1)
    assert radii.mean() == pytest.approx(0.35, abs=1e-3)


def test_grid_has_cubic_cells_and_covers_the_bounds():
    bounds = np.array([[0.0, -1.0, 2.0], [2.0, 0.3, 2.5]])
    grid = make_grid(bounds, 50)
    assert grid.cells[0] == 50 and grid.spacing == pytest.approx(0.04)
    low = grid.origin
    high = grid.origin + np.array(grid.cells) * grid.spacing
    assert (low <= bounds[0] + 1e-12).all() and (high >= bounds[1] - 1e-12).all()
    assert ((high - low) - (bounds[1] - bounds[0]) < grid.spacing).all()


# ------------------------------------------------------------ chunked vs one skimage call


@pytest.mark.parametrize("name", ["sphere", "torus", "wavy", "two_spheres"])
def test_chunked_evaluation_matches_one_skimage_call(name):
    field = FIELDS[name]
    verts, faces, spacing = reference_mesh(field, 80, UNIT_BOX)
    mesh = extract_mesh(field, 80, UNIT_BOX, coarse_to_fine=False)
    ours = mesh.vertices.double().numpy()
    assert len(ours) == len(verts) and len(mesh.faces) == len(faces)
    distance, match = cKDTree(verts).query(ours)
    assert distance.max() < 1e-4 * spacing  # float32 positions, 80 cells * 2^-24 ~ 5e-6 cells
    assert len(np.unique(match)) == len(match)
    assert np.array_equal(canonical_faces(match[mesh.faces.numpy()]), canonical_faces(faces))


def test_values_a_hair_from_the_level_still_give_a_closed_mesh():
    """Random signs with a fifth of the grid points 1e-7 from the level (as a fitted field can be):
    their edges' vertices would share a float32 position and pinch the mesh (not watertight before
    `off_level`); strictly signed values always close, and `off_level` keeps every sign."""
    rng = np.random.default_rng(0)
    values = rng.uniform(-1, 1, (24, 24, 24)).astype(np.float32)
    tiny = rng.random(values.shape) < 0.2
    values[tiny] = np.sign(values[tiny]) * 1e-7
    values[[0, -1]], values[:, [0, -1]], values[:, :, [0, -1]] = 1, 1, 1
    moved = off_level(torch.from_numpy(values), 0.0).numpy()
    assert np.array_equal(np.sign(moved), np.sign(values)) and np.abs(moved - values).max() <= 2e-4  # 1e-4 x 2
    assert marching_cubes(values, make_grid(UNIT_BOX.numpy(), 23)).is_watertight


def test_blocks_merge_where_vertices_sit_on_grid_points():
    verts, faces, _ = reference_mesh(ALIGNED_BOX.sdf, 64, UNIT_BOX)
    a, b, c = (torch.from_numpy(verts[faces[:, i]]) for i in range(3))
    reference_area = float(0.5 * torch.linalg.cross(b - a, c - a).norm(dim=1).sum())
    mesh = extract_mesh(ALIGNED_BOX.sdf, 64, UNIT_BOX, coarse_to_fine=False)
    assert area(mesh) == pytest.approx(reference_area, rel=1e-9)
    assert len(faces) > len(mesh.faces) > 0.9 * len(faces)  # zero-area slivers at grid points dropped
    assert (mesh.face_areas() > 0).all()
    assert mesh.is_watertight


@pytest.mark.parametrize("step", [1 / 32, 1 / 40])
def test_quantised_fields_with_many_exact_zeros_stay_watertight(step):
    # plateaus and exact zeros: vertices round onto grid points all over the block faces
    for shape in (Torus(), Box()):
        def field(x, shape=shape):
            return torch.round(shape.sdf(x) / step) * step

        dense = extract_mesh(field, 80, UNIT_BOX, coarse_to_fine=False)
        assert dense.is_watertight
        # rounding to 0 makes |sdf| < step / 2 inside: the shape grows by up to step / 2
        assert shape.volume < signed_volume(dense) < shape.volume + shape.area * step / 2


# ---------------------------------------------------------------------- coarse to fine


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_coarse_to_fine_equals_dense(name):
    field = Counting(FIELDS[name])
    dense = extract_mesh(field, 128, UNIT_BOX, coarse_to_fine=False)
    dense_points, field.points = field.points, 0
    fine = extract_mesh(field, 128, UNIT_BOX, coarse_to_fine=True, coarse_resolution=16)  # 3 levels
    assert_identical(dense, fine)
    assert dense_points == 129**3
    assert field.points < dense_points / 2


def test_coarse_to_fine_equals_dense_on_odd_grids_and_levels():
    sphere = Sphere(center=(0.61, 0.1, -0.05), radius=0.22)
    bounds = torch.tensor([[0.3, -0.2, -0.33], [1.0, 0.38, 0.24]], dtype=torch.float64)
    for resolution, level in ((90, 0.0), (77, 0.03)):  # cells not multiples of the coarse size
        dense = extract_mesh(sphere.sdf, resolution, bounds, level=level, coarse_to_fine=False)
        fine = extract_mesh(sphere.sdf, resolution, bounds, level=level, coarse_resolution=9)
        assert_identical(dense, fine)
        assert dense.is_watertight


def test_margin_bound_is_tight_enough_for_lipschitz_fields():
    # margin m is safe for |grad f| <= 2 m: a 3-Lipschitz field with m = 1.5, a 2-Lipschitz one with the default
    # (1.0), an SDF with m = 0.5
    for slope, margin in ((3.0, {"margin": 1.5}), (2.0, {})):
        def steep(x, slope=slope):
            return slope * FIELDS["torus"](x)

        dense = extract_mesh(steep, 96, UNIT_BOX, coarse_to_fine=False)
        assert_identical(dense, extract_mesh(steep, 96, UNIT_BOX, coarse_resolution=12, **margin))
    dense = extract_mesh(FIELDS["two_spheres"], 96, UNIT_BOX, coarse_to_fine=False)
    fine = extract_mesh(FIELDS["two_spheres"], 96, UNIT_BOX, margin=0.5, coarse_resolution=12)
    assert_identical(dense, fine)


def test_coarse_to_fine_evaluates_a_thin_shell():
    sphere = Sphere(radius=0.35)
    counts = {}
    for margin in (0.5, 2.0):
        field = Counting(sphere.sdf)
        extract_mesh(field, 192, UNIT_BOX, margin=margin, coarse_resolution=24)
        counts[margin] = field.points
    # about 2 * (margin * diagonal + cell) thick: 9% of the grid for margin 0.5, 18% for 2.0
    assert counts[0.5] < 0.1 * 193**3
    assert counts[0.5] < counts[2.0] < 0.2 * 193**3


@pytest.mark.parametrize("name", sorted(set(FIELDS) - {"aligned_box"}))
def test_sparse_coarse_to_fine_gives_the_dense_surface_from_the_same_evaluations(name):
    field = Counting(FIELDS[name])
    fine = extract_mesh(field, 128, UNIT_BOX, coarse_resolution=16)
    fine_points, field.points = field.points, 0
    sparse = extract_mesh(field, 128, UNIT_BOX, coarse_resolution=16, sparse=True)
    assert sparse.is_watertight and len(sparse.faces) == len(fine.faces)
    # ambiguous cells may be split otherwise: area and volume agree to a hair, the volume's sign says outward
    assert area(sparse) == pytest.approx(area(fine), rel=1e-4)
    assert signed_volume(sparse) == pytest.approx(signed_volume(fine), rel=1e-4)
    nearest, _ = cKDTree(fine.vertices.numpy()).query(sparse.vertices.numpy())
    assert nearest.max() < 1e-3 * make_grid(UNIT_BOX, 128).spacing  # the same vertices (bar the level nudge)
    assert field.points <= fine_points  # each shared corner once a block: no more than the dense bookkeeping


def test_sparse_extraction_closes_surfaces_through_grid_points():
    # exact zeros at grid points count as above the level (marching's rule): the faces stay on their grid
    # planes, the box's edges along grid lines are cut by a chamfer one cell wide (2 % of the area at 128)
    dense = extract_mesh(ALIGNED_BOX.sdf, 128, UNIT_BOX, coarse_resolution=16)
    sparse = extract_mesh(ALIGNED_BOX.sdf, 128, UNIT_BOX, coarse_resolution=16, sparse=True)
    assert sparse.is_watertight
    assert area(sparse) == pytest.approx(area(dense), rel=0.03)
    on_dense, _ = cKDTree(dense.vertices.numpy()).query(sparse.vertices.numpy())
    to_sparse, _ = cKDTree(sparse.vertices.numpy()).query(dense.vertices.numpy())
    cell = make_grid(UNIT_BOX, 128).spacing
    assert on_dense.max() < 1e-3 * cell and to_sparse.max() < 1.5 * cell


def test_sparse_extraction_of_odd_grids_levels_and_a_surface_without_any():
    sphere = Sphere(center=(0.61, 0.1, -0.05), radius=0.22)
    bounds = torch.tensor([[0.3, -0.2, -0.33], [1.0, 0.38, 0.24]], dtype=torch.float64)
    for resolution, level in ((90, 0.0), (77, 0.03)):
        dense = extract_mesh(sphere.sdf, resolution, bounds, level=level, coarse_to_fine=False)
        sparse = extract_mesh(sphere.sdf, resolution, bounds, level=level, coarse_resolution=9, sparse=True)
        assert sparse.is_watertight and len(sparse.faces) == len(dense.faces)
        assert area(sparse) == pytest.approx(area(dense), rel=1e-5)
    with pytest.raises(ExtractionError, match="no 0-level set"):
        extract_mesh(lambda x: Sphere(radius=0.1).sdf(x) + 0.2, 128, UNIT_BOX, sparse=True)
    with pytest.warns(UserWarning, match="touches the boundary"):
        extract_mesh(Sphere(radius=0.6).sdf, 64, UNIT_BOX, coarse_resolution=16, sparse=True)


# --------------------------------------------------------------------- inputs and devices


def test_chunk_size_does_not_change_the_result():
    for coarse in (False, True):
        a = extract_mesh(FIELDS["torus"], 64, UNIT_BOX, coarse_to_fine=coarse, coarse_resolution=16)
        b = extract_mesh(FIELDS["torus"], 64, UNIT_BOX, coarse_to_fine=coarse, coarse_resolution=16,
                         chunk_size=7919)
        assert_identical(a, b)


class ModuleField(torch.nn.Module):
    """An nn.Module field with a parameter and a bounds buffer, like the trained models."""

    def __init__(self):
        super().__init__()
        self.radius = torch.nn.Parameter(torch.tensor(0.3))
        bounds = torch.tensor([[-0.5, -0.4, -0.45], [0.6, 0.5, 0.4]], dtype=torch.float64)
        self.register_buffer("bounds", bounds)
        self.calls: list[tuple[torch.dtype, torch.device, bool]] = []

    def forward(self, x):
        self.calls.append((x.dtype, x.device, torch.is_grad_enabled()))
        return x.norm(dim=-1) - self.radius


def test_module_field_uses_its_bounds_device_float32_and_no_grad():
    field = ModuleField()
    mesh = extract_mesh(field, 64)
    assert mesh.is_watertight
    assert signed_volume(mesh) == pytest.approx(4 / 3 * np.pi * 0.3**3, rel=0.01)
    assert field.calls and all(c == (torch.float32, torch.device("cpu"), False) for c in field.calls)


def test_missing_bounds_is_an_input_error():
    with pytest.raises(InputError, match="bounds"):
        extract_mesh(Sphere().sdf, 32)
    with pytest.raises(InputError, match="shape"):
        extract_mesh(Sphere().sdf, 32, bounds=[[0, 0, 0], [1, 1, 1], [2, 2, 2]])
    with pytest.raises(InputError, match="max > min"):
        extract_mesh(Sphere().sdf, 32, bounds=[[0, 0, 0], [1, 0, 1]])
    with pytest.raises(ConfigError, match="resolution"):
        extract_mesh(Sphere().sdf, 1, UNIT_BOX)
    with pytest.raises(ConfigError, match="chunk_size"):
        extract_mesh(Sphere().sdf, 32, UNIT_BOX, chunk_size=0)
    with pytest.raises(InputError, match="one value per point"):
        extract_mesh(lambda x: x, 32, UNIT_BOX)


@pytest.mark.parametrize("coarse", [False, True])
def test_no_surface_reports_the_range(coarse):
    with pytest.raises(ExtractionError, match=r"no 0-level set.*\[0\.\d+, 0\.\d+\].*bounds.*level"):
        extract_mesh(lambda x: Sphere(radius=0.1).sdf(x) + 0.2, 128, UNIT_BOX, coarse_to_fine=coarse)


@pytest.mark.parametrize("coarse", [False, True])
def test_nan_is_an_extraction_error(coarse):
    def broken(x):
        f = Sphere().sdf(x)
        return torch.where(x[..., 0] > 0.3, torch.nan, f)

    with pytest.raises(ExtractionError, match="NaN"):
        extract_mesh(broken, 128, UNIT_BOX, coarse_to_fine=coarse)


def test_open_surface_warns():
    def plane(x):
        return x[..., 2] - 0.1

    with pytest.warns(UserWarning, match="touches the boundary.*not be watertight.*larger bounds"):
        mesh = extract_mesh(plane, 32, UNIT_BOX)
    assert not mesh.is_watertight
    assert area(mesh) == pytest.approx(1.0, rel=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert extract_mesh(Sphere().sdf, 32, UNIT_BOX).is_watertight  # closed: no warning


# ------------------------------------------------------------------------------ slices


def test_field_slice_shape_and_sign():
    bounds = torch.tensor([[-0.5, -0.25, -0.5], [0.5, 0.25, 0.5]], dtype=torch.float64)
    values = field_slice(Sphere(radius=0.2).sdf, bounds, axis="z", position=0.5, resolution=64)
    assert values.shape == (32, 64) and values.dtype == torch.float32
    assert values[16, 32] < 0 and values[0, 0] > 0
    assert float(values.min()) == pytest.approx(-0.2, abs=0.02)
    side = field_slice(Sphere(radius=0.2).sdf, bounds, axis="x", position=0.5, resolution=64)
    assert side.shape == (64, 32)  # columns along y, rows along z
    assert (field_slice(Sphere(radius=0.2).sdf, bounds, axis="z", position=0.0, resolution=16) > 0).all()
    with pytest.raises(ConfigError, match="axis"):
        field_slice(Sphere().sdf, bounds, axis="w")


def test_field_slice_rows_run_upwards():
    values = field_slice(lambda x: x[..., 1], UNIT_BOX, axis="z", resolution=8)
    assert (values[0] > values[-1]).all()  # row 0 is the top (largest y)
    assert torch.allclose(values[:, 0], values[:, -1])


def test_slice_image_colours():
    values = field_slice(Sphere(radius=0.2).sdf, UNIT_BOX, axis="y", resolution=64)
    image = slice_image(values)
    assert image.dtype == np.uint8 and image.shape == (64, 64, 3)
    centre, corner = image[32, 32].astype(int), image[0, 0].astype(int)
    assert centre[2] > centre[0]  # inside: blue
    assert corner[0] > corner[2]  # outside: red
    black = (image.sum(-1) == 0)
    assert black.any() and not black[32, 32] and not black[0, 0]
    assert black.sum() < 0.1 * black.size  # a thin contour, not a filled disc
    assert slice_image(np.zeros((4, 5))).shape == (4, 5, 3)


def test_marching_cubes_skips_cells_with_invalid_corners():
    grid = make_grid(UNIT_BOX, 48)
    index = np.stack(np.meshgrid(*[np.arange(s) for s in grid.shape], indexing="ij"), -1).reshape(-1, 3)
    values = Sphere().sdf(torch.from_numpy(grid.world(index))).numpy().reshape(grid.shape)
    valid = np.ones(grid.shape, dtype=bool)
    valid[: grid.shape[0] // 2] = False  # the x < 0 half is unobserved
    half = marching_cubes(values, grid, valid=valid)
    full = marching_cubes(values, grid)
    assert half.vertices[:, 0].min() >= -grid.spacing
    assert 0.4 * len(full.faces) < len(half.faces) < 0.6 * len(full.faces)
    assert int(half.faces.max()) == len(half.vertices) - 1  # unused vertices are dropped


