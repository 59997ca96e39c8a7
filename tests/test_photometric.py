"""Photometric stereo, chrome-ball calibration, normal integration and the synthetic photometric rig,
against analytic oracles (a sphere's normals, planes, sphere caps, mirror reflection) and per-pixel
numpy reference solves."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from neuralsurf.cameras import backproject_depth_to_camera, render_depth
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.photometric import (
    angular_error,
    calibrate_chrome_ball,
    continuous_pieces,
    depth_error,
    integrate_bilateral,
    integrate_least_squares,
    least_squares_stereo,
    photometric_stereo,
    reflect_view,
    render_lambertian,
    robust_stereo,
    sphere_from_mask,
    trimmed_stereo,
)
from neuralsurf.scenes import Sphere, look_at
from neuralsurf.scenes.photometric_rig import (
    SpecularLobe,
    cap_lights,
    checker_albedo,
    render_photometric,
    ring_lights,
)
from neuralsurf.structures import Mesh, PhotometricCapture


def sphere_normals(size: int = 64, radius: float = 0.45) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic normals of an orthographic sphere filling the image: normals (h, w, 3), mask (h, w)."""
    v, u = torch.meshgrid(
        torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij"
    )
    centre = (size - 1) / 2
    x, y = (u - centre) / (radius * size), (v - centre) / (radius * size)
    mask = x**2 + y**2 < 0.98
    z = -torch.sqrt((1 - x**2 - y**2).clamp_min(0))
    return torch.stack([x, y, z], -1) * mask[..., None], mask


def tilted(directions) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.tensor(directions, dtype=torch.float64), dim=-1)


LIGHTS = tilted(
    [
        [0.3, 0.2, -1],
        [-0.4, 0.1, -1],
        [0.1, -0.5, -1],
        [0.5, 0.5, -1],
        [-0.3, -0.3, -1],
        [0.0, 0.6, -1],
        [-0.6, 0.0, -1],
        [0.2, -0.1, -1],
    ]
)


# ---------------------------------------------------------------------------------------------- stereo


def test_sphere_under_known_lights_gives_its_analytic_normals():
    normals, mask = sphere_normals()
    images = render_lambertian(normals, torch.full(mask.shape, 0.7, dtype=torch.float64), LIGHTS).float()
    lit = mask & (images > 0).all(0)  # least squares is exact where no light is clamped
    result = least_squares_stereo(images, LIGHTS.float(), mask)
    assert angular_error(result.normals, normals.float(), lit).mean_deg < 0.1
    torch.testing.assert_close(result.albedo[lit], torch.full((int(lit.sum()),), 0.7), atol=1e-4, rtol=0)
    # the robust method drops the clamped (attached-shadow) observations: exact on the whole disc
    robust = robust_stereo(images, LIGHTS.float(), mask)
    error = angular_error(robust.normals, normals.float(), mask)
    assert error.mean_deg < 0.1 and error.errors_deg[mask].max() < 0.5
    assert robust.confidence[lit].min() > 0.99 and (robust.confidence[~mask] == 0).all()


def test_least_squares_matches_a_per_pixel_numpy_solve():
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(10, 6, 7, 3, generator=generator)
    lights = torch.nn.functional.normalize(torch.randn(10, 3, generator=generator), dim=-1)
    result = least_squares_stereo(images, lights)
    gray = images.mean(-1).numpy().astype(np.float64)
    for row, column in ((0, 0), (3, 4), (5, 6)):
        g = np.linalg.lstsq(lights.double().numpy(), gray[:, row, column], rcond=None)[0]
        np.testing.assert_allclose(result.normals[row, column].numpy(), g / np.linalg.norm(g), atol=1e-5)
        shading = lights.double().numpy() @ (g / np.linalg.norm(g))
        for channel in range(3):  # per-channel albedo: least squares of I_c = rho_c (n . l)
            rho = shading @ images[:, row, column, channel].double().numpy() / (shading @ shading)
            assert abs(float(result.albedo[row, column, channel]) - rho) < 1e-5


