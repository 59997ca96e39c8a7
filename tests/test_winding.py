"""Winding-number signs against analytic oracles: solid angles, spheres, and CAD-like damaged meshes
whose inside must stay that of the clean shape away from the damage."""

import math
import warnings

import pytest
import torch
import trimesh

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.priors.mesh_folders import damage_mesh
from neuralsurf.structures import Mesh
from neuralsurf.winding import (
    MeshWinding,
    border_edges,
    boundary_faces,
    consistent_patches,
    inside,
    orient_outward,
    signed_distance,
    triangle_solid_angles,
    winding_number,
)


def sphere(subdivisions: int = 3, radius: float = 1.0, centre=(0.0, 0.0, 0.0)) -> Mesh:
    mesh = trimesh.creation.icosphere(subdivisions, radius)
    return Mesh(torch.tensor(mesh.vertices) + torch.tensor(centre), torch.tensor(mesh.faces))


def ring_and_post(x: torch.Tensor) -> torch.Tensor:
    """Analytic SDF (a bound, exact sign) of a torus with a box post through it: thin parts, a hole."""
    q = torch.stack([x[..., [0, 2]].norm(dim=-1) - 0.3, x[..., 1]], -1)
    torus = q.norm(dim=-1) - 0.1
    box = (x - x.new_tensor([0.0, 0.2, 0.0])).abs() - x.new_tensor([0.06, 0.3, 0.06])
    post = box.clamp_min(0).norm(dim=-1) + box.amax(-1).clamp_max(0)
    return torch.minimum(torus, post)


def ring_at(resolution: int) -> Mesh:
    from neuralsurf.extract import extract_mesh

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return extract_mesh(ring_and_post, resolution=resolution, bounds=torch.tensor([[-0.5] * 3, [0.6] * 3]),
                            progress=False)


@pytest.fixture(scope="module")
def ring_mesh() -> Mesh:
    return ring_at(48)


def test_solid_angle_of_an_octant_triangle_is_an_eighth_of_the_sphere():
    triangle = torch.eye(3, dtype=torch.float64)[None]  # corners on the axes, normal (1, 1, 1) away from 0
    origin = torch.zeros(1, 3, dtype=torch.float64)
    # the origin sees the triangle's back, as the inside of a closed outward surface does: +1/8
    assert triangle_solid_angles(origin, triangle).item() == pytest.approx(1 / 8, abs=1e-12)
    assert triangle_solid_angles(origin, triangle.flip(1)).item() == pytest.approx(-1 / 8, abs=1e-12)


def test_closed_sphere_is_one_inside_and_zero_outside():
    mesh = sphere(3)
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(400, 3, dtype=torch.float64, generator=generator), dim=-1)
    radii = torch.rand(400, 1, dtype=torch.float64, generator=generator)
    near_in, near_out = directions * 0.9 * radii, directions * (1.1 + 2 * radii)
    assert torch.allclose(winding_number(near_in, mesh), torch.ones(400, dtype=torch.float64), atol=1e-4)
    assert winding_number(near_out, mesh).abs().max() < 1e-4
    reversed_faces = Mesh(mesh.vertices, mesh.faces.flip(1))
    assert torch.allclose(winding_number(near_in, reversed_faces), -torch.ones(400, dtype=torch.float64), atol=1e-4)
    doubled = Mesh(mesh.vertices, torch.cat([mesh.faces, mesh.faces]))  # coincident copies count twice
    assert torch.allclose(winding_number(near_in, doubled), 2 * torch.ones(400, dtype=torch.float64), atol=1e-4)


def test_fast_winding_number_is_within_its_tolerance_of_the_exact_sum():
    """The oracle is the exact sum over every triangle; the mesh is damaged every way (holes, coincident
    copies facing either way, inner sheets, reversed faces), the points uniform and near the surface."""
    ring_mesh = ring_at(28)
    damaged = damage_mesh(ring_mesh, holes=3, duplicated=2, inner=2, flipped=0.3, radius=0.06, inset=0.015, seed=7)
    generator = torch.Generator().manual_seed(1)
    uniform = torch.rand(150, 3, dtype=torch.float64, generator=generator) * 1.2 - 0.55
    near_damage = damaged.centres[torch.randint(len(damaged.centres), (150,), generator=generator)]
    near = near_damage + 0.05 * torch.randn(150, 3, dtype=torch.float64, generator=generator)
    query = torch.cat([uniform, near])
    for mesh in (damaged.mesh, orient_outward(damaged.mesh)):
        exact = winding_number(query, mesh, approximate=False)
        for tolerance in (0.25, 0.05, 0.0):
            error = (winding_number(query, mesh, tolerance=tolerance) - exact).abs().max()
            assert error <= tolerance + 1e-4, (tolerance, float(error))
        clear = (exact - 0.5).abs() > 1e-4  # float32 rounding of the exact sum
        assert torch.equal(inside(query, mesh)[clear], (exact >= 0.5)[clear])
    assert MeshWinding(ring_mesh).closed  # marching cubes of a closed shape: no caps
    assert len(MeshWinding(damaged.mesh).caps.radius) >= 5  # holes and sheets are closed by caps
    truth = ring_and_post(query) < 0
    clear = ring_and_post(query).abs() > 0.04  # farther from the surface than marching cubes error at 28^3
    assert torch.equal(inside(query, ring_mesh)[clear], truth[clear])
    assert torch.equal(winding_number(query, ring_mesh)[clear], truth[clear].double())  # exactly 0 and 1


