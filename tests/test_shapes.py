"""Procedural shapes and their caches: exact primitives, seeds and splits, watertightness, labels
against independent oracles, cache round trip and resume after an interruption."""

import json
import math

import numpy as np
import pytest
import torch

from neuralsurf.errors import ConfigError, FileFormatError
from neuralsurf.geometry import mesh_contains, point_to_mesh_distance
from neuralsurf.priors import Chair, Shape, ShapeRecord, SlatChair, check_shape, collection_records, csg
from neuralsurf.priors import cache as cache_module
from neuralsurf.priors.cache import CacheRecipe, build_collection, cache_path, load_cache, shape_samples

TINY = CacheRecipe(n_sdf=3000, n_occ=2000, n_surface=2000, mesh_resolution=48)


def _dense_surface_distance(query: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    return torch.cdist(query, surface).amin(1)


def test_capped_cone_and_torus_are_exact_distances():
    """|f| equals the distance to a dense sample of the surface (brute force), outside and inside;
    the sign matches a direct inside test."""
    g = torch.Generator().manual_seed(0)
    h, r1, r2 = 0.2, 0.3, 0.1
    n = 400
    # dense cone surface: lateral (parameterised by height and angle) and both caps
    ys = torch.linspace(-h, h, n, dtype=torch.float64)
    angles = torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)
    Y, A = torch.meshgrid(ys, angles, indexing="ij")
    R = r1 + (r2 - r1) * (Y + h) / (2 * h)
    lateral = torch.stack([R * A.cos(), Y, R * A.sin()], -1).reshape(-1, 3)
    caps = []
    for y, r in ((-h, r1), (h, r2)):
        rr = torch.linspace(0, r, n // 2, dtype=torch.float64)
        RR, AA = torch.meshgrid(rr, angles, indexing="ij")
        caps.append(torch.stack([RR * AA.cos(), torch.full_like(RR, y), RR * AA.sin()], -1).reshape(-1, 3))
    surface = torch.cat([lateral, *caps])
    query = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * 0.9
    f = csg.capped_cone(query, (0, 0, 0), h, r1, r2)
    assert torch.allclose(f.abs(), _dense_surface_distance(query, surface), atol=3e-3)
    radius_at = r1 + (r2 - r1) * (query[:, 1] + h) / (2 * h)
    inside = (query[:, [0, 2]].norm(dim=-1) < radius_at) & (query[:, 1].abs() < h)
    assert torch.equal(f < 0, inside)

    major, minor = 0.25, 0.08
    U, V = torch.meshgrid(angles, angles, indexing="ij")
    torus = torch.stack([(major + minor * V.cos()) * U.cos(), (major + minor * V.cos()) * U.sin(), minor * V.sin()],
                        -1).reshape(-1, 3)
    f = csg.torus_z(query, (0, 0, 0), major, minor)
    assert torch.allclose(f.abs(), _dense_surface_distance(query, torus), atol=3e-3)


def test_primitives_agree_where_they_coincide_and_are_distances():
    g = torch.Generator().manual_seed(1)
    p = (torch.rand(2000, 3, generator=g, dtype=torch.float64) - 0.5) * 1.2
    # a cone with equal radii is a cylinder; a box of equal half-sides with full rounding is a sphere
    assert torch.allclose(csg.capped_cone(p, (0.1, 0, 0), 0.2, 0.15, 0.15), csg.cylinder(p, (0.1, 0, 0), 0.15, 0.2),
                          atol=1e-12)
    assert torch.allclose(csg.box(p, (0, 0, 0), (0.2, 0.2, 0.2), rounding=0.2), csg.sphere(p, (0, 0, 0), 0.2),
                          atol=1e-12)
    # an axis-aligned box: outside, the distance is the norm of the positive excess
    f = csg.box(p, (0, 0, 0), (0.1, 0.2, 0.3))
    excess = (p.abs() - torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)).clamp_min(0)
    outside = excess.norm(dim=-1) > 0
    assert torch.allclose(f[outside], excess.norm(dim=-1)[outside])
    # exact SDFs have unit gradients, also exactly on the surface (finite there)
    for sdf in (lambda x: csg.capped_cone(x, (0, 0, 0), 0.2, 0.3, 0.1), lambda x: csg.torus_z(x, (0, 0, 0), 0.3, 0.1),
                lambda x: csg.cylinder(x, (0, 0, 0), 0.2, 0.3), lambda x: csg.box(x, (0, 0, 0), (0.1, 0.2, 0.3), 0.05)):
        x = p.clone().requires_grad_(True)
        (gradient,) = torch.autograd.grad(sdf(x).sum(), x)
        assert torch.allclose(gradient.norm(dim=-1), torch.ones(len(p), dtype=torch.float64), atol=1e-6)
    on_surface = torch.tensor([[0.0, 0.3, 0.0], [0.2, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    (gradient,) = torch.autograd.grad(csg.cylinder(on_surface, (0, 0, 0), 0.2, 0.3).sum(), on_surface)
    assert torch.isfinite(gradient).all()


def test_records_are_seeded_and_splits_draw_disjoint_streams():
    records = collection_records(("chair", "mug", "lamp"), n_train=3, n_val=2, n_test=2, seed=5)
    assert [r.split for r in records] == ["train"] * 9 + ["val"] * 6 + ["test"] * 6
    assert len({r.seed for r in records}) == len(records)
    assert len({r.name for r in records}) == len(records)
    again = Shape.from_record(ShapeRecord("chair", "test", 1, 5))
    assert again.parameters == Shape.from_record(ShapeRecord("chair", "test", 1, 5)).parameters
    assert again.parameters != Shape.from_record(ShapeRecord("chair", "train", 1, 5)).parameters
    assert again.parameters != Shape.from_record(ShapeRecord("chair", "test", 1, 6)).parameters
    with pytest.raises(ConfigError, match="unknown shape class"):
        collection_records(("sofa",))
    with pytest.raises(ConfigError, match="unknown split"):
        _ = ShapeRecord("chair", "training", 0).seed


def _check_generated(kind: str, indices) -> None:
    for index in indices:
        shape = Shape.from_record(ShapeRecord(kind, "train", index))
        mesh = shape.mesh(resolution=64)
        check_shape(shape, mesh)  # raises unless watertight, consistently oriented, one piece, in the cube
        assert mesh.is_watertight
        lo, hi = mesh.bounds.double()
        assert float((hi - lo).max()) == pytest.approx(1.0, abs=0.02)  # normalised: longest side 1
        assert hi.max() <= 0.5 + 1e-3 and lo.min() >= -0.5 - 1e-3


@pytest.mark.parametrize("kind", ["chair", "mug", "lamp", "slat_chair"])
def test_generated_shapes_are_watertight_one_piece_and_fill_the_unit_cube(kind):
    _check_generated(kind, [0])


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["chair", "mug", "lamp", "slat_chair"])
def test_many_generated_shapes_are_watertight_and_one_piece(kind):
    _check_generated(kind, range(1, 25))


def test_chair_occupancy_against_its_parts():
    """A chair written down by hand: the seat's centre is inside, the space between the legs under the
    seat and above the seat in front of the back is outside."""
    chair = Chair(seat_width=0.5, seat_depth=0.5, seat_thickness=0.06, seat_height=0.45, leg_half=0.04,
                  leg_inset=0.02, round_legs=False, back_height=0.5, back_thickness=0.05)
    raw = torch.tensor([[0.0, 0.42, 0.0],  # seat centre
                        [0.0, 0.2, 0.0],  # between the legs
                        [0.0, 0.7, 0.1],  # above the seat, in front of the back
                        [0.0, 0.7, -0.23],  # in the back rest
                        [0.19, 0.2, 0.19]],  # in a leg (centre at 0.25 - 0.02 - 0.04 = 0.19)
                       dtype=torch.float64)
    assert (chair.raw_sdf(raw) < 0).tolist() == [True, False, False, True, True]


def test_slat_chair_occupancy_against_its_thin_parts():
    """A slatted chair written down by hand: slats, stretchers and the top rail are inside, the gaps
    between the slats and between the stretchers and the seat are outside."""
    chair = SlatChair(seat_width=0.5, seat_depth=0.5, seat_thickness=0.04, seat_height=0.45, leg_half=0.025,
                      stretcher_half=0.015, stretcher_height=0.15, back_height=0.4, slats=3, slat_width=0.03,
                      slat_half=0.015, rail_half=0.03)
    back_z = -(0.25 - 0.025)
    slat_x = [-0.225 + 0.45 * (i + 1) / 4 for i in range(3)]  # between the rear legs at x = +-0.225
    raw = torch.tensor([[slat_x[0], 0.65, back_z],  # in a slat
                        [(slat_x[0] + slat_x[1]) / 2, 0.65, back_z],  # between two slats
                        [0.0, 0.85, back_z],  # in the top rail
                        [0.225, 0.15, 0.0],  # in a side stretcher
                        [0.225, 0.3, 0.0],  # between the stretcher and the seat
                        [0.0, 0.15, 0.225]],  # in the front stretcher
                       dtype=torch.float64)
    assert (chair.raw_sdf(raw) < 0).tolist() == [True, False, True, True, False, True]


def test_cache_labels_and_distances_against_independent_oracles(tmp_path):
    shape = Shape.from_record(ShapeRecord("mug", "test", 0))
    arrays = shape_samples(shape, TINY)
    mesh = shape.mesh(resolution=TINY.mesh_resolution)
    voxel = 1.1 / TINY.mesh_resolution
    # occupancy labels agree with ray parity on the ground-truth mesh away from its discretisation
    for kind in ("uniform", "near"):
        points = torch.from_numpy(arrays[f"occ_{kind}_points"]).double()
        labels = torch.from_numpy(arrays[f"occ_{kind}_inside"])
        far = shape.sdf(points).abs() > voxel / 2
        assert far.sum() > 200
        assert torch.equal(mesh_contains(points[far], mesh), labels[far])
    # SDF samples outside: a mug is a difference (the cavity), whose max(a, -b) bounds the distance
    # from below; a lamp is a union of exact primitives, exact outside (up to the mesh's discretisation)
    points = torch.from_numpy(arrays["sdf_points"]).double()
    values = torch.from_numpy(arrays["sdf_values"]).double()
    outside = values > 0
    distance = point_to_mesh_distance(points[outside], mesh).double()
    assert (values[outside] - distance).max() < voxel / 2
    assert (values[outside] - distance).abs().median() < 2e-3
    lamp = Shape.from_record(ShapeRecord("lamp", "test", 0))
    lamp_arrays = shape_samples(lamp, TINY)
    lamp_points = torch.from_numpy(lamp_arrays["sdf_points"]).double()
    lamp_values = torch.from_numpy(lamp_arrays["sdf_values"]).double()
    outside = lamp_values > 0
    lamp_distance = point_to_mesh_distance(lamp_points[outside], lamp.mesh(TINY.mesh_resolution)).double()
    assert (lamp_values[outside] - lamp_distance).abs().max() < voxel / 2
    # surface samples lie on the analytic zero set, with unit normals along the gradient
    surface = torch.from_numpy(arrays["surface_points"]).double()
    assert shape.sdf(surface).abs().max() < 1e-5
    normals = torch.from_numpy(arrays["surface_normals"]).double()
    stepped = shape.sdf(surface + 1e-3 * normals)
    assert (stepped > 0).float().mean() > 0.99
    # DeepSDF's recipe: mostly near the surface, a volume fraction spread over the padded cube
    assert (values.abs() < 0.05).float().mean() > 0.8
    volume = points[-round(TINY.n_sdf * TINY.volume_fraction):]
    assert volume.abs().max() <= 0.5 + TINY.padding and volume.abs().max() > 0.5


def test_cache_round_trip_and_refuses_foreign_files(tmp_path):
    records = [ShapeRecord("lamp", "train", 0)]
    counts = build_collection(tmp_path, records, TINY, progress=False)
    assert counts == {"built": 1, "cached": 0}
    path = cache_path(tmp_path, records[0])
    loaded = load_cache(path)
    expected = shape_samples(Shape.from_record(records[0]), TINY)
    assert set(loaded) == set(expected)
    for key, value in expected.items():
        assert loaded[key].dtype == value.dtype and np.array_equal(loaded[key], value), key
    assert json.loads(str(loaded["recipe"]))["record"]["kind"] == "lamp"
    manifest = json.loads((tmp_path / "collection.json").read_text())
    assert [s["kind"] for s in manifest["shapes"]] == ["lamp"]
    # another recipe in the same folder is an error, never a silent mix
    with pytest.raises(ConfigError, match="another recipe"):
        build_collection(tmp_path, records, CacheRecipe(n_sdf=100, n_occ=100, n_surface=100, mesh_resolution=48),
                         progress=False)
    path.write_bytes(b"not an npz")
    with pytest.raises(FileFormatError, match="delete it"):
        load_cache(path)


def test_interrupted_build_leaves_no_half_file_and_resumes(tmp_path, monkeypatch):
    records = [ShapeRecord("lamp", "train", i) for i in range(2)]
    real_savez = np.savez
    calls = {"n": 0}

    def savez_then_interrupt(handle, **arrays):
        calls["n"] += 1
        if calls["n"] == 2:  # the second shape: half a file, then Ctrl-C
            handle.write(b"PK\x03\x04 half a zip")
            raise KeyboardInterrupt
        real_savez(handle, **arrays)

    monkeypatch.setattr(cache_module.np, "savez", savez_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        build_collection(tmp_path, records, TINY, progress=False)
    monkeypatch.setattr(cache_module.np, "savez", real_savez)
    files = sorted(p.name for p in (tmp_path / "train").iterdir())
    assert files == ["lamp_train_0000.npz"]  # no half file, no temporary left behind
    first = (tmp_path / "train" / files[0]).read_bytes()

    done = []
    counts = build_collection(tmp_path, records, TINY, progress=False, on_done=lambda name, status: done.append(name))
    assert counts == {"built": 1, "cached": 1} and done == ["lamp_train_0001"]  # only the missing shape
    assert (tmp_path / "train" / files[0]).read_bytes() == first
    expected = shape_samples(Shape.from_record(records[1]), TINY)  # what an uninterrupted build writes
    loaded = load_cache(cache_path(tmp_path, records[1]))
    assert all(np.array_equal(loaded[k], expected[k]) for k in expected)
    assert build_collection(tmp_path, records, TINY, progress=False) == {"built": 0, "cached": 2}


@pytest.mark.slow
def test_parallel_build_writes_the_same_files_as_a_serial_one(tmp_path):
    records = collection_records(("chair", "lamp"), n_train=2, n_val=0, n_test=1)
    build_collection(tmp_path / "serial", records, TINY, workers=0, progress=False)
    build_collection(tmp_path / "parallel", records, TINY, workers=2, progress=False)
    for record in records:
        a = load_cache(cache_path(tmp_path / "serial", record))
        b = load_cache(cache_path(tmp_path / "parallel", record))
        assert all(np.array_equal(a[k], b[k]) for k in a)


def test_command_line_builds_a_collection(tmp_path, capsys):
    from neuralsurf.priors.__main__ import main

    argv = ["build", "--out", str(tmp_path), "--classes", "lamp", "--n-train", "1", "--n-val", "0", "--n-test", "1",
            "--workers", "0", "--n-sdf", "500", "--n-occ", "500", "--n-surface", "500", "--mesh-resolution", "48"]
    assert main(argv) == 0
    assert "2 built" in capsys.readouterr().out
    assert (tmp_path / "test" / "lamp_test_0000.npz").is_file()
    assert main(argv) == 0
    assert "2 already cached" in capsys.readouterr().out