def test_trimmed_fit_matches_a_per_pixel_numpy_solve_of_the_kept_observations():
    generator = torch.Generator().manual_seed(1)
    images = torch.rand(12, 5, 5, generator=generator)
    lights = torch.nn.functional.normalize(torch.randn(12, 3, generator=generator), dim=-1)
    result = trimmed_stereo(images, lights, dark_fraction=0.25, bright_fraction=0.25)
    chunked = trimmed_stereo(images, lights, dark_fraction=0.25, bright_fraction=0.25, chunk_pixels=7)
    for name in ("normals", "albedo", "confidence", "mask", "inliers"):
        torch.testing.assert_close(getattr(chunked, name), getattr(result, name))
    for row, column in ((0, 0), (2, 3), (4, 1)):
        values = images[:, row, column].double().numpy()
        kept = np.argsort(values)[3:9]  # 25 % of 12 = 3 darkest and 3 brightest left out
        g = np.linalg.lstsq(lights.double().numpy()[kept], values[kept], rcond=None)[0]
        np.testing.assert_allclose(result.normals[row, column].numpy(), g / np.linalg.norm(g), atol=1e-4)
        assert float(result.inliers[row, column]) == 6


def test_robust_beats_least_squares_under_shadows_and_highlights():
    normals, mask = sphere_normals(48)
    lights = cap_lights(40, 45.0)
    images = render_lambertian(normals, torch.full(mask.shape, 0.6, dtype=torch.float64), lights)
    # Blinn-Phong highlights (viewer along -z) and random cast shadows on a fifth of the observations
    half = torch.nn.functional.normalize(lights + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), dim=-1)
    highlight = 0.8 * torch.einsum("nk,hwk->nhw", half, normals).clamp_min(0) ** 40
    generator = torch.Generator().manual_seed(0)
    shadow = torch.rand(images.shape, generator=generator, dtype=torch.float64) < 0.2
    images = torch.where(shadow, 0.0, images + highlight * (images > 0)).float()
    ls = angular_error(least_squares_stereo(images, lights.float(), mask).normals, normals.float(), mask)
    robust = angular_error(robust_stereo(images, lights.float(), mask).normals, normals.float(), mask)
    assert robust.mean_deg <= 0.7 * ls.mean_deg
    assert (
        robust.median_deg < 0.5
    )  # the mean carries pixels facing the camera, where most lights give highlights


def test_colour_albedo_and_photometric_stereo_on_a_capture():
    normals, mask = sphere_normals(32)
    albedo = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64).expand(32, 32, 3)
    images = render_lambertian(normals, albedo, LIGHTS).float()
    capture = PhotometricCapture(images, LIGHTS.float(), mask=mask, normals=normals.float())
    result = photometric_stereo(capture, "robust")
    assert result.albedo.shape == (32, 32, 3)
    torch.testing.assert_close(result.albedo[mask], albedo[mask].float(), atol=1e-3, rtol=0)
    assert angular_error(result.normals, capture.normals, mask).mean_deg < 0.1
    with pytest.raises(ConfigError, match="unknown photometric-stereo method"):
        photometric_stereo(capture, "magic")


def test_angular_error_of_a_known_tilt():
    normals, mask = sphere_normals(32)
    tangent = torch.nn.functional.normalize(
        torch.linalg.cross(normals, torch.tensor([0.3, 0.5, 0.8], dtype=torch.float64).expand_as(normals)),
        dim=-1,
    )
    tilted_normals = normals + math.tan(math.radians(10.0)) * tangent  # 10 degrees away from every normal
    error = angular_error(tilted_normals * mask[..., None], normals, mask)
    assert abs(error.mean_deg - 10.0) < 1e-6 and abs(error.median_deg - 10.0) < 1e-6
    unsolved = normals.clone()
    first = mask.nonzero()[0]
    unsolved[first[0], first[1]] = 0  # an unsolved pixel counts as 90 degrees
    assert abs(angular_error(unsolved, normals, mask).mean_deg - 90.0 / int(mask.sum())) < 1e-6


