"""Depth rays and the observation contract against closed-form oracles: ray-sphere hits, exact sphere SDFs."""

import math
import warnings

import pytest
import torch
from small_models import tiny_model

from neuralsurf.cameras import depth_rays
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.observations import DepthRays, PointSamples
from neuralsurf.observations.rays import box_entry, carve_labels, denoise_hits, ray_terms, winding_labels
from neuralsurf.scenes import Sphere, look_at
from neuralsurf.structures import DepthFrames, Normalization
from neuralsurf.training import fit

CENTER, RADIUS = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64), 0.5
K = torch.tensor([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])


def sphere_frames(eyes, width: int = 64, height: int = 48, targets=None, focal: float = 60.0) -> DepthFrames:
    """Closed-form z-depth of the sphere: the nearer root of |o + t d - c| = r along each pixel's ray
    (K of a 64x48 image with fx = fy = `focal`, scaled to width x height); from inside the sphere (a
    room), the farther root.
    Each camera looks at the sphere's centre, or at its entry of `targets`."""
    poses = torch.stack([look_at(eye, CENTER if targets is None else target)
                         for eye, target in zip(eyes, targets or eyes)])
    f = focal * width / 64
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    camera = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    depths = []
    for pose in poses:
        d = camera @ pose[:3, :3].T  # world direction per unit z
        o = pose[:3, 3] - CENTER
        a, b, c = (d * d).sum(-1), 2 * (d * o).sum(-1), float(o @ o) - RADIUS**2
        disc = b**2 - 4 * a * c
        inside = c < 0  # the camera is inside the sphere: it sees the far side
        z = (-b + (1 if inside else -1) * disc.clamp_min(0).sqrt()) / (2 * a)
        depths.append(torch.where(disc > 0, z, 0.0))
    return DepthFrames(torch.stack(depths).float(), K, poses.float())


class ExactSphere(torch.nn.Module):
    """The sphere's SDF in a unit frame."""

    def __init__(self, normalization: Normalization, radius: float = RADIUS, shift=(0.0, 0.0, 0.0)):
        super().__init__()
        self.center = normalization.to_unit(CENTER + torch.tensor(shift, dtype=torch.float64)).float()
        self.radius = radius / normalization.scale

    def forward(self, x):
        return (x - self.center).norm(dim=-1) - self.radius


def prepared(frames, **options):
    """Rays of exact hits for the term oracles: no denoising (it has its own test) unless asked."""
    observation = DepthRays(frames, noise_model="constant", sigma=0.001, **{"denoise_k": 0, **options})
    normalization = Normalization.from_points(observation.bounds())
    return observation, normalization, observation.prepare(normalization, 0.55, torch.device("cpu"), 0)


def test_rays_hit_the_sphere_where_ray_sphere_intersection_says():
    frames = sphere_frames([(2.0, 0.5, 1.0), (-1.5, 1.0, -1.0)])
    rays = depth_rays(frames, lambda z: torch.full_like(z, 0.001))
    assert len(rays.hit) == int((frames.depth > 0).sum()) > 1000
    assert torch.allclose(rays.directions.norm(dim=-1), torch.ones(len(rays.hit)), atol=1e-6)
    hits = rays.origins.double() + rays.hit[:, None].double() * rays.directions.double()
    assert ((hits - CENTER).norm(dim=-1) - RADIUS).abs().max() < 1e-5
    # the depth map's normals are the sphere's: |cos| between ray and normal from the geometry
    normal = (hits - CENTER) / RADIUS
    expected = (normal * rays.directions.double()).sum(-1).abs()
    interior = rays.cosine > 0.3  # away from the limb, where one-sided differences are coarse
    assert (rays.cosine.double() - expected)[interior].abs().median() < 0.01
    # the normals themselves point outwards, their length is the confidence 1 / (1 + (sigma / spacing)^2)^2
    length = rays.normals.norm(dim=-1)
    known = length > 0  # isolated pixels have no normal
    assert (length <= 1).all() and known.float().mean() > 0.95
    assert (length[interior & known] > 0.9).all()  # 1 mm noise against ~3 cm pixels
    outward = (rays.normals.double() / length[:, None].clamp_min(1e-12) * normal).sum(-1)
    assert outward[interior & known].median() > 0.999


AROUND = [(2.2, 0.3, 0.1), (-1.8, 0.1, 0.4), (0.3, 2.0, 0.2), (0.1, -2.0, 0.5), (0.4, 0.2, 2.1), (-0.2, -0.3, -1.6)]


