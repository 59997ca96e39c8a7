"""NormalMaps against closed-form oracles: an exact sphere SDF with its analytic normals gives a zero
term, wrong normals or a wrong field a positive one; depth maps of half the resolution place the normals."""

import pytest
import torch

from neuralsurf.cameras import resample_depth
from neuralsurf.errors import InputError
from neuralsurf.observations import DepthRays, NormalMaps, NotObserved
from neuralsurf.scenes import look_at
from neuralsurf.structures import DepthFrames, Normalization
from neuralsurf.training import fit

CENTER, RADIUS = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64), 0.5
EYES = [(2.0, 0.5, 1.0), (-1.5, 1.0, -1.0)]


def intrinsics(width: int, height: int, focal: float) -> torch.Tensor:
    return torch.tensor([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]], dtype=torch.float64)


def sphere_views(width: int, height: int, focal: float, center=CENTER, radius=RADIUS):
    """Closed-form z-depth [v, h, w] and camera-frame outward normals [v, h, w, 3] of the sphere."""
    K = intrinsics(width, height, focal)
    poses = torch.stack([look_at(eye, CENTER) for eye in EYES])
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    camera = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    depths, normals = [], []
    for pose in poses:
        d = camera @ pose[:3, :3].T
        o = pose[:3, 3] - center
        a, b, c = (d * d).sum(-1), 2 * (d * o).sum(-1), float(o @ o) - radius**2
        disc = b**2 - 4 * a * c
        z = torch.where(disc > 0, (-b - disc.clamp_min(0).sqrt()) / (2 * a), 0.0)
        world = (o + z[..., None] * d) / radius  # outward unit normal, world frame
        normals.append(torch.where((z > 0)[..., None], world @ pose[:3, :3], 0.0))  # R^T n
        depths.append(z)
    return torch.stack(depths), torch.stack(normals), K, poses


class ExactSphere(torch.nn.Module):
    def __init__(self, normalization: Normalization, center=CENTER, radius: float = RADIUS):
        super().__init__()
        self.center = normalization.to_unit(torch.as_tensor(center, dtype=torch.float64)).float()
        self.radius = radius / normalization.scale

    def forward(self, x):
        return (x - self.center).norm(dim=-1) - self.radius


def observation(normals=None, **options):
    """Normal maps at 64x48, depth at half that resolution (same poses)."""
    _, exact, K, poses = sphere_views(64, 48, 100.0)
    low = intrinsics(32, 24, 50.0)
    low[0, 2], low[1, 2] = (K[0, 2] + 0.5) / 2 - 0.5, (K[1, 2] + 0.5) / 2 - 0.5
    depth = torch.stack([render_depth_with(low, pose) for pose in poses])
    frames = DepthFrames(depth.float(), low.float().expand(2, 3, 3), poses.float())
    normals = exact if normals is None else normals
    confidence = (normals.norm(dim=-1) > 0).float()
    return NormalMaps(normals.float(), confidence, K.float().expand(2, 3, 3), poses.float(), frames, **options)


def render_depth_with(K, pose, center=CENTER, radius=RADIUS):
    v, u = torch.meshgrid(torch.arange(24, dtype=torch.float64), torch.arange(32, dtype=torch.float64), indexing="ij")
    camera = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    d = camera @ pose[:3, :3].T
    o = pose[:3, 3] - center
    a, b, c = (d * d).sum(-1), 2 * (d * o).sum(-1), float(o @ o) - radius**2
    disc = b**2 - 4 * a * c
    return torch.where(disc > 0, (-b - disc.clamp_min(0).sqrt()) / (2 * a), 0.0)


def term(obs: NormalMaps, model_of) -> float:
    normalization = Normalization.from_points(obs.bounds())
    sampler = obs.prepare(normalization, 0.55, torch.device("cpu"), 0)
    batch = sampler.sample(torch.Generator().manual_seed(0))
    return float(sampler.losses(model_of(normalization), batch)["normal"].detach())