def test_border_edges_are_the_open_boundary_and_the_disagreeing_edges():
    box = trimesh.creation.box()
    faces = torch.tensor(box.faces)
    assert len(border_edges(faces)) == 0
    side = [i for i, f in enumerate(box.faces) if (box.vertices[f][:, 0] > 0.4).all()]  # the two faces at x = 0.5
    open_box = faces[[i for i in range(len(faces)) if i not in side]]
    loop = border_edges(open_box)
    assert len(loop) == 4 and sorted(loop[:, 0].tolist()) == sorted(loop[:, 1].tolist())  # a closed loop
    directed = {tuple(e) for f in open_box.tolist() for e in zip(f, f[1:] + f[:1])}
    assert all(tuple(e) in directed for e in loop.tolist())  # run the way the faces run them
    flipped = faces.clone()
    flipped[0] = flipped[0].flip(0)
    assert len(border_edges(flipped)) == 6  # each edge of the reversed face, twice
    # the caps close it: a closed box's winding number is exact (an integer) inside and outside
    winding = MeshWinding(Mesh(torch.tensor(box.vertices), open_box))
    assert not winding.closed and len(winding.caps.radius) == 1
    inner = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.1, -0.2]], dtype=torch.float64)
    assert winding.closed_winding(winding.unit(inner)).tolist() == [1, 1]


def test_overlapping_closed_parts_count_twice_and_stay_inside():
    first, second = sphere(3, 0.5, (-0.25, 0.0, 0.0)), sphere(3, 0.5, (0.25, 0.0, 0.0))
    both = Mesh(torch.cat([first.vertices, second.vertices]), torch.cat([first.faces, second.faces + len(first.vertices)]))
    query = torch.tensor([[0.0, 0.0, 0.0], [-0.6, 0.0, 0.0], [0.6, 0.0, 0.0], [0.0, 0.6, 0.0], [1.0, 0.0, 0.0]],
                         dtype=torch.float64)
    w = winding_number(query, both)
    assert w.tolist() == pytest.approx([2.0, 1.0, 1.0, 0.0, 0.0], abs=0.05)  # the clustered sum
    assert winding_number(query, both, approximate=False).tolist() == pytest.approx([2.0, 1.0, 1.0, 0.0, 0.0], abs=1e-3)
    assert inside(query, both).tolist() == [True, True, True, False, False]


def test_signed_distance_of_a_sphere_mesh_matches_the_analytic_one():
    mesh = sphere(4)
    generator = torch.Generator().manual_seed(2)
    query = torch.rand(500, 3, dtype=torch.float64, generator=generator) * 3 - 1.5
    truth = query.norm(dim=-1) - 1
    assert (signed_distance(query, mesh) - truth).abs().max() < 0.01  # the mesh's chord error


def test_consistent_patches_undo_single_flips():
    box = trimesh.creation.box()
    faces = torch.tensor(box.faces)
    flipped = faces.clone()
    flipped[[0, 3, 7]] = flipped[[0, 3, 7]].flip(1)
    patch, flip = consistent_patches(flipped)
    assert patch.unique().tolist() == [0]
    repaired = flipped.clone()
    repaired[flip] = repaired[flip].flip(1)
    mesh = trimesh.Trimesh(box.vertices, repaired.numpy(), process=False)
    assert mesh.is_winding_consistent


def test_orient_outward_turns_an_inside_out_sphere_and_keeps_a_good_one():
    mesh = sphere(2)
    assert torch.equal(orient_outward(mesh).faces, mesh.faces)
    assert torch.equal(orient_outward(Mesh(mesh.vertices, mesh.faces.flip(1))).faces, mesh.faces)