def test_denoising_moves_noisy_hits_along_their_rays_onto_the_sphere():
    from dataclasses import replace

    rays = depth_rays(sphere_frames(AROUND[:4], width=128, height=96), lambda z: torch.full_like(z, 0.005))

    def radial_error(rays):
        hits = rays.origins.double() + rays.hit[:, None].double() * rays.directions.double()
        return ((hits - CENTER).norm(dim=-1) - RADIUS).abs()

    # exact hits stay where they are: a sphere is a quadric to fourth order in the neighbourhood's radius
    assert radial_error(denoise_hits(rays, 30)).median() < 1e-4
    noise = 0.005 * torch.randn(len(rays.hit), generator=torch.Generator().manual_seed(0))
    noisy = replace(rays, hit=rays.hit + noise)
    denoised = denoise_hits(noisy, 30)
    assert radial_error(denoised).mean() < 0.4 * radial_error(noisy).mean()
    assert torch.equal(denoised.origins, noisy.origins) and torch.equal(denoised.directions, noisy.directions)
    assert ((denoised.hit - noisy.hit).abs() <= 3 * noisy.sigma + 1e-6).all()  # at most 3 sigmas along the ray


def test_space_carving_labels_agree_with_the_sphere():
    frames = sphere_frames(AROUND)
    points = CENTER + (2 * torch.rand(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) - 1)
    bounds = torch.stack([CENTER - RADIUS, CENTER + RADIUS])
    labels = carve_labels(points, frames, band=0.01, sigma_of_depth=lambda z: torch.zeros_like(z), bounds=bounds)
    distance = (points - CENTER).norm(dim=-1) - RADIUS
    assert (labels == 1).sum() > 2000 and (labels == -1).sum() > 0.3 * (distance < 0).sum()
    assert not ((distance > 0) & (labels == -1)).any()
    # a point is compared with the reading of the nearest pixel centre: near the limb that reading can
    # lie a pixel footprint (about 0.01 here) farther than the point's own ray would see
    assert not ((distance < -0.01) & (labels == 1)).any()


def test_winding_labels_agree_with_the_sphere_seen_from_outside_and_from_within():
    points = CENTER + 1.2 * (2 * torch.rand(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) - 1)
    distance = (points - CENTER).norm(dim=-1) - RADIUS
    rays = depth_rays(sphere_frames(AROUND), lambda z: torch.full_like(z, 0.001))
    labels = winding_labels(points.float(), rays, 3000)
    assert (labels[distance > 0] == 1).float().mean() > 0.8 and (labels[distance < 0] == -1).float().mean() > 0.5
    assert not ((distance > 0) & (labels == -1)).any() and not ((distance < 0) & (labels == 1)).any()
    # a room: cameras inside the sphere looking out at all of its wall (106 degree views along the six
    # axes); their side, inside the sphere, is free
    axes = torch.cat([torch.eye(3), -torch.eye(3)]).double()
    eyes = [tuple((CENTER + 0.05 * a).tolist()) for a in axes]
    targets = [tuple((CENTER + a + 0.01 * a.roll(1)).tolist()) for a in axes]
    room = depth_rays(sphere_frames(eyes, 96, 96, targets, focal=24.0), lambda z: torch.full_like(z, 0.001))
    labels = winding_labels(points.float(), room, 3000)
    assert (labels[distance < 0] == 1).float().mean() > 0.5 and (labels[distance > 0] == -1).float().mean() > 0.5
    assert not ((distance > 0) & (labels == 1)).any() and not ((distance < 0) & (labels == -1)).any()
    # a part of the wall alone winds around nothing: no label
    assert (winding_labels(points.float(), depth_rays(sphere_frames(eyes[:2], 96, 96, targets[:2], focal=24.0),
                                                      lambda z: torch.full_like(z, 0.001)), 3000) == 0).all()


