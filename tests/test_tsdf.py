"""TSDF fusion: analytic oracles (sphere, planes), Open3D side by side, dense == sparse, one
marching-cubes call as the reference of the block-wise extraction, the bunny bar, 7-Scenes, bad input."""

from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from neuralsurf.baselines import FusionSettings, TSDFVolume, depth_bounds
from neuralsurf.baselines.tsdf.bands import candidate_blocks
from neuralsurf.baselines.tsdf.voxels import camera_to_grid, pixel_weights
from neuralsurf.cameras import backproject_depth, kinect_sigma
from neuralsurf.errors import ConfigError, DeviceError, ExtractionError, InputError, NeuralsurfError
from neuralsurf.geometry import point_to_mesh_distance
from neuralsurf.scenes import Sphere, bunny, scan_depth
from neuralsurf.structures import DepthFrames, Mesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from open3d_tsdf import fuse_open3d, fuse_voxel_block_grid  # Open3D's fusions, shared with the benchmarks

SPHERE = Sphere(center=(0.02, -0.01, 0.03), radius=0.3)
BOX = torch.tensor([[-0.4] * 3, [0.4] * 3], dtype=torch.float64)
VOXEL = 0.02
K_SMALL = torch.tensor([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def sphere_frames() -> DepthFrames:
    """24 exact views of the sphere, 64 x 48: a pixel covers about 0.7 voxel (VOXEL) on it."""
    return scan_depth(SPHERE.mesh(5), n_views=24, width=64, height=48)


@pytest.fixture(scope="module")
def sphere_mesh(sphere_frames) -> Mesh:
    return TSDFVolume(BOX, VOXEL, device="cpu").integrate(sphere_frames).extract_mesh()


def radial_error(mesh: Mesh) -> torch.Tensor:
    """Distance of each vertex to the analytic sphere."""
    return ((mesh.vertices.double() - torch.tensor(SPHERE.center)).norm(dim=-1) - SPHERE.radius).abs()


def signed_volume(mesh: Mesh) -> float:
    a, b, c = mesh.vertices.double()[mesh.faces].unbind(1)
    return float((a * torch.linalg.cross(b, c)).sum() / 6)


def flat_frames(depths: list[float], colors: bool = False) -> DepthFrames:
    """Cameras at the origin looking down +z at fronto-parallel walls at the given depths."""
    n = len(depths)
    depth = torch.tensor(depths, dtype=torch.float32)[:, None, None].expand(n, 48, 64).clone()
    rgb = torch.rand(n, 48, 64, 3, generator=torch.Generator().manual_seed(0)) if colors else None
    return DepthFrames(depth, K_SMALL, torch.eye(4).expand(n, 4, 4), rgb)


def axis_value(volume: TSDFVolume, z: float) -> tuple[float, float]:
    """(tsdf, weight) of the grid point on the optical axis at depth z (volumes from `axis_box`)."""
    tsdf, weight = volume.to_dense()
    k = round((z - volume.origin[2]) / volume.voxel_size)
    i, j = (round(-volume.origin[a] / volume.voxel_size) for a in (0, 1))
    return float(tsdf[i, j, k]), float(weight[i, j, k])


def axis_box(voxel: float = 0.01) -> list[list[float]]:
    """A box around the optical axis whose grid has a point at x = y = 0 and at z = 1.0."""
    return [[-0.1, -0.1, 0.8], [0.1, 0.1, 1.3]]


# ------------------------------------------------------------------------------- geometry


def test_sphere_matches_the_analytic_surface(sphere_mesh):
    error = radial_error(sphere_mesh) / VOXEL  # projective distances bias convex shapes outward a little
    assert float(error.mean()) < 0.15 and float(error.max()) < 0.75
    assert sphere_mesh.is_watertight
    assert signed_volume(sphere_mesh) == pytest.approx(SPHERE.volume, rel=0.02)  # > 0: faces point outward


def test_agrees_with_open3d_within_a_voxel(sphere_frames, sphere_mesh):
    reference = fuse_open3d(sphere_frames, BOX, VOXEL, 3 * VOXEL)
    ours_to_theirs = point_to_mesh_distance(sphere_mesh.vertices.double(), reference)
    theirs_to_ours = point_to_mesh_distance(reference.vertices.double(), sphere_mesh)
    chamfer = 0.5 * (ours_to_theirs.mean() + theirs_to_ours.mean())
    assert float(chamfer) < 0.1 * VOXEL  # well within one voxel
    assert float(torch.maximum(ours_to_theirs.max(), theirs_to_ours.max())) < VOXEL


def test_band_only_is_as_complete_as_open3d_voxel_block_grid():
    """The band-only update (free_space 0) against Open3D's VoxelBlockGrid at the same voxel size,
    truncation and grid on 12 views of the bunny: at least 95 % of its vertices, ours within half a
    voxel of its vertices (median), and all but 1 % of its vertices within a voxel of ours."""
    truth = bunny()
    frames = scan_depth(truth, n_views=12, width=320, height=240)
    lo, hi = truth.bounds.double()
    voxel = float((hi - lo).max()) / 128
    start = torch.floor((lo - 4 * voxel) / voxel) * voxel  # on Open3D's grid: multiples of the voxel
    volume = TSDFVolume(torch.stack([start, hi + 4 * voxel]), voxel, 3 * voxel, device="cpu", sparse=True)
    ours = volume.integrate(frames).extract_mesh().vertices.double().numpy()
    theirs = fuse_voxel_block_grid(frames, voxel, 3 * voxel).vertices.double().numpy()
    assert len(ours) >= 0.95 * len(theirs)  # measured 0.99
    ours_to_theirs = cKDTree(theirs).query(ours)[0]
    theirs_to_ours = cKDTree(ours).query(theirs)[0]
    assert np.median(ours_to_theirs) < 0.5 * voxel  # measured 0.24 voxel (Open3D reads pixel floor(u))
    assert np.mean(theirs_to_ours > voxel) < 0.01


def plane_frame(degrees: float) -> DepthFrames:
    """One 128 x 96 view of the plane through (0, 0, 1) whose normal makes `degrees` with the
    optical axis (closed-form depth, cut at 2.5 m)."""
    angle = math.radians(degrees)
    normal = torch.tensor([0.0, -math.sin(angle), math.cos(angle)], dtype=torch.float64)
    K = torch.tensor([[120.0, 0.0, 63.5], [0.0, 120.0, 47.5], [0.0, 0.0, 1.0]])
    v, u = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
    rays = torch.stack([(u - 63.5) / 120, (v - 47.5) / 120, torch.ones_like(u)], -1).double()
    depth = normal[2] / (rays @ normal)
    return DepthFrames(torch.where((depth > 0) & (depth < 2.5), depth, 0.0).float()[None], K, torch.eye(4)[None])


def mesh_area(mesh: Mesh) -> float:
    a, b, c = mesh.vertices.double()[mesh.faces].unbind(1)
    return float(torch.linalg.cross(b - a, c - a).norm(dim=-1).sum() / 2)


@pytest.mark.parametrize("degrees", [45, 70, 80])
def test_band_only_meshes_grazing_views_at_least_as_far_as_open3d(degrees):
    """Seen at a grazing angle, the voxels just in front of a surface have projective distances far
    beyond the truncation: the band's blocks observe them all (at +truncation), so their cells are
    meshed. Behind the surface the band ends at -truncation along the ray, i.e. truncation * cos
    (angle) from the plane, as in Open3D: one view at 70-80 degrees leaves stripes (area measured
    0.47 and 0.25 of the patch; VoxelBlockGrid 0.26 and 0.16)."""
    frame = plane_frame(degrees)
    box = [[-0.8, -0.8, 0.3], [0.8, 0.8, 2.8]]
    ours = TSDFVolume(box, 0.01, 0.03, device="cpu").integrate(frame).extract_mesh()
    theirs = fuse_voxel_block_grid(frame, 0.01, 0.03)
    assert mesh_area(ours) >= mesh_area(theirs)
    if degrees == 45:
        grid = backproject_depth(frame)[0].double()  # the visible patch: the depth image's grid mesh
        valid = frame.depth[0] > 0
        cells = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
        patch = torch.linalg.cross(grid[1:, :-1] - grid[:-1, :-1], grid[:-1, 1:] - grid[:-1, :-1]).norm(dim=-1)
        assert mesh_area(ours) > 0.95 * float(patch[cells].sum())  # measured 0.985
    normal = torch.tensor([0.0, -math.sin(math.radians(degrees)), math.cos(math.radians(degrees))])
    distance = ((ours.vertices.double() - torch.tensor([0.0, 0.0, 1.0])) @ normal.double()).abs()
    assert float(distance.median()) < 0.25 * 0.01  # on the plane


def test_sparse_and_dense_give_the_same_mesh(sphere_frames, sphere_mesh):
    sparse = TSDFVolume(BOX, VOXEL, device="cpu", sparse=True).integrate(sphere_frames)
    dense_blocks = int(sparse.block_counts.prod())
    assert 0 < sparse.n_blocks < 0.7 * dense_blocks
    mesh = sparse.extract_mesh()
    assert torch.equal(mesh.vertices, sphere_mesh.vertices) and torch.equal(mesh.faces, sphere_mesh.faces)


@pytest.mark.parametrize("sparse", [True, False])
def test_observed_voxels_are_the_dense_grids_weighted_points(sphere_frames, sparse):
    volume = TSDFVolume(BOX, 0.02, block_size=4, device="cpu", sparse=sparse).integrate(sphere_frames[:6])
    linear, values = volume.observed_voxels()
    tsdf, weight = volume.to_dense()
    seen = (weight > 0).reshape(-1).nonzero()[:, 0]
    order = linear.argsort()
    assert torch.equal(linear[order], seen) and torch.equal(values[order], tsdf.reshape(-1)[seen])


def test_block_extraction_equals_one_marching_cubes_call(sphere_frames, monkeypatch):
    from skimage.measure import marching_cubes

    from neuralsurf.baselines.tsdf import volume as tsdf

    monkeypatch.setattr(tsdf, "_MESH_BLOCKS", 300)  # several marching-cubes calls, merged
    volume = TSDFVolume(BOX, 0.01, block_size=4, device="cpu", sparse=True).integrate(sphere_frames[:12])
    mesh = volume.extract_mesh()  # 80^3 voxels in blocks of 4^3, some cells never observed
    tsdf, weight = volume.to_dense()
    valid = (weight > 0).numpy()
    values = np.where(valid, tsdf.numpy(), 1.0).astype(np.float32)
    vertices, faces, _, _ = marching_cubes(values, 0.0)
    corners = [
        valid[i : i + valid.shape[0] - 1, j : j + valid.shape[1] - 1, k : k + valid.shape[2] - 1]
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    ]
    cell_valid = np.logical_and.reduce(corners)
    faces = faces[cell_valid[tuple(np.floor(vertices[faces].mean(1)).astype(int).T)]]
    assert len(faces) == len(mesh.faces)
    reference = vertices[np.unique(faces)] * volume.voxel_size + volume.origin
    assert len(reference) == len(mesh.vertices)
    gap, _ = cKDTree(reference).query(mesh.vertices.double().numpy())
    assert gap.max() < 1e-6  # the same vertices (float32 rounding apart), merged across blocks and calls
    assert not mesh.is_watertight  # half the views leave holes: no faces were made up there


def test_one_view_meshes_only_what_it_sees():
    eye = torch.tensor([0.02, -0.01, 0.03 - 1.0])
    frames = scan_depth(
        SPHERE.mesh(5),
        cam_to_world=torch.eye(4).index_put((torch.arange(3), torch.tensor(3)), eye)[None],
        K=K_SMALL,
        width=64,
        height=48,
    )
    mesh = TSDFVolume(BOX, VOXEL, device="cpu").integrate(frames).extract_mesh()
    assert float(radial_error(mesh).max()) < 0.6 * VOXEL  # no faces between observed and unobserved voxels
    assert float(mesh.vertices[:, 2].max()) < SPHERE.center[2]  # only the near half
    assert not mesh.is_watertight


def test_fusion_averages_out_noise(sphere_frames):
    noisy = scan_depth(
        SPHERE.mesh(5),
        cam_to_world=sphere_frames.cam_to_world,
        K=sphere_frames.K,
        width=64,
        height=48,
        noise="gaussian",
        sigma=0.4 * VOXEL,
        seed=1,
    )
    mesh = TSDFVolume(BOX, VOXEL, device="cpu").integrate(noisy).extract_mesh()
    per_pixel = (
        (noisy.depth - sphere_frames.depth)[(noisy.depth > 0) & (sphere_frames.depth > 0)].abs().mean()
    )
    assert float(radial_error(mesh).mean()) < 0.5 * float(per_pixel)


def test_the_stanford_bunny_bar():
    """24 exact 320 x 240 views, voxel = 1/256 of the longest side: Chamfer-L1 <= 1e-3 (unit frame)."""
    from neuralsurf.metrics import evaluate_mesh

    truth = bunny()
    frames = scan_depth(truth, n_views=24, width=320, height=240)
    lo, hi = truth.bounds.double()
    voxel = float((hi - lo).max()) / 256
    volume = TSDFVolume(torch.stack([lo - 8 * voxel, hi + 8 * voxel]), voxel, device="cpu").integrate(frames)
    metrics = evaluate_mesh(volume.extract_mesh(), truth, n_samples=50_000)
    assert float(metrics["chamfer_l1_exact"]) <= 1.0e-3


# ------------------------------------------------------------------------------ integration


def test_batched_and_frame_by_frame_integration_agree(sphere_frames):
    batched = TSDFVolume(BOX, VOXEL, device="cpu", sparse=True).integrate(sphere_frames[:6])
    single = TSDFVolume(BOX, VOXEL, device="cpu", sparse=True)
    for i in range(6):
        single.integrate(sphere_frames[i])
    assert single.frames_integrated == batched.frames_integrated == 6
    for a, b in zip(batched.to_dense(), single.to_dense()):
        assert torch.equal(a.nan_to_num(99.0), b.nan_to_num(99.0))


def test_projective_distance_running_average_and_truncation():
    volume = TSDFVolume(axis_box(), 0.01, truncation=0.04, device="cpu").integrate(flat_frames([1.02, 1.01]))
    tsdf, weight = axis_value(volume, 1.0)
    assert (tsdf, weight) == (pytest.approx(0.015, abs=1e-6), 2.0)  # mean of d - z = 0.02 and 0.01
    assert axis_value(volume, 1.05)[0] == pytest.approx(-0.035, abs=1e-6)  # behind the walls
    # in front, in a block the band touches (z in [0.96, 1.04)): clamped to +truncation
    assert axis_value(volume, 0.97) == (pytest.approx(0.04, abs=1e-6), 2.0)
    assert axis_value(volume, 0.92)[1] == 0.0  # in a block the band does not touch: never updated
    assert axis_value(volume, 1.07)[1] == 0.0  # behind the band: never updated


def test_free_space_carves_the_blocks_in_front_of_the_band():
    """free_space (metres) reaches the band's blocks that much further towards the camera: there
    every voxel in front of the surface is observed at +truncation, the band itself unchanged.
    Blocks along z: [0.8, 0.88), [0.88, 0.96), [0.96, 1.04), ..."""
    frames = flat_frames([1.02, 1.01])
    band = TSDFVolume(axis_box(), 0.01, truncation=0.04, device="cpu").integrate(frames)
    carved = TSDFVolume(axis_box(), 0.01, truncation=0.04, device="cpu", fusion=FusionSettings(free_space=0.105)).integrate(frames)
    assert axis_value(carved, 0.92) == (pytest.approx(0.04, abs=1e-6), 2.0)
    assert axis_value(carved, 0.85) == (pytest.approx(0.04, abs=1e-6), 2.0)  # reached: 0.875 and 0.865
    for z in (0.97, 1.0, 1.05):
        assert axis_value(carved, z) == axis_value(band, z)
    assert axis_value(carved, 1.07)[1] == axis_value(band, 1.07)[1] == 0.0
    assert torch.equal(band.extract_mesh().faces, carved.extract_mesh().faces)
    # each frame reaches its own blocks: 1.02 - 0.135 = 0.885 stops short of the first block
    shorter = TSDFVolume(axis_box(), 0.01, truncation=0.04, device="cpu", fusion=FusionSettings(free_space=0.095)).integrate(frames)
    assert axis_value(shorter, 0.85) == (pytest.approx(0.04, abs=1e-6), 1.0)


def test_depth_weighting_and_max_weight():
    frames = flat_frames([1.02, 1.05])
    volume = TSDFVolume(axis_box(), 0.01, truncation=0.06, device="cpu", fusion=FusionSettings(weighting="depth")).integrate(frames)
    w = pixel_weights(torch.tensor([1.02, 1.05]), "depth")
    assert float(w[0]) == pytest.approx(
        float((kinect_sigma(torch.tensor(0.4)) / kinect_sigma(torch.tensor(1.02))) ** 2)
    )
    expected = float((w[0] * 0.02 + w[1] * 0.05) / w.sum())
    assert axis_value(volume, 1.0) == (
        pytest.approx(expected, abs=1e-6),
        pytest.approx(float(w.sum()), rel=1e-5),
    )
    capped = TSDFVolume(axis_box(), 0.01, truncation=0.06, device="cpu", fusion=FusionSettings(max_weight=1.0))
    capped.integrate(flat_frames([1.02, 1.01, 1.05]))
    assert axis_value(capped, 1.0) == (pytest.approx(((0.02 + 0.01) / 2 + 0.05) / 2, abs=1e-6), 1.0)


def test_colors_are_averaged_like_the_distances(sphere_frames):
    points = backproject_depth(sphere_frames)
    paint = lambda p: ((p - BOX[0].float()) / 0.8).clamp(0, 1)  # colour = position in the box
    frames = DepthFrames(sphere_frames.depth, sphere_frames.K, sphere_frames.cam_to_world, paint(points))
    mesh = TSDFVolume(BOX, VOXEL, device="cpu", with_color=True).integrate(frames).extract_mesh()
    assert mesh.vertex_colors is not None and mesh.vertex_colors.shape == mesh.vertices.shape
    assert float((mesh.vertex_colors - paint(mesh.vertices.float())).abs().max()) < 0.05


@pytest.mark.parametrize("tile", [1, 2])
@pytest.mark.parametrize("free_space", [0.0, 0.3])
def test_candidate_blocks_hold_every_block_a_band_meets(sphere_frames, free_space, tile):
    """The coverage claim of `candidate_blocks`, brute force over every grid point: a point whose
    nearest pixel has a depth d and whose z lies in [d - truncation - free_space, d + truncation]
    is in a candidate block (also with long segments: free_space 0.3 m), and there are few more;
    with tiles of one pixel (the compiled path's) and of 2 x 2 (the eager path's)."""
    volume = TSDFVolume(BOX, VOXEL, block_size=4, device="cpu", fusion=FusionSettings(free_space=free_space))
    origin = torch.as_tensor(volume.origin, dtype=torch.float64)
    for i in (3, 11):
        frame = sphere_frames[i]
        rotation, translation = camera_to_grid(frame.cam_to_world, origin, VOXEL)
        keys, frame_keys = candidate_blocks(
            frame.depth, frame.K, rotation.float(), translation.float(), volume.truncation, free_space, 4,
            volume.block_counts, tile=tile,
        )
        assert frame_keys is None
        every = torch.arange(int(volume.block_counts.prod()))
        points = (volume._block_coords(every)[:, None] * 4 + volume._local.long()).reshape(-1, 3).double()
        camera = (points - translation[0]) @ torch.linalg.inv(rotation[0]).T  # grid -> camera, metres
        uvz = camera @ frame.K[0].double().T
        u, v, z = uvz[:, 0] / uvz[:, 2], uvz[:, 1] / uvz[:, 2], uvz[:, 2]
        inside = (z > 0) & (u >= -0.5) & (u < 63.5) & (v >= -0.5) & (v < 47.5)
        col, row = (u + 0.5).floor().clamp(0, 63).long(), (v + 0.5).floor().clamp(0, 47).long()
        d = frame.depth[0, row, col].double()
        met = inside & (d > 0) & (z >= d - volume.truncation - free_space) & (z <= d + volume.truncation)
        needed = torch.unique(every[met.nonzero()[:, 0] // 64])
        assert len(needed) > 50 and torch.isin(needed, keys).all()
        assert len(keys) < 3 * len(needed)  # and few more (blocks of 4 voxels here; 1.15 x on 7-Scenes)


def test_candidate_blocks_of_several_frames_are_each_frames_own(sphere_frames):
    """With several frames, frame_keys says which frame's band touches which block: the same as
    each frame alone, and the keys are their union."""
    volume = TSDFVolume(BOX, VOXEL, block_size=4, device="cpu")
    origin = torch.as_tensor(volume.origin, dtype=torch.float64)
    frames = sphere_frames[:5]
    rotation, translation = camera_to_grid(frames.cam_to_world, origin, VOXEL)
    args = (volume.truncation, 0.0, 4, volume.block_counts)
    keys, frame_keys = candidate_blocks(frames.depth, frames.K, rotation.float(), translation.float(), *args)
    total = int(volume.block_counts.prod())
    alone = [
        candidate_blocks(frames.depth[i : i + 1], frames.K[i : i + 1], rotation[i : i + 1].float(),
                         translation[i : i + 1].float(), *args)[0]
        for i in range(5)
    ]
    assert torch.equal(frame_keys, torch.cat([k + i * total for i, k in enumerate(alone)]))
    assert torch.equal(keys, torch.unique(torch.cat(alone)))


@pytest.mark.slow
def test_compiled_fusion_equals_eager_fusion(sphere_frames):
    """compiled=True runs `tile_box_codes` and `fuse_blocks` through torch.compile: the same candidate
    blocks and the same fused values (depth weights, a weight cap, colour) as the same code run eagerly
    with the same tiles, and a mesh within a hundredth of a voxel of the eager default's."""
    from neuralsurf.baselines.tsdf import volume as tsdf

    points = backproject_depth(sphere_frames)
    frames = DepthFrames(sphere_frames.depth, sphere_frames.K, sphere_frames.cam_to_world, points.abs().clamp(0, 1))
    make = lambda compiled: TSDFVolume(BOX, VOXEL, device="cpu", sparse=True, with_color=True,
                                       fusion=FusionSettings(weighting="depth", max_weight=5.0, compiled=compiled))
    volume = make(False)
    origin = torch.as_tensor(volume.origin, dtype=torch.float64)
    rotation, translation = camera_to_grid(frames.cam_to_world[:1], origin, VOXEL)
    for tile in (1, 2):
        blocks = [
            candidate_blocks(frames.depth[:1], frames.K[:1], rotation.float(), translation.float(), volume.truncation,
                             0.0, 8, volume.block_counts, box_codes, tile)[0]
            for box_codes in (tsdf.tile_box_codes, tsdf._COMPILED[tsdf.tile_box_codes])
        ]
        assert len(blocks[0]) > 20 and torch.equal(*blocks)
    compiled = make(True).integrate(frames)
    with pytest.MonkeyPatch.context() as patch:  # the eager run with the compiled run's tiles
        patch.setitem(tsdf.TILE, "eager", tsdf.TILE["compiled"])
        volume.integrate(frames)
    assert compiled.n_blocks == volume.n_blocks and torch.equal(compiled._keys, volume._keys)
    (tsdf_c, weight_c), (tsdf_e, weight_e) = compiled.to_dense(), volume.to_dense()
    assert torch.equal(weight_c, weight_e)
    torch.testing.assert_close(tsdf_c, tsdf_e, equal_nan=True, rtol=0, atol=1e-6)
    torch.testing.assert_close(compiled._color, volume._color, rtol=0, atol=1e-5)
    mesh, default_mesh = compiled.extract_mesh(), make(False).integrate(frames).extract_mesh()
    gap = cKDTree(default_mesh.vertices.numpy()).query(mesh.vertices.numpy())[0]
    assert abs(len(mesh.faces) - len(default_mesh.faces)) <= 0.01 * len(default_mesh.faces)
    assert float(np.median(gap)) < 0.01 * VOXEL


def test_a_failed_compilation_warns_and_fuses_eagerly(sphere_frames, monkeypatch):
    """Without a C++ compiler torch.compile's CPU backend fails: FusionSettings(compiled=True) says so once
    and gives the eager result."""
    from neuralsurf.baselines.tsdf import volume as tsdf
    from neuralsurf.devices import CompiledOnCPU

    def no_compiler(function, **options):
        def fail(*args):
            raise torch._dynamo.exc.BackendCompilerFailed(fail, RuntimeError("InvalidCxxCompiler: none"), None)
        return fail

    monkeypatch.setattr(torch, "compile", no_compiler)
    monkeypatch.setattr(tsdf, "_COMPILED", {f: CompiledOnCPU(f, "TSDF fusion") for f in tsdf._COMPILED})
    with pytest.warns(UserWarning, match="C\\+\\+ compiler"):
        compiled = TSDFVolume(BOX, VOXEL, device="cpu", fusion=FusionSettings(compiled=True)).integrate(sphere_frames[:4])
    monkeypatch.setitem(tsdf.TILE, "eager", tsdf.TILE["compiled"])
    eager = TSDFVolume(BOX, VOXEL, device="cpu").integrate(sphere_frames[:4])
    assert torch.equal(compiled.to_dense()[1], eager.to_dense()[1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once: the next call goes straight to the eager function
        TSDFVolume(BOX, VOXEL, device="cpu", fusion=FusionSettings(compiled=True)).integrate(sphere_frames[:1])


def test_long_integrations_are_compiled_by_default(sphere_frames, monkeypatch):
    """compiled=None compiles an integrate call of _COMPILE_PIXELS depth pixels or more, not a shorter one;
    True and False force it either way."""
    from neuralsurf.baselines.tsdf import volume as tsdf

    calls = []
    spy = lambda function: lambda *args: (calls.append(function.__name__), function(*args))[1]
    monkeypatch.setattr(tsdf, "_COMPILED", {f: spy(f) for f in tsdf._COMPILED})
    monkeypatch.setattr(tsdf, "_COMPILE_PIXELS", 4 * 64 * 48)
    runs = {(None, 3): [], (None, 4): ["tile_box_codes", "fuse_blocks"], (True, 1): ["tile_box_codes", "fuse_blocks"],
            (False, 24): []}
    for (compiled, frames), expected in runs.items():
        calls.clear()
        TSDFVolume(BOX, VOXEL, device="cpu", fusion=FusionSettings(compiled=compiled)).integrate(sphere_frames[:frames])
        assert sorted(set(calls)) == sorted(expected), (compiled, frames)
    with pytest.raises(ConfigError, match="compiled"):
        FusionSettings(compiled="yes")


def test_auto_device_is_cpu_without_cuda():
    volume = TSDFVolume(BOX, VOXEL)
    assert volume.device.type == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("sparse", [False, True])
def test_frames_fused_in_batches_equal_frames_fused_one_by_one(sphere_frames, sparse):
    """frames_per_pass (the GPU default) changes how the work is grouped, not the result: the same
    running averages, in the same order, with depth weights, a weight cap and colour."""
    points = backproject_depth(sphere_frames)
    frames = DepthFrames(sphere_frames.depth, sphere_frames.K, sphere_frames.cam_to_world, points.abs().clamp(0, 1))
    make = lambda n: TSDFVolume(BOX, VOXEL, device="cpu", sparse=sparse, with_color=True, fusion=FusionSettings(
        weighting="depth", max_weight=5.0, frames_per_pass=n)).integrate(frames)
    one, batched = make(1), make(7)  # 24 frames: passes of 7, 7, 7 and 3
    (tsdf, weight), (batched_tsdf, batched_weight) = one.to_dense(), batched.to_dense()
    assert torch.equal(weight, batched_weight)  # every voxel saw the same pixels
    torch.testing.assert_close(batched_tsdf, tsdf, equal_nan=True, rtol=0, atol=1e-6)  # float32 rounding
    mesh, batched_mesh = one.extract_mesh(), batched.extract_mesh()
    assert torch.equal(mesh.faces, batched_mesh.faces)
    torch.testing.assert_close(batched_mesh.vertex_colors, mesh.vertex_colors, rtol=0, atol=1e-5)
    assert one.n_blocks == batched.n_blocks
    with pytest.raises(ConfigError, match="frames_per_pass"):
        FusionSettings(frames_per_pass=0)


def test_threads_are_set_for_integration_and_restored(sphere_frames):
    before = torch.get_num_threads()
    seen = []
    volume = TSDFVolume(BOX, VOXEL, device="cpu", fusion=FusionSettings(threads=1))
    original = volume._integrate_frames
    volume._integrate_frames = lambda *args: (seen.append(torch.get_num_threads()), original(*args))
    volume.integrate(sphere_frames[:2])
    assert seen == [1, 1] and torch.get_num_threads() == before
    with pytest.raises(ConfigError, match="threads"):
        FusionSettings(threads=0)


def test_chunks_on_worker_threads_give_the_same_volume(sphere_frames):
    """Eager CPU fusion runs a pass's chunks of blocks side by side on `threads` worker threads (each torch
    op on one thread) and finds the next pass's blocks meanwhile: the volume is the one a single thread
    fuses, bit for bit."""
    seen = []
    make = lambda threads: TSDFVolume(BOX, VOXEL, device="cpu", sparse=True, with_color=True,
                                      fusion=FusionSettings(weighting="depth", max_weight=5.0, threads=threads))
    single, pooled = make(1), make(2)
    single._chunk_observations = pooled._chunk_observations = 4096  # many chunks a frame
    original = pooled._integrate_frames
    pooled._integrate_frames = lambda *args: (seen.append(torch.get_num_threads()), original(*args))
    frames = sphere_frames[:6]
    frames = DepthFrames(frames.depth, frames.K, frames.cam_to_world, backproject_depth(frames).clamp(0, 1))
    single.integrate(frames), pooled.integrate(frames)
    assert set(seen) == {1}
    assert torch.equal(single._keys, pooled._keys) and torch.equal(single._slots, pooled._slots)
    for name in ("_tsdf", "_weight", "_color"):
        assert torch.equal(getattr(single, name), getattr(pooled, name)), name


def analytic_sphere_frames(n_views: int, width: int, height: int) -> DepthFrames:
    """Closed-form z-depth of SPHERE from orbit cameras (ray-sphere intersection; no Open3D, so it
    runs on any machine with a GPU)."""
    from neuralsurf.scenes.scanner import intrinsics_from_fov, orbit_cameras

    K = intrinsics_from_fov(width, height, 60.0)  # as scan_depth's defaults
    poses = orbit_cameras(SPHERE.center, SPHERE.radius, n_views, 60.0, width / height)
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)  # z = 1
    world = rays @ poses[:, None, :3, :3].transpose(-1, -2)  # (n, h, w, 3) per unit of z
    centre = (torch.tensor(SPHERE.center) - poses[:, :3, 3])[:, None, None]  # sphere centre from the camera
    a, b = (world**2).sum(-1), (world * centre).sum(-1)
    c = (centre**2).sum(-1) - SPHERE.radius**2
    disc = b**2 - a * c
    z = torch.where(disc > 0, (b - disc.clamp_min(0).sqrt()) / a, 0.0)  # the nearer root, in z units
    return DepthFrames(z.float(), K.float(), poses.float())


def test_analytic_sphere_frames_agree_with_the_ray_caster(sphere_frames):
    """The oracle of the CUDA test against scan_depth on the tessellated sphere (sphere_frames)."""
    frames = analytic_sphere_frames(24, 64, 48)
    torch.testing.assert_close(frames.cam_to_world, sphere_frames.cam_to_world, atol=1e-5, rtol=0)
    hit, ray_cast_hit = frames.depth > 0, sphere_frames.depth > 0
    assert (hit != ray_cast_hit).float().mean() < 0.01  # silhouettes agree up to the tessellation
    gap = (frames.depth - sphere_frames.depth)[hit & ray_cast_hit].abs()
    assert float(gap.max()) < 0.005 * SPHERE.radius


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("sparse", [False, True])
def test_cuda_matches_cpu(sparse):
    """The GPU path (32 frames per pass) against the CPU path (one at a time) on the same frames."""
    frames = analytic_sphere_frames(24, 64, 48)
    cpu = TSDFVolume(BOX, VOXEL, device="cpu", sparse=sparse).integrate(frames)
    gpu = TSDFVolume(BOX, VOXEL, device="cuda", sparse=sparse).integrate(frames)
    assert gpu.frames_per_pass == 32 and cpu.frames_per_pass == 1
    (cpu_tsdf, cpu_weight), (gpu_tsdf, gpu_weight) = cpu.to_dense(), [t.cpu() for t in gpu.to_dense()]
    same = cpu_weight == gpu_weight  # float rounding may move a voxel across a pixel border, rarely
    assert same.float().mean() > 0.999
    both = same & (cpu_weight > 0)
    torch.testing.assert_close(gpu_tsdf[both], cpu_tsdf[both], atol=1e-5, rtol=0)
    gpu_vertices, cpu_vertices = gpu.extract_mesh().vertices, cpu.extract_mesh().vertices
    gap = cKDTree(cpu_vertices.double().numpy()).query(gpu_vertices.double().numpy())[0]
    assert gap.mean() < 0.01 * VOXEL


# -------------------------------------------------------------------------------- real data


def read_seven_scenes(folder, **options) -> DepthFrames:
    from neuralsurf.io import read_rgbd_folder

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 7-Scenes colour is not registered to depth: said once
        return read_rgbd_folder(folder, format="7scenes", **options)


def assert_mesh_fits_depth(mesh: Mesh, frames: DepthFrames, tolerance: float) -> None:
    """Median distance from back-projected depth (every 8th pixel) to the fused mesh."""
    points = backproject_depth(frames)[:, ::8, ::8][frames.depth[:, ::8, ::8] > 0].double()
    assert float(point_to_mesh_distance(points, mesh).median()) < tolerance


def test_seven_scenes_few_frames(shared_data):
    frames = read_seven_scenes(shared_data / "7scenes_redkitchen_every10", stride=10, with_color=False)
    volume = TSDFVolume(depth_bounds(frames, margin=0.1), 0.03, device="cpu", sparse=True).integrate(frames)
    mesh = volume.extract_mesh()
    assert volume.n_blocks < 0.3 * int(volume.block_counts.prod())
    assert_mesh_fits_depth(mesh, frames, 0.01)


@pytest.mark.slow
def test_seven_scenes_full_sequence_at_one_centimetre(shared_data):
    frames = read_seven_scenes(shared_data / "7scenes_redkitchen_every10", with_color=True)
    volume = TSDFVolume(
        depth_bounds(frames, margin=0.05), 0.01, truncation=0.04, device="cpu", sparse=True, with_color=True
    )
    volume.integrate(frames)
    blocks = int(volume.block_counts.prod())  # of the dense volume over the room's box
    assert volume.n_blocks < 0.15 * blocks  # 11,527 of 112,596 blocks
    assert volume.memory_bytes < 0.2 * blocks * volume.block_size**3 * 20  # capacity grows by 1.5x
    mesh = volume.extract_mesh()
    assert len(mesh.faces) > 500_000 and mesh.vertex_colors is not None
    assert_mesh_fits_depth(
        mesh, frames[::10], 0.01
    )  # one voxel; the poses agree to ~6 mm, the depth to ~1 cm


# -------------------------------------------------------------------------------- bad input


def test_bad_input_is_explained(sphere_frames):
    with pytest.raises(ConfigError, match="voxel_size"):
        TSDFVolume(BOX, 0.0)
    with pytest.raises(ConfigError, match="truncation"):
        TSDFVolume(BOX, VOXEL, truncation=-0.01)
    with pytest.warns(UserWarning, match="smaller than a voxel"):
        TSDFVolume(BOX, VOXEL, truncation=0.5 * VOXEL, device="cpu")
    with pytest.raises(ConfigError, match="weighting"):
        FusionSettings(weighting="fancy")
    with pytest.raises(ConfigError, match="fusion must be a FusionSettings"):
        TSDFVolume(BOX, VOXEL, fusion={"weighting": "depth"})
    with pytest.raises(InputError, match="bounds"):
        TSDFVolume([[0, 0, 0], [1, -1, 1]], VOXEL)
    with pytest.raises(ConfigError, match="sparse=True"):
        TSDFVolume([[0, 0, 0], [100, 100, 100]], 0.01, device="cpu")  # 10^12 voxels
    volume = TSDFVolume(BOX, VOXEL, device="cpu")
    with pytest.raises(ExtractionError, match="integrate"):
        volume.extract_mesh()
    with pytest.raises(InputError, match="DepthFrames"):
        volume.integrate(sphere_frames.depth)
    wrong_K = sphere_frames.K.clone()
    wrong_K[:, 0, 2] = 320.0  # K of a 640-wide camera on 64-wide images
    with pytest.raises(InputError, match="principal point"):
        volume.integrate(DepthFrames(sphere_frames.depth, wrong_K, sphere_frames.cam_to_world))
    with pytest.raises(InputError, match="colors"):
        TSDFVolume(BOX, VOXEL, device="cpu", with_color=True).integrate(sphere_frames)
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="CUDA"):
            TSDFVolume(BOX, VOXEL, device="cuda")
    outside = TSDFVolume([[5, 5, 5], [6, 6, 6]], VOXEL, device="cpu").integrate(sphere_frames)
    with pytest.raises(ExtractionError, match="observed"):
        outside.extract_mesh()
    assert all(
        issubclass(e, NeuralsurfError) for e in (ConfigError, InputError, ExtractionError, DeviceError)
    )


def test_ten_real_range_scans_fuse_within_a_millimetre_of_the_zipper_mesh(shared_data, record_property):
    """The Stanford scans as depth images (read_range_scan_frames) fused at 1 mm voxels: exact
    distances to bun_zipper.ply under 1 mm each way (measured 0.094 mm; 0.076 mm at 0.5 mm voxels)."""
    from neuralsurf.geometry import point_to_mesh_distance, sample_mesh_surface
    from neuralsurf.io import read_mesh, read_range_scan_frames

    folder = shared_data / "stanford_bunny"
    frames = read_range_scan_frames(folder / "data" / "bun.conf")
    gt = read_mesh(folder / "reconstruction" / "bun_zipper.ply")
    lo, hi = gt.bounds.double()
    mesh = TSDFVolume(torch.stack([lo - 0.01, hi + 0.01]), 1e-3, 3e-3, device="cpu").integrate(frames).extract_mesh()
    g = torch.Generator().manual_seed(0)
    accuracy = point_to_mesh_distance(sample_mesh_surface(mesh, 50_000, g)[0].double(), gt).double().mean()
    completeness = point_to_mesh_distance(sample_mesh_surface(gt, 50_000, g)[0].double(), mesh).double().mean()
    record_property("stanford_tsdf_chamfer_mm", float(0.5 * (accuracy + completeness)) * 1e3)
    assert accuracy < 1e-3 and completeness < 1e-3
    assert 0.5 * (accuracy + completeness) < 0.2e-3


# ------------------------------------------------------------------------------- save / load


@pytest.mark.parametrize("sparse, colors", [(False, False), (True, False), (True, True)])
def test_saved_volume_loads_to_the_same_mesh_and_keeps_integrating(tmp_path, sphere_frames, sparse, colors):
    frames = sphere_frames
    if colors:
        rgb = torch.rand(*frames.depth.shape, 3, generator=torch.Generator().manual_seed(0))
        frames = DepthFrames(frames.depth, frames.K, frames.cam_to_world, rgb)
    settings = {"device": "cpu", "sparse": sparse, "with_color": colors,
                "fusion": FusionSettings(weighting="depth", max_weight=50.0)}
    half = TSDFVolume(BOX, VOXEL, **settings).integrate(frames[:12])
    path = half.save(tmp_path / "volume.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["volume.npz"]  # no temporary left behind
    loaded = TSDFVolume.load(path, device="cpu")
    assert loaded.fusion == settings["fusion"]  # the file's rule, the default execution
    with pytest.raises(ConfigError, match="keeps its fusion rule"):
        TSDFVolume.load(path, device="cpu", fusion=FusionSettings(weighting="constant"))
    assert TSDFVolume.load(path, device="cpu", fusion=FusionSettings(weighting="depth", max_weight=50.0,
                                                                      threads=1)).fusion.threads == 1
    assert (loaded.frames_integrated, loaded.n_blocks, loaded.grid_shape) == (12, half.n_blocks, half.grid_shape)
    before, after = half.extract_mesh(), loaded.extract_mesh()
    assert torch.equal(before.vertices, after.vertices) and torch.equal(before.faces, after.faces)
    if colors:
        assert torch.equal(before.vertex_colors, after.vertex_colors)
    # fusing the rest into the loaded volume = fusing everything in one volume
    whole = TSDFVolume(BOX, VOXEL, **settings).integrate(frames).extract_mesh()
    resumed = loaded.integrate(frames[12:]).extract_mesh()
    assert torch.equal(whole.vertices, resumed.vertices) and torch.equal(whole.faces, resumed.faces)


def test_loading_refuses_pickles_and_foreign_or_truncated_files(tmp_path, sphere_frames):
    from neuralsurf.errors import FileFormatError

    path = TSDFVolume(BOX, VOXEL, device="cpu", sparse=True).integrate(sphere_frames[:2]).save(tmp_path / "v.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(FileFormatError, match="truncated.npz.*truncated or not a file written by TSDFVolume.save"):
        TSDFVolume.load(truncated)
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, format=np.array(["neuralsurf.TSDFVolume/1", {"a": 1}], dtype=object))
    with pytest.raises(FileFormatError, match="pickled.npz"):  # numpy refuses the object array: no pickle runs
        TSDFVolume.load(pickled)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, x=np.zeros(3))
    with pytest.raises(FileFormatError, match=r"foreign.npz' is not a TSDF volume written by TSDFVolume.save"):
        TSDFVolume.load(foreign)
    with pytest.raises(FileFormatError, match="not found"):
        TSDFVolume.load(tmp_path / "absent.npz")


def test_an_interrupted_save_leaves_the_earlier_file_intact(tmp_path, sphere_frames, monkeypatch):
    from neuralsurf.errors import FileFormatError

    volume = TSDFVolume(BOX, VOXEL, device="cpu", sparse=True).integrate(sphere_frames[:2])
    path = volume.save(tmp_path / "v.npz")
    saved = path.read_bytes()

    def disk_full(file, **arrays):
        file.write(b"PK\x03\x04 half a zip")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", disk_full)
    with pytest.raises(FileFormatError, match="No space left on device"):
        volume.integrate(sphere_frames[2:4]).save(path)
    assert path.read_bytes() == saved and [p.name for p in tmp_path.iterdir()] == ["v.npz"]
