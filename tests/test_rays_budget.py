"""Depth rays sized to the capture: the pixel stride chosen for a ray budget, against counted oracles."""

import math
import warnings

import pytest
import torch

from neuralsurf.cameras import Rays, depth_rays, stride_frames
from neuralsurf.errors import ConfigError
from neuralsurf.observations import DepthRays
from neuralsurf.observations.rays import budget_stride, strided_count
from neuralsurf.scenes import look_at
from neuralsurf.structures import DepthFrames, Normalization

HEIGHT, WIDTH = 48, 64


def wall_frames(n_views: int = 3, height: int = HEIGHT, width: int = WIDTH) -> DepthFrames:
    """Cameras 2 m in front of the plane z = 0, looking at it from slightly different places: every pixel
    reads the plane, except the missing column band 10..19 (depth 0, as a sensor's dropouts)."""
    eyes = [torch.tensor([0.1 * i, -0.05 * i, 2.0], dtype=torch.float64) for i in range(n_views)]
    poses = torch.stack([look_at(eye, eye * torch.tensor([1.0, 1.0, 0.0])) for eye in eyes]).float()
    f = 50.0 * width / 64
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    depth = torch.full((n_views, height, width), 2.0)
    depth[:, :, 10:20] = 0
    return DepthFrames(depth, K, poses)


def counted(n_views: int, stride: int) -> int:
    """Oracle: valid pixels of `wall_frames` at `stride`: rows ceil(48 / s) times the kept columns
    0, s, 2s, ... outside 10..19."""
    columns = sum(1 for c in range(0, WIDTH, stride) if not 10 <= c < 20)
    return n_views * math.ceil(HEIGHT / stride) * columns


@pytest.mark.parametrize("stride", [1, 2, 3, 5, 64])
def test_strided_count_is_the_valid_pixels_at_that_stride(stride):
    assert strided_count(wall_frames().depth, stride) == counted(3, stride)


def test_budget_stride_is_the_smallest_stride_that_fits():
    depth = wall_frames().depth
    for stride in (1, 2, 3, 4, 7):
        budget = counted(3, stride)
        assert budget_stride(depth, budget) == stride  # exactly at the budget: it fits
        assert budget_stride(depth, budget - 1) > stride
        assert strided_count(depth, budget_stride(depth, budget - 1)) <= budget - 1
    assert budget_stride(depth, 10**9, min_stride=3) == 3  # a stride asked for is never lowered
    assert budget_stride(depth, counted(3, 4), min_stride=2) == 4


def test_sizes_of_the_suite_scenes_under_the_default_budget():
    """The 24 synthetic 320x240 bunny views keep every pixel; 90 frames of 640x480 (a room) get every 4th."""
    budget = DepthRays.__dataclass_fields__["max_rays"].default
    assert budget_stride(torch.ones(24, 240, 320), budget) == 1
    assert budget_stride(torch.ones(90, 480, 640), budget) == 4  # every 3rd: 90 * 160 * 214 > 2e6 rays


def test_rays_under_budget_are_every_pixel_and_no_warning():
    frames = wall_frames()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        observation = DepthRays(frames, max_rays=counted(3, 1))
        rays = observation.world_rays
    assert observation.stride == 1
    expected = depth_rays(frames)
    for name in Rays.__dataclass_fields__:
        assert torch.equal(getattr(rays, name), getattr(expected, name)), name


def test_rays_over_budget_are_the_full_frames_rays_of_the_strided_pixels_with_one_warning():
    frames = wall_frames()
    observation = DepthRays(frames, max_rays=counted(3, 2) - 1, n_carve=2000, winding_points=0, denoise_k=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        normalization = Normalization.from_points(observation.bounds())
        sampler = observation.prepare(normalization, 0.55, torch.device("cpu"), 0)
    assert len(caught) == 1 and caught[0].category is UserWarning
    message = str(caught[0].message)
    assert "pixel_stride=3" in message and "max_rays" in message and f"{counted(3, 3):,} rays" in message
    assert len(sampler.rays.hit) == counted(3, 3)
    # oracle: the rays of every pixel, kept at rows and columns 0, 3, 6, ... (normals from full-resolution
    # neighbours, so the missing band's edge columns keep theirs)
    full = depth_rays(frames)
    rows, cols = torch.meshgrid(torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    valid = frames.depth > 0
    kept = (valid & (rows % 3 == 0) & (cols % 3 == 0))[valid]
    rays = observation.world_rays
    for name in Rays.__dataclass_fields__:
        torch.testing.assert_close(getattr(rays, name), getattr(full, name)[kept], atol=1e-6, rtol=0, msg=name)
    # the same rays as the strided frames' (`stride_frames`), but for the normals' neighbours
    strided = depth_rays(stride_frames(frames, 3))
    for name in ("origins", "directions", "hit", "sigma"):
        torch.testing.assert_close(getattr(rays, name), getattr(strided, name), atol=1e-6, rtol=0, msg=name)


def test_a_budget_below_one_ray_per_frame_is_named():
    with pytest.raises(ConfigError, match="max_rays=2 is fewer than one ray per frame"):
        DepthRays(wall_frames(), max_rays=2).bounds()
    with pytest.raises(ConfigError, match="max_rays"):
        DepthRays(wall_frames(), max_rays=0)