@pytest.mark.parametrize("hit_fraction", [0.0, 1.0])
def test_each_ray_term_is_about_zero_for_the_exact_sdf_and_positive_for_a_wrong_radius(hit_fraction):
    frames = sphere_frames(AROUND)
    # carve signs only: with a margin, the distance to the nearest hit overestimates the exact one (test below)
    observation, normalization, sampler = prepared(frames, hit_fraction=hit_fraction, winding_points=2000,
                                                    carve_margin=0.0)
    expected_hits = max(min(round(hit_fraction * len(sampler.rays.hit)), 4096) - 1024, 0)  # beyond the 1024 rays
    assert sampler.n_hits == expected_hits and (hit_fraction == 0 or expected_hits > 500)
    batch = sampler.sample(torch.Generator().manual_seed(0))
    exact = ray_terms(ExactSphere(normalization), batch, observation.weights)
    assert set(exact) == {"surface", "band", "free", "carve", "normal", "eikonal"}
    assert exact["surface"] < 1e-5 and exact["free"] < 1e-6 and exact["eikonal"] < 1e-6
    assert exact["normal"] < 2e-3  # finite-difference normals of the depth map vs the sphere's
    shifted = ray_terms(ExactSphere(normalization, shift=(0.0, 0.05, 0.0)), batch, observation.weights)
    assert shifted["normal"] > 5 * exact["normal"]
    assert exact["carve"] < 1e-4  # only labels within a pixel footprint of the limb can be off
    assert exact["band"] < 0.02 * float(sampler.band.mean())  # projected-distance target vs. a curved surface
    wrong = ray_terms(ExactSphere(normalization, radius=0.45), batch, observation.weights)
    assert wrong["surface"].item() == pytest.approx(0.05 / normalization.scale, rel=0.02)
    assert wrong["band"] > 10 * exact["band"]
    larger = ray_terms(ExactSphere(normalization, radius=0.55), batch, observation.weights)
    assert larger["free"] > 1e-3 and larger["carve"] > 1e-3  # a surface in seen free space
    assert wrong["carve"] > 1e-3  # a hollow where the views say inside