def test_damaged_mesh_keeps_the_clean_inside_away_from_the_damage(ring_mesh):
    damaged = damage_mesh(ring_mesh, holes=3, duplicated=2, inner=2, flipped=0.4, radius=0.04, inset=0.015, seed=3)
    assert not damaged.mesh.is_watertight
    assert len(damaged.mesh.faces) != len(ring_mesh.faces)
    generator = torch.Generator().manual_seed(4)
    query = torch.rand(800, 3, dtype=torch.float64, generator=generator) * 1.2 - 0.55
    query = query[damaged.away(query) & (ring_and_post(query).abs() > 0.01)]
    clean = inside(query, ring_mesh)
    assert torch.equal(clean, ring_and_post(query) < 0)
    oriented = orient_outward(damaged.mesh)
    assert torch.equal(inside(query, oriented), clean)
    # inner sheets are not boundary: with them left out the surface is the clean one away from holes
    boundary = Mesh(oriented.vertices, oriented.faces[boundary_faces(oriented)])
    assert len(boundary.faces) < len(oriented.faces)
    from neuralsurf.geometry import point_to_mesh_distance

    on_sheets = damaged.mesh.vertices[len(ring_mesh.vertices):]  # the vertices of the added sheets
    assert point_to_mesh_distance(on_sheets, boundary).max() < 0.02  # coincident copies stay, inner ones go
    assert (point_to_mesh_distance(on_sheets, boundary) > 0.01).any()
    assert torch.equal(inside(query, boundary), clean)
    # without the orientation repair 40% reversed faces pull the inside below one half
    assert inside(query, damaged.mesh)[clean].double().mean() < 0.5
    assert len(query) > 200


def test_inner_sheets_just_below_the_surface_leave_the_boundary_and_the_signs_above_them():
    """An open sheet just inside the surface puts the winding number of the layer between them near
    1/2; whole sheets must go before the faces between inside and outside are chosen. Oracle: the
    clean sphere mesh's exact inside (ray parity) and distances."""
    from neuralsurf.geometry import mesh_contains, point_to_mesh_distance

    mesh = sphere(3)
    damaged = damage_mesh(mesh, holes=0, duplicated=0, inner=6, flipped=0.0, radius=0.15, inset=0.01, seed=5)
    n_sphere = len(mesh.faces)
    assert len(damaged.mesh.faces) > n_sphere + 100  # the sheets, 0.02 below the surface, facing either way
    boundary = boundary_faces(damaged.mesh)
    assert boundary[:n_sphere].all() and not boundary[n_sphere:].any()
    generator = torch.Generator().manual_seed(6)
    directions = damaged.centres[torch.randint(len(damaged.centres), (1500,), generator=generator)]
    directions = torch.nn.functional.normalize(directions + 0.1 * torch.randn(1500, 3, dtype=torch.float64,
                                                                             generator=generator), dim=-1)
    query = directions * (1 + 0.06 * (torch.rand(1500, 1, dtype=torch.float64, generator=generator) - 0.5))
    surface = Mesh(damaged.mesh.vertices, damaged.mesh.faces[boundary])
    truth = torch.where(mesh_contains(query, mesh), -1.0, 1.0).double() * point_to_mesh_distance(query, mesh)
    assert (truth.abs() < 0.01).sum() > 300  # the layer between the sheets and the surface is sampled
    assert torch.equal(inside(query, surface), truth < 0)
    assert (signed_distance(query, surface) - truth).abs().max() < 1e-5


@pytest.mark.slow
def test_a_closed_marching_cubes_mesh_keeps_every_face_slivers_on_thin_rims_included():
    """Oracle: every face of a watertight, outward, one-part mesh lies between inside and outside. This
    procedural lamp's marching-cubes mesh has slivers 7e-4 wide on its shade's thin rim; tested 1e-3
    along their normals both sides were outside and four faces were dropped (the mesh left open)."""
    from neuralsurf.priors import Shape, collection_records

    record = [r for r in collection_records(("lamp",), 1, 0, 4, seed=0) if r.split == "test"][3]
    mesh = Shape.from_record(record).mesh(48)
    assert mesh.is_watertight
    assert boundary_faces(mesh).all()


def test_bad_input_is_named():
    mesh = sphere(1)
    with pytest.raises(InputError, match="empty mesh"):
        winding_number(torch.zeros(1, 3), Mesh(torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.long)))
    with pytest.raises(InputError, match=r"shape \(n, 3\)"):
        winding_number(torch.zeros(4), mesh)
    with pytest.raises(ConfigError, match="tolerance"):
        winding_number(torch.zeros(1, 3), mesh, tolerance=-1.0)
    with pytest.raises(ConfigError, match="flipped"):
        damage_mesh(mesh, flipped=2.0)
    assert math.isfinite(float(winding_number(torch.zeros(1, 3), mesh)))