def test_stereo_input_errors():
    images = torch.rand(4, 5, 5)
    with pytest.raises(InputError, match="one direction per image"):
        least_squares_stereo(images, torch.randn(3, 3))
    with pytest.raises(InputError, match="at least 3 lights"):
        least_squares_stereo(images[:2], torch.randn(2, 3))
    coplanar = torch.tensor([[1.0, 0, -1], [0, 1, -1], [-1, 0, -1], [0, -1, -1]])
    coplanar[:, 2] = 0
    with pytest.raises(InputError, match="coplanar"):
        least_squares_stereo(images, coplanar)
    with pytest.raises(InputError, match="mask must be"):
        robust_stereo(images, torch.randn(4, 3), torch.ones(4, 4, dtype=torch.bool))
    with pytest.raises(ConfigError, match="fewer than 3"):
        trimmed_stereo(images, torch.randn(4, 3), dark_fraction=0.5, bright_fraction=0.25)
    lights = torch.tensor([[0.0, 0, -1], [0.5, 0, -1], [0, 0.5, -1], [-0.5, 0, -1]])
    with pytest.raises(InputError, match=r"lights hold NaN or inf \(rows \[2\]\)"):
        least_squares_stereo(images, torch.where(torch.arange(4)[:, None] == 2, float("nan"), lights))
    broken = images.clone()
    broken[1, 2, 3] = float("inf")
    with pytest.raises(InputError, match="images hold NaN or inf at 1 masked pixels"):
        robust_stereo(torch.stack([broken] * 3, -1), lights)
    outside = torch.ones(5, 5, dtype=torch.bool)
    outside[2, 3] = False  # a broken pixel outside the mask is not read
    assert least_squares_stereo(broken, lights, outside).mask[2, 3].item() is False


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_stereo_runs_on_cuda_and_agrees_with_the_cpu():
    normals, mask = sphere_normals(64)
    images = render_lambertian(
        normals, torch.full(mask.shape, 0.5, dtype=torch.float64), cap_lights(20)
    ).float()
    lights = cap_lights(20).float()
    for method in (least_squares_stereo, robust_stereo):
        cpu = method(images, lights, mask)
        gpu = method(images.cuda(), lights.cuda(), mask.cuda())
        assert gpu.normals.is_cuda
        torch.testing.assert_close(gpu.normals.cpu(), cpu.normals, atol=1e-4, rtol=0)


# ---------------------------------------------------------------------------------------------- chrome ball


def render_chrome_ball(
    lights: torch.Tensor, size: int = 96, radius_px: float = 30.0, spread_deg: float = 3.0
):
    """Orthographic images of a mirror sphere under distant lights: each pixel reflects the view
    direction about its normal, and a light shows where the reflection points at it (a Gaussian lobe)."""
    v, u = torch.meshgrid(
        torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij"
    )
    cu, cv = 0.52 * size, 0.47 * size
    x, y = (u - cu) / radius_px, (v - cv) / radius_px
    mask = x**2 + y**2 <= 1
    normals = torch.stack([x, y, -torch.sqrt((1 - x**2 - y**2).clamp_min(0))], -1)
    reflected = reflect_view(normals)
    cosine = torch.einsum("nk,hwk->nhw", lights, reflected).clamp(-1, 1)
    images = torch.exp(-((torch.rad2deg(torch.acos(cosine)) / spread_deg) ** 2)) * mask
    return images.float(), mask, (cu, cv)


def test_chrome_ball_calibration_recovers_the_lights():
    lights = ring_lights(8, 35.0)
    lights[::2] = cap_lights(4, 25.0)  # two slants
    images, mask, (cu, cv) = render_chrome_ball(lights, size=160, radius_px=60.0, spread_deg=4.0)
    calibration = calibrate_chrome_ball(images, mask)
    center, radius = sphere_from_mask(mask)
    assert abs(float(center[0]) - cu) < 0.1 and abs(float(center[1]) - cv) < 0.1 and abs(radius - 60.0) < 0.3
    angles = torch.rad2deg(torch.acos((calibration.directions.double() * lights).sum(-1).clamp(-1, 1)))
    assert float(angles.max()) < 0.3, angles
    assert (calibration.directions[:, 2] < 0).all()  # lights on the camera's side


def test_reflect_view_is_a_mirror_reflection():
    facing = torch.tensor([[0.0, 0.0, -1.0]])
    torch.testing.assert_close(
        reflect_view(facing), torch.tensor([[0.0, 0.0, -1.0]])
    )  # light behind the camera
    tilted45 = torch.tensor([[math.sin(math.pi / 8), 0.0, -math.cos(math.pi / 8)]])
    light = reflect_view(tilted45)[0]
    assert abs(math.degrees(math.acos(-float(light[2]))) - 45.0) < 1e-5 and light[0] > 0


# ---------------------------------------------------------------------------------------------- integration