def test_back_projected_pixels_lie_on_the_sphere_with_its_normals():
    obs = observation()
    pixels = obs._world()
    radial = (pixels.points - CENTER).norm(dim=-1)
    assert len(pixels.points) > 1000
    # bilinear depth between pixels of half the resolution: close to the surface, not exact
    assert float((radial - RADIUS).abs().max()) < 0.01 * RADIUS
    outward = torch.nn.functional.normalize(pixels.points - CENTER, dim=-1)
    assert float((outward * pixels.normals).sum(-1).min()) > 0.999


def test_exact_sphere_sdf_with_analytic_normals_gives_zero_and_wrong_ones_do_not():
    obs = observation(n_pixels=4096)
    assert term(obs, ExactSphere) < 1e-4
    # a wrong field: the sphere moved sideways by half its radius
    moved = CENTER + torch.tensor([0.25, 0.0, 0.0], dtype=torch.float64)
    assert term(obs, lambda n: ExactSphere(n, moved)) > 0.02
    # wrong normals: the analytic ones flipped (inward) give the maximum, 2
    _, exact, _, _ = sphere_views(64, 48, 100.0)
    assert term(observation(-exact, n_pixels=4096), ExactSphere) == pytest.approx(2.0, abs=1e-3)


def test_confidence_weights_the_term():
    _, exact, _, _ = sphere_views(64, 48, 100.0)
    wrong = exact.clone()
    wrong[:, :, :32] = -wrong[:, :, :32]  # left half of every view flipped
    half = observation(wrong, n_pixels=4096)
    flipped = (half.normals.norm(dim=-1) > 0) & (torch.arange(64) < 32)
    trusted = NormalMaps(half.normals, torch.where(flipped, 0.0, half.confidence), half.K, half.cam_to_world,
                         half.depth, n_pixels=4096)
    assert term(half, ExactSphere) > 0.5
    assert term(trusted, ExactSphere) < 1e-4


def test_resample_depth_of_a_fronto_parallel_plane_is_exact_and_gaps_stay_missing():
    K = intrinsics(64, 48, 100.0)
    low = intrinsics(32, 24, 50.0)
    low[0, 2], low[1, 2] = (K[0, 2] + 0.5) / 2 - 0.5, (K[1, 2] + 0.5) / 2 - 0.5
    depth = torch.full((24, 32), 1.5)
    depth[10:12, 10:12] = 0  # a hole
    up = resample_depth(depth, low, K, 48, 64)
    valid = up > 0
    assert torch.allclose(up[valid], torch.tensor(1.5))
    assert valid.float().mean() > 0.8 and not valid[22, 22]  # next to the hole (low 10.75..11.25)


def test_mismatched_poses_and_missing_data_are_clear_errors():
    obs = observation()
    frames = DepthFrames(obs.depth.depth[:1], obs.depth.K[:1], obs.depth.cam_to_world[:1])
    with pytest.raises(InputError, match="same camera pose"):
        NormalMaps(obs.normals, obs.confidence, obs.K, obs.cam_to_world, frames).bounds()

    class NoNormals:
        name, normal_maps, photometric, frames, depth_input = "x", None, None, None, False

    with pytest.raises(NotObserved):
        NormalMaps.from_scene(NoNormals())


@pytest.mark.slow
def test_depth_rays_and_normal_maps_fit_together():
    from neuralsurf.models import SDFMLP, HashGrid

    obs = observation(n_pixels=256)
    rays = DepthRays(obs.depth, noise_model="constant", sigma=0.001, n_rays=256, n_uniform=256, n_carve=2000)
    model = SDFMLP(encoding=HashGrid(levels=4, log2_table_size=12, max_resolution=64), width=32, depth=2, skip_layers=[], weight_norm=False)
    result = fit(model, [rays, obs], steps=20, device="cpu", seed=0, progress=False, log_every=10,
                 image_every=0)
    normal = result.history["normals/normal"]
    assert all(torch.isfinite(torch.tensor(normal))) and "rays/surface" in result.history
    assert normal[-1] < normal[0]