def test_box_entry_is_where_rays_cross_the_cube():
    origins = torch.tensor([[-2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 3.0, 0.1]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    assert torch.allclose(box_entry(origins, directions, 0.5), torch.tensor([1.5, 0.0, 2.5]))


def test_missing_pixels_are_skipped_and_all_missing_is_a_clear_error():
    frames = sphere_frames([(2.0, 0.5, 1.0)])
    rays = depth_rays(frames)
    assert len(rays.hit) == int((frames.depth > 0).sum()) < frames.depth.numel()
    empty = DepthFrames(torch.zeros(1, 48, 64), K, frames.cam_to_world)
    with pytest.raises(InputError, match="missing"):
        DepthRays(empty).bounds()
    with pytest.raises(ConfigError, match="no loss term"):
        DepthRays(frames, weights={"surfaec": 1.0})
    for bad in ({"hit_fraction": -0.1}, {"carve_margin": -1.0}, {"winding_points": 0.5}, {"max_hits": -1},
                {"denoise_k": 3}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            DepthRays(frames, **bad)


FINE = {"depth": 2, "levels": 6, "log2_table_size": 14, "max_resolution": 96}
"""tiny_model with a finer grid: two views of a sphere fitted to 1 % of its radius."""


def test_a_fit_of_two_depth_views_recovers_the_sphere_radius_within_one_percent():
    frames = sphere_frames([(2.0, 0.5, 1.0), (-1.5, 1.0, -1.0)], width=96, height=72)
    observation = DepthRays(frames, n_rays=512, noise_model="constant", sigma=0.001)
    result = fit(tiny_model(**FINE), observation, steps=250, device="cpu", progress=False, image_every=0)
    # radius along rays through the centre towards both cameras (the seen caps)
    seen = depth_rays(frames, lambda z: torch.full_like(z, 1e-3))
    towards = torch.nn.functional.normalize(seen.origins.double()[[0, -1]] - CENTER, dim=-1)
    t = torch.linspace(0.3, 0.7, 4001, dtype=torch.float64)
    for direction in towards:
        values = result.field((CENTER + t[:, None] * direction).float()).detach()
        crossing = float(t[int((values > 0).nonzero()[0])])
        assert crossing == pytest.approx(RADIUS, rel=0.01)


def test_a_fit_sums_the_terms_of_two_observations():
    frames = sphere_frames([(2.0, 0.5, 1.0), (-1.5, 1.0, -1.0)])
    cloud = Sphere(center=tuple(CENTER.tolist()), radius=RADIUS).sample_surface(2000, seed=0)
    observations = [DepthRays(frames, n_rays=128), PointSamples(cloud, batch_size=256, n_near=4000, n_free=1000)]
    result = fit(tiny_model(**FINE), observations, steps=30, device="cpu", progress=False, image_every=0, log_every=10)
    history = result.history
    assert {"rays/surface", "rays/band", "rays/free", "points/surface", "points/sdf"} <= set(history)
    recomputed = sum(observations[0].weights[k.split("/")[1]] * history[k][-1] for k in history if k.startswith("rays/"))
    recomputed += sum(observations[1].weights[k.split("/")[1]] * history[k][-1] for k in history if k.startswith("points/"))
    assert history["total"][-1] == pytest.approx(recomputed, rel=1e-5)
    assert history["total"][-1] < history["total"][0]
    with pytest.raises(ConfigError, match="distinct names"):
        fit(tiny_model(**FINE), [observations[1], observations[1]], steps=1, device="cpu", progress=False)
    assert math.isfinite(history["total"][-1])


def test_an_unoriented_noisy_cloud_is_projected_onto_its_local_quadrics_and_an_oriented_one_is_not():
    """Oracle: the sphere's radius. Without normals, `denoise` (the default) moves the noisy points
    towards the sphere; with given normals the points are kept as they are."""
    from neuralsurf.observations.points import prepare_cloud
    from neuralsurf.structures import PointCloud

    g = torch.Generator().manual_seed(0)
    direction = torch.nn.functional.normalize(torch.randn(20_000, 3, generator=g, dtype=torch.float64), dim=1)
    noisy = CENTER + direction * (RADIUS + 0.005 * torch.randn(20_000, 1, generator=g, dtype=torch.float64))
    error = lambda cloud: ((cloud.points - CENTER).norm(dim=1) - RADIUS).abs().mean()
    projected = prepare_cloud(PointCloud(noisy), "estimate", 30, denoise=True)
    assert error(projected) < error(PointCloud(noisy)) / 2
    assert ((projected.normals * direction).sum(1) > 0.9).all()  # outward, like the sphere's
    kept = prepare_cloud(PointCloud(noisy, normals=direction), "estimate", 30, denoise=True)
    assert torch.equal(kept.points, noisy)
    assert PointSamples(PointCloud(noisy)).denoise  # the default for unoriented input


@pytest.mark.parametrize("flipped", [0.5, 0.2])
def test_unoriented_normals_are_made_consistent_with_a_warning_and_oriented_ones_are_kept(flipped):
    """Oracle: the sphere's outward normals. A share of them flipped at random (normals estimated and saved without
    orientation) come back outward; normals='given' keeps them as they are."""
    from neuralsurf.geometry import opposed_share
    from neuralsurf.observations.points import UNORIENTED, prepare_cloud

    cloud = Sphere(center=(0.1, -0.2, 0.05), radius=0.4).sample_surface(20_000, seed=0)
    signs = torch.where(torch.rand(20_000, 1, generator=torch.Generator().manual_seed(1)) < flipped, -1.0, 1.0)
    unoriented = cloud.with_normals(signs.double() * cloud.normals)
    assert opposed_share(cloud.points, cloud.normals) == 0 < UNORIENTED < opposed_share(unoriented.points,
                                                                                         unoriented.normals)
    with pytest.warns(UserWarning, match="point against most of their neighbours'"):
        repaired = prepare_cloud(unoriented, "estimate", 30)
    assert torch.allclose(repaired.normals, cloud.normals)
    assert torch.allclose(prepare_cloud(unoriented, "given", 30).normals, unoriented.normals)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.allclose(prepare_cloud(cloud, "estimate", 30).normals, cloud.normals)


class ScaledSDF(torch.nn.Module):
    """A field of the right sign everywhere but `factor` times too flat: what lets bubbles pop up."""

    def __init__(self, field: torch.nn.Module, factor: float):
        super().__init__()
        self.field, self.factor = field, factor

    def forward(self, x):
        return self.factor * self.field(x)


def test_the_carve_margin_asks_labelled_points_for_distance_not_only_for_sign():
    frames = sphere_frames(AROUND)
    observation, normalization, sampler = prepared(frames, carve_margin=0.5)
    signs_only = prepared(frames, carve_margin=0.0)[2]
    batch = sampler.sample(torch.Generator().manual_seed(0))
    plain = signs_only.sample(torch.Generator().manual_seed(0))
    assert torch.equal(batch.uniform, plain.uniform) and (plain.uniform_margin == 0).all()
    labelled = batch.uniform_label != 0
    assert (batch.uniform_margin[labelled] > 0).float().mean() > 0.99 and (batch.uniform_margin[~labelled] == 0).all()
    exact, flat = ExactSphere(normalization), ScaledSDF(ExactSphere(normalization), 0.1)
    # the margin (half the distance to the nearest hit) is at most the true distance where hits are dense
    assert ray_terms(exact, batch, observation.weights)["carve"] < 2e-4
    assert ray_terms(flat, plain, observation.weights)["carve"] < 1e-4  # the signs alone are right
    assert ray_terms(flat, batch, observation.weights)["carve"] > 0.02