def test_integration_recovers_a_tilted_plane_orthographic_and_perspective():
    h, w = 24, 32
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    # orthographic: z = 0.3 u - 0.2 v (pixel units), normal (dz/du, dz/dv, -1)
    slope = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
    normals = torch.nn.functional.normalize(slope, dim=0).expand(h, w, 3)
    truth = 0.3 * u - 0.2 * v + 50
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(normals, torch.ones(h, w, dtype=torch.bool))
        assert depth_error(result.depth, truth, align="offset").mean_abs < 1e-6
    # perspective: the plane n . X = -d seen by a pinhole camera
    K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]], dtype=torch.float64)
    n = torch.nn.functional.normalize(torch.tensor([0.2, -0.3, -1.0], dtype=torch.float64), dim=0)
    rays = torch.stack([(u - 15.5) / 40, (v - 11.5) / 40, torch.ones_like(u)], -1)
    depth = 2.0 / -(rays @ n)  # n . (z r) = -2
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(n.expand(h, w, 3), torch.ones(h, w, dtype=torch.bool), K=K)
        # log-depth is not linear along a perspective plane: the trapezoid rule leaves ~1e-6
        assert depth_error(result.depth, depth, align="scale").mean_abs < 1e-5 * float(depth.mean())


def sphere_cap(h: int = 48, w: int = 64, K: torch.Tensor | None = None):
    """Normals and depth of a sphere (centre (0, 0, 3), radius 1) seen by `K` (default: orthographic,
    one pixel = 0.025 units): normals (h, w, 3), depth (h, w), mask."""
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    centre = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    if K is None:
        x, y = (u - (w - 1) / 2) * 0.025, (v - (h - 1) / 2) * 0.025
        inside = x**2 + y**2 < 0.9**2
        z = 3 - torch.sqrt((1 - x**2 - y**2).clamp_min(0))
        points = torch.stack([x, y, z], -1)
    else:
        rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
        rays_unit = torch.nn.functional.normalize(rays, dim=-1)
        b = (rays_unit * centre).sum(-1)
        disc = b**2 - (centre @ centre - 1)
        inside = disc > 0.19 * 1  # keep away from the grazing rim (as the orthographic 0.9 radius does)
        t = b - torch.sqrt(disc.clamp_min(0))
        points = rays_unit * t[..., None]
        z = points[..., 2]
    normals = torch.nn.functional.normalize(points - centre, dim=-1) * inside[..., None]
    return normals, torch.where(inside, z, 0.0), inside


@pytest.mark.parametrize("perspective", [False, True])
def test_integration_recovers_a_sphere_cap(perspective):
    K = (
        torch.tensor([[70.0, 0, 31.5], [0, 70.0, 23.5], [0, 0, 1]], dtype=torch.float64)
        if perspective
        else None
    )
    normals, depth, mask = sphere_cap(K=K)
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(normals, mask, K=K, pixel_size=0.025)
        error = depth_error(result.depth, depth, mask, align="scale" if perspective else "offset")
        assert error.mean_abs < 0.003, (integrate.__name__, error.mean_abs)  # 0.15 % of the sphere's diameter


def dome_on_ground(width: int = 64, height: int = 48) -> PhotometricCapture:
    """A half sphere on a ground plane seen obliquely: its far rim occludes the ground (a depth step)
    while its near side meets the ground, so the step's height is fixed by the visible surface."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    dome = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.vertices[sphere.faces].mean(1)[:, 1] > 0])
    ground = trimesh.Trimesh([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], [[0, 2, 1], [0, 3, 2]])
    scene = trimesh.util.concatenate([dome, ground])
    pose = look_at((0.0, 0.7, -1.3), (0.0, 0.1, 0.0), up=(0, 1, 0))
    return render_photometric(
        Mesh(scene.vertices, scene.faces),
        ring_lights(3, 30.0),
        cam_to_world=pose,
        width=width,
        height=height,
        fov_deg=40,
        shadows=False,
    )[0]


def step_band(depth: torch.Tensor, mask: torch.Tensor, relative_jump: float = 0.03) -> torch.Tensor:
    """Bool[h, w]: pixels within 2 of a neighbour pair whose depths differ by more than `relative_jump`."""
    jump = torch.zeros_like(mask)
    across = (depth[:, 1:] - depth[:, :-1]).abs() > relative_jump * depth[:, 1:]
    jump[:, 1:] |= across
    jump[:, :-1] |= across
    across = (depth[1:] - depth[:-1]).abs() > relative_jump * depth[1:]
    jump[1:] |= across
    jump[:-1] |= across
    return torch.from_numpy(ndimage.binary_dilation(jump.numpy(), iterations=2)) & mask


def test_bilateral_integration_keeps_a_depth_step():
    capture = dome_on_ground()
    band = step_band(capture.depth, capture.mask)
    assert band.sum() > 50
    errors = {}
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(capture.normals, capture.mask, K=capture.K)
        aligned = depth_error(result.depth, capture.depth, capture.mask, align="scale").aligned
        errors[integrate.__name__] = float((aligned - capture.depth).abs()[band].mean())
    assert errors["integrate_bilateral"] <= 0.5 * errors["integrate_least_squares"], errors


def cap_over_wall(h: int = 48, w: int = 64):
    """Orthographic (pixels 0.025 apart): a sphere cap (centre (0, 0, 3), radius 1, seen within 0.5 of
    its axis) in front of a wall at z = 4: normals, depth, mask. The cap's rim occludes the wall: the
    normals hold no trace of the step (a cap sunk into the wall has the same ones)."""
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    x, y = (u - (w - 1) / 2) * 0.025, (v - (h - 1) / 2) * 0.025
    on_cap = x**2 + y**2 < 0.5**2
    cap = torch.stack([x, y, -torch.sqrt((1 - x**2 - y**2).clamp_min(0))], -1)
    wall = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    normals = torch.where(on_cap[..., None], cap, wall.expand_as(cap))
    depth = torch.where(on_cap, 3 + cap[..., 2], 4.0)
    return normals, depth, torch.ones(h, w, dtype=torch.bool)


def test_continuous_pieces_split_at_an_occluding_rim_and_depth_error_aligns_each_piece():
    normals, depth, mask = cap_over_wall()
    pieces = continuous_pieces(depth, normals, mask, pixel_size=0.025)
    x, y = torch.meshgrid(
        (torch.arange(48, dtype=torch.float64) - 23.5) * 0.025,
        (torch.arange(64, dtype=torch.float64) - 31.5) * 0.025,
        indexing="ij",
    )
    on_cap = y**2 + x**2 < 0.5**2
    # two pieces, the wall (the larger) first; only cap pixels whose slope exceeds 3 footprints drop out
    assert set(pieces.unique().tolist()) <= {-1, 0, 1}
    assert (pieces[~on_cap] == 0).all() and (pieces[on_cap] != 0).all() and (pieces[on_cap] == 1).float().mean() > 0.9
    # an estimate right up to a different offset per piece is exact piece by piece, not as a whole
    shifted = depth + torch.where(on_cap, 0.7, -0.3)
    assert depth_error(shifted, depth, mask, align="offset", pieces=pieces).mean_abs < 1e-12
    assert depth_error(shifted, depth, mask, align="offset").mean_abs > 0.3
    # integration recovers each piece's shape (0.1 % of the cap's size); the step between them is lost
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(normals, mask, pixel_size=0.025)
        assert depth_error(result.depth, depth, mask, align="offset", pieces=pieces).mean_abs < 1e-3
        assert depth_error(result.depth, depth, mask, align="offset").mean_abs > 0.5
    # a piece under min_fraction of the mask is dropped; bad shapes are named
    assert (continuous_pieces(depth, normals, mask, pixel_size=0.025, min_fraction=0.5) <= 0).all()
    with pytest.raises(InputError, match="normals' size"):
        continuous_pieces(depth[:, :10], normals, pixel_size=0.025)
    with pytest.raises(InputError, match="pieces must be"):
        depth_error(depth, depth, pieces=pieces[:, :10])


def test_integration_and_depth_error_input_errors():
    with pytest.raises(InputError, match=r"\(h, w, 3\)"):
        integrate_least_squares(torch.zeros(4, 4))
    with pytest.raises(InputError, match="fewer than 2 pixels"):
        integrate_least_squares(torch.zeros(4, 4, 3))
    with pytest.raises(ConfigError, match="align"):
        depth_error(torch.ones(2, 2), torch.ones(2, 2), align="affine")
    normals = torch.tensor([0.0, 0.0, -1.0]).expand(4, 4, 3).clone()
    normals[1, 1] = float("nan")
    for integrate in (integrate_least_squares, integrate_bilateral):
        with pytest.raises(InputError, match="normals hold NaN or inf at 1 masked pixels"):
            integrate(normals)
    K = torch.tensor([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]])
    with pytest.raises(InputError, match="holds NaN or inf"):
        integrate_least_squares(normals[2:], K=K * torch.tensor([[float("nan"), 1, 1], [1, 1, 1], [1, 1, 1]]))
    depth = torch.ones(4, 4)
    depth[0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN or inf inside the mask"):
        depth_error(depth, torch.ones(4, 4))
    with pytest.raises(InputError, match="depth holds NaN or inf"):
        continuous_pieces(depth, normals[[0, 2, 3, 3]], K=K)
    aligned = depth_error(
        2 * torch.ones(3, 3) + torch.eye(3), 4 * torch.ones(3, 3) + 2 * torch.eye(3), align="scale"
    )
    assert aligned.mean_abs < 1e-6 and abs(aligned.scale - 2) < 1e-9


# ---------------------------------------------------------------------------------------------- rig


SPHERE = Sphere(center=(0.0, 0.0, 2.0), radius=0.4)


@pytest.fixture(scope="module")
def sphere_capture() -> PhotometricCapture:
    return render_photometric(
        SPHERE.mesh(5),
        ring_lights(8, 35.0),
        cam_to_world=torch.eye(4),
        width=64,
        height=64,
        fov_deg=30,
        shadows=False,
    )[0]


def test_rig_ground_truth_matches_the_analytic_sphere_and_the_depth_camera(sphere_capture):
    capture = sphere_capture
    assert capture.images.shape == (8, 64, 64) and capture.mask.float().mean() > 0.3
    points = backproject_depth_to_camera(capture.depth[None].double(), capture.K[None].double())[0]
    analytic = torch.nn.functional.normalize(
        points - torch.tensor(SPHERE.center, dtype=torch.float64), dim=-1
    )
    error = angular_error(capture.normals, analytic.float(), capture.mask)
    assert error.mean_deg < 0.1  # interpolated vertex normals of a 5-times subdivided icosphere
    depth, _ = render_depth(SPHERE.mesh(5), capture.K[None].double(), torch.eye(4)[None].double(), 64, 64)
    torch.testing.assert_close(capture.depth, depth[0], atol=1e-5, rtol=0)
    assert ((capture.depth > 0) == capture.mask).all()
    # the rig's images are Lambertian: albedo 0.8 times the clamped cosine with its own normals
    expected = render_lambertian(capture.normals, torch.full((64, 64), 0.8), capture.light_directions)
    torch.testing.assert_close(capture.images, expected, atol=1e-5, rtol=0)


def test_rig_lambertian_least_squares_is_exact_where_every_light_is_on(sphere_capture):
    capture = sphere_capture
    lit = capture.mask & (capture.images > 0).all(0)
    result = least_squares_stereo(capture.images, capture.light_directions, capture.mask)
    assert angular_error(result.normals, capture.normals, lit).mean_deg < 0.01
    # without the clamp of attached shadows (an idealised linear sensor) it is exact everywhere
    linear = render_photometric(
        SPHERE.mesh(5),
        ring_lights(8, 35.0),
        cam_to_world=torch.eye(4),
        width=64,
        height=64,
        fov_deg=30,
        shadows=False,
        attached_shadows=False,
    )[0]
    assert (linear.images < 0).any()
    result = least_squares_stereo(linear.images, linear.light_directions, linear.mask)
    assert angular_error(result.normals, linear.normals, linear.mask).mean_deg < 0.01


def test_rig_cast_shadows_specular_noise_and_quantisation():
    import trimesh

    # a ball floating over a wall: with the light from straight behind the camera there is no cast
    # shadow on the wall in view; with a slanted light the ball shadows part of it
    wall = trimesh.Trimesh([[-2, -2, 3], [2, -2, 3], [2, 2, 3], [-2, 2, 3]], [[0, 1, 2], [0, 2, 3]])
    ball = trimesh.creation.icosphere(3, radius=0.3)
    ball.apply_translation((0, 0, 2.2))
    mesh = Mesh(trimesh.util.concatenate([wall, ball]).vertices, trimesh.util.concatenate([wall, ball]).faces)
    lights = tilted([[0.0, 0.0, -1.0], [0.6, 0.0, -1.0]])
    shadowed = render_photometric(mesh, lights, cam_to_world=torch.eye(4), width=48, height=48, fov_deg=60)[0]
    unshadowed = render_photometric(
        mesh, lights, cam_to_world=torch.eye(4), width=48, height=48, fov_deg=60, shadows=False
    )[0]
    wall_pixels = shadowed.mask & (shadowed.depth > 2.9)
    dark = wall_pixels & (shadowed.images[1] == 0)
    assert dark.sum() > 20 and (unshadowed.images[1][dark] > 0.3).all()
    assert (shadowed.images[0][wall_pixels] == unshadowed.images[0][wall_pixels]).all()
    # a specular lobe brightens the ball where the half vector meets the normal; never the unlit side
    glossy = render_photometric(
        mesh,
        lights,
        cam_to_world=torch.eye(4),
        width=48,
        height=48,
        fov_deg=60,
        specular=SpecularLobe("cook_torrance", strength=1.0, roughness=0.3),
    )[0]
    assert float((glossy.images - shadowed.images).max()) > 0.2
    assert ((glossy.images - shadowed.images)[shadowed.images == 0] == 0).all()
    # noise is repeatable by seed and the images sit on the 8-bit levels
    noisy = [
        render_photometric(
            mesh,
            lights,
            cam_to_world=torch.eye(4),
            width=48,
            height=48,
            fov_deg=60,
            noise_sigma=0.01,
            bits=8,
            seed=s,
        )[0].images
        for s in (3, 3, 4)
    ]
    assert torch.equal(noisy[0], noisy[1]) and not torch.equal(noisy[0], noisy[2])
    levels = noisy[0] * 255
    assert (levels - levels.round()).abs().max() < 1e-4 and noisy[0].min() >= 0 and noisy[0].max() <= 1


def test_rig_robust_stereo_beats_least_squares_on_highlights_and_cast_shadows():
    from neuralsurf.scenes import Torus

    capture = render_photometric(
        Torus().mesh(48),
        cap_lights(24, 45.0),
        cam_to_world=look_at((0.0, -0.9, -0.9), (0, 0, 0)),
        width=48,
        height=48,
        fov_deg=40,
        specular=SpecularLobe("blinn_phong", strength=0.6, shininess=40.0),
    )[0]
    assert ((capture.images == 0) & capture.mask).any()  # shadows (cast and attached)
    ls = angular_error(
        least_squares_stereo(capture.images, capture.light_directions, capture.mask).normals,
        capture.normals,
        capture.mask,
    )
    robust = angular_error(
        robust_stereo(capture.images, capture.light_directions, capture.mask).normals,
        capture.normals,
        capture.mask,
    )
    assert robust.mean_deg <= 0.7 * ls.mean_deg, (robust.mean_deg, ls.mean_deg)


def test_rig_textured_albedo_is_recovered_and_views_are_in_their_camera_frames():
    albedo = checker_albedo(0.2, 0.3, 0.9)
    captures = render_photometric(
        SPHERE.mesh(4), cap_lights(12, 40.0), n_views=2, width=40, height=40, albedo=albedo, shadows=False
    )
    for capture in captures:
        result = robust_stereo(capture.images, capture.light_directions, capture.mask)
        assert angular_error(result.normals, capture.normals, capture.mask).mean_deg < 0.5
        points = backproject_depth_to_camera(capture.depth[None].double(), capture.K[None].double())[0]
        world = points @ capture.cam_to_world[:3, :3].double().T + capture.cam_to_world[:3, 3].double()
        expected = albedo(world)
        solved = result.mask & (result.confidence > 0.99)
        inner = torch.from_numpy(ndimage.binary_erosion(solved.numpy(), iterations=1))
        agree = (result.albedo - expected.float()).abs()[inner] < 0.01
        assert agree.float().mean() > 0.9  # all but pixels whose footprint straddles a checker edge
        # normals face their camera
        assert (capture.normals[capture.mask][:, 2] < 0.05).all()


def test_rig_input_errors():
    with pytest.raises(ConfigError, match="specular model"):
        SpecularLobe("phong")
    with pytest.raises(ConfigError, match="bits"):
        render_photometric(
            SPHERE.mesh(1), ring_lights(3), cam_to_world=torch.eye(4), width=8, height=8, bits=12
        )
    with pytest.raises(InputError, match="non-empty"):
        render_photometric(Mesh(torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.int64)))
    with pytest.raises(ConfigError, match="n must be"):
        ring_lights(2)
