"""A synthetic depth camera: exact z-depth of a mesh by ray casting, with sensor noise models.

Cameras follow the project's contract (OpenCV pinhole: x right, y down, z forward; `K` 3x3,
`cam_to_world` 4x4; pixel centres at integer coordinates). Depth is z-depth in metres, float32,
0 where the ray misses. Noise models:

- ``"none"``: exact depth (float32 rounding of Open3D's float32 ray caster).
- ``"gaussian"``: z + N(0, sigma^2), sigma in metres.
- ``"kinect"``: Kinect v1 as measured by Nguyen, Izadi & Lovell (3DIMPVT 2012): axial noise
  sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 metres, plus dropout where the ray meets the surface at
  a grazing angle (angle to the normal above `max_angle_deg`) and next to depth discontinuities
  (a 4-neighbour that misses or whose depth differs by more than `edge_jump` * z).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from neuralsurf.cameras import kinect_sigma, render_depth
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.strategies import choose, names, register
from neuralsurf.structures import DepthFrames, Mesh, check_intrinsics


def fibonacci_sphere(n: int) -> Tensor:
    """Float64[Tensor, "n 3"]: n nearly uniform unit directions (golden-angle spiral, z from +1 to -1)."""
    i = torch.arange(n, dtype=torch.float64)
    z = 1 - (2 * i + 1) / n
    radius = torch.sqrt(1 - z**2)
    phi = i * math.pi * (3 - math.sqrt(5))
    return torch.stack([radius * torch.cos(phi), radius * torch.sin(phi), z], -1)


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> Tensor:
    """Float64[Tensor, "4 4"]: OpenCV cam_to_world of a camera at `eye` looking at `target`.

    The image's y axis (down) points along -`up` as far as possible; when the view direction is
    (nearly) parallel to `up`, world z (or x) stands in for it.
    """
    eye, target = (torch.as_tensor(v, dtype=torch.float64).reshape(3) for v in (eye, target))
    forward = target - eye
    if float(forward.norm()) == 0:
        raise InputError(f"look_at needs eye != target, both are {eye.tolist()}")
    forward = forward / forward.norm()
    up = torch.as_tensor(up, dtype=torch.float64).reshape(3)
    for candidate in (
        up,
        torch.tensor([0.0, 0, 1], dtype=torch.float64),
        torch.tensor([1.0, 0, 0], dtype=torch.float64),
    ):
        down = -(candidate - (candidate @ forward) * forward)
        if float(down.norm()) > 1e-6 * float(candidate.norm()):
            break
    down = down / down.norm()
    right = torch.linalg.cross(down, forward)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def intrinsics_from_fov(width: int, height: int, fov_deg: float) -> Tensor:
    """Float64[Tensor, "3 3"]: square-pixel K with vertical field of view `fov_deg`, centred image."""
    focal = (height / 2) / math.tan(math.radians(fov_deg) / 2)
    return torch.tensor(
        [[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]], dtype=torch.float64
    )


def orbit_cameras(
    center, radius: float, n_views: int, fov_deg: float, aspect: float, distance: float | None = None
) -> Tensor:
    """Float64[Tensor, "n 4 4"]: cameras on a Fibonacci sphere around `center`, looking at it.

    The default distance puts the bounding sphere (`radius`) just inside the narrower field of
    view (vertical `fov_deg`, horizontal from `aspect` = width / height), so the object fills it.
    """
    center = torch.as_tensor(center, dtype=torch.float64).reshape(3)
    if distance is None:
        half_v = math.radians(fov_deg) / 2
        half = min(half_v, math.atan(math.tan(half_v) * aspect))
        distance = radius / math.sin(half)
    return torch.stack([look_at(center + distance * d, center) for d in fibonacci_sphere(n_views)])


ONE_VIEW_IMAGE = {"width": 160, "height": 120, "fov_deg": 50.0}
"""The image of a one-view camera (the shapes_one_view scene's, and the OccNet's one-sided training views)."""


def one_view_camera(seed: int, distance: float = 1.6) -> Tensor:
    """Float64[Tensor, "4 4"] cam_to_world looking at the origin from a random azimuth and an elevation
    of 0.2 to 0.6 rad (from above, as a person sees a chair, mug or lamp) at `distance`."""
    rng = np.random.default_rng(seed)
    azimuth, elevation = rng.uniform(0, 2 * math.pi), rng.uniform(0.2, 0.6)
    eye = distance * np.array([math.cos(azimuth) * math.cos(elevation), math.sin(elevation),
                               math.sin(azimuth) * math.cos(elevation)])
    return torch.as_tensor(look_at(eye, (0.0, 0.0, 0.0)), dtype=torch.float64)


def depth_edges(depth: Tensor, edge_jump: float) -> Tensor:
    """Bool[Tensor, "n h w"]: valid pixels with a 4-neighbour that is invalid or whose depth differs by
    more than `edge_jump` times the pixel's depth (pixels on the image border count their outside
    neighbours as valid)."""
    padded = torch.nn.functional.pad(depth[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    h, w = depth.shape[1:]
    edge = torch.zeros_like(depth, dtype=torch.bool)
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        other = padded[:, 1 + dv : 1 + dv + h, 1 + du : 1 + du + w]
        edge |= (other <= 0) | ((other - depth).abs() > edge_jump * depth)
    return edge & (depth > 0)


@register("depth noise", "none")
def no_noise(depth: Tensor, cosine: Tensor, generator: torch.Generator, sigma: float, max_angle_deg: float,
             edge_jump: float) -> Tensor:
    """The exact depth Float[Tensor, "n h w"] (0: no reading), unchanged."""
    return depth


@register("depth noise", "gaussian")
def gaussian_noise(depth: Tensor, cosine: Tensor, generator: torch.Generator, sigma: float, max_angle_deg: float,
                   edge_jump: float) -> Tensor:
    """Depth Float[Tensor, "n h w"] plus N(0, sigma^2) drawn from `generator` (readings pushed to or
    below 0 are dropped)."""
    if not sigma > 0:
        return depth
    noisy = depth + sigma * torch.randn(depth.shape, generator=generator)
    return torch.where((depth > 0) & (noisy > 0), noisy, 0.0)


@register("depth noise", "kinect")
def kinect_noise(depth: Tensor, cosine: Tensor, generator: torch.Generator, sigma: float, max_angle_deg: float,
                 edge_jump: float) -> Tensor:
    """Kinect v1 (module docstring): depth Float[Tensor, "n h w"] dropped where the ray meets the
    surface more obliquely than `max_angle_deg` (`cosine`: of that angle, per pixel) or next to a
    jump of `edge_jump` * z, plus axial noise of `kinect_sigma(z)` drawn from `generator`."""
    if not 0 < max_angle_deg <= 90:
        raise ConfigError(f"max_angle_deg must lie in (0, 90], got {max_angle_deg}")
    if not edge_jump > 0:
        raise ConfigError(f"edge_jump must be a positive fraction of the depth, got {edge_jump}")
    drop = depth_edges(depth, edge_jump) | (cosine < math.cos(math.radians(max_angle_deg)))
    noisy = depth + kinect_sigma(depth) * torch.randn(depth.shape, generator=generator)
    return torch.where((depth > 0) & ~drop & (noisy > 0), noisy, 0.0)


NOISE_MODELS = names("depth noise")
"""The depth noise models by name: `scan_depth(noise=...)` (or pass a function of the same signature)."""


def scan_depth(
    mesh: Mesh,
    n_views: int = 24,
    width: int = 320,
    height: int = 240,
    fov_deg: float = 60.0,
    distance: float | None = None,
    noise: str = "none",
    sigma: float | None = None,
    seed: int = 0,
    cam_to_world=None,
    K=None,
    *,
    max_angle_deg: float = 75.0,
    edge_jump: float = 0.03,
) -> DepthFrames:
    """Synthetic depth images of `mesh` from cameras around it (or given ones).

    Args:
        mesh: the scanned object, non-empty Mesh in metres (world frame).
        n_views: number of cameras on a Fibonacci sphere of view directions around the centre of
            the mesh's bounding box, looking at it (ignored when `cam_to_world` is given).
        width, height: image size in pixels.
        fov_deg: vertical field of view, used when `K` is None (square pixels, centred).
        distance: camera distance from the box centre; default: the sphere around the box centre
            through the farthest vertex just fits the narrower field of view, so the object fills
            the images as far as it can while staying whole from every direction.
        noise: "none", "gaussian" or "kinect" (see the module docstring), or a function with the
            signature of `gaussian_noise`.
        sigma: standard deviation in metres of "gaussian" noise (default 1 mm); only for "gaussian".
        seed: seed of the noise (the same seed gives the same frames).
        cam_to_world: Float[Tensor, "n 4 4"] (or 4x4) OpenCV poses to use instead of the orbit.
        K: Float[Tensor, "3 3"] or "n 3 3" intrinsics to use instead of `fov_deg`.
        max_angle_deg: "kinect" drops pixels whose ray meets the surface more obliquely than this.
        edge_jump: "kinect" drops pixels next to a depth jump larger than this fraction of the depth.
    Returns:
        DepthFrames with depth (n, height, width) float32 metres (0 = no reading), K, cam_to_world.
    """
    if not isinstance(mesh, Mesh) or mesh.is_empty:
        raise InputError(
            f"scan_depth needs a non-empty neuralsurf Mesh, got {type(mesh).__name__}"
            + (" without faces" if isinstance(mesh, Mesh) else "")
        )
    if isinstance(noise, str) and noise not in NOISE_MODELS:
        raise ConfigError(f"noise must be one of {NOISE_MODELS}, got {noise!r}")
    add_noise = choose("depth noise", noise)
    if sigma is not None and add_noise in (no_noise, kinect_noise):
        raise ConfigError(
            f"sigma sets the 'gaussian' noise only; the {noise!r} model takes no sigma (pass sigma=None)"
        )
    sigma = 0.001 if sigma is None else float(sigma)
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ConfigError(f"sigma must be a non-negative standard deviation in metres, got {sigma}")
    for name, value in (("width", width), ("height", height)):
        if not (isinstance(value, (int, np.integer)) and value >= 2):
            raise ConfigError(f"{name} must be an integer number of pixels >= 2, got {value!r}")
    if not 0 < fov_deg < 180:
        raise ConfigError(f"fov_deg must lie in (0, 180) degrees, got {fov_deg}")
    if distance is not None and not distance > 0:
        raise ConfigError(f"distance must be positive (metres from the object's centre), got {distance}")

    lo, hi = mesh.bounds.double().cpu()
    if cam_to_world is None:
        if not (isinstance(n_views, (int, np.integer)) and n_views >= 1):
            raise ConfigError(f"n_views must be a positive integer, got {n_views!r}")
        center = (lo + hi) / 2
        radius = float((mesh.vertices.detach().double().cpu() - center).norm(dim=-1).max())
        cam_to_world = orbit_cameras(center, radius, int(n_views), fov_deg, width / height, distance)
    pose = torch.as_tensor(cam_to_world, dtype=torch.float64)
    pose = pose[None] if pose.shape == (4, 4) else pose
    if pose.ndim != 3 or pose.shape[1:] != (4, 4):
        raise InputError(f"cam_to_world must be 4x4 or (n, 4, 4), got {tuple(pose.shape)}")
    n = len(pose)
    K = intrinsics_from_fov(width, height, fov_deg) if K is None else torch.as_tensor(K, dtype=torch.float64)
    K = K.expand(n, 3, 3) if K.shape == (3, 3) else K
    if K.shape != (n, 3, 3):
        raise InputError(f"K must be 3x3 or (n={n}, 3, 3), got {tuple(K.shape)}")
    check_intrinsics(K, width, height)

    depth, cosine = render_depth(mesh, K, pose, width, height)
    generator = torch.Generator().manual_seed(int(seed))
    depth = add_noise(depth, cosine, generator, sigma, max_angle_deg, edge_jump)
    return DepthFrames(depth.float(), K.float(), pose.float())


__all__ = [
    "NOISE_MODELS",
    "depth_edges",
    "fibonacci_sphere",
    "gaussian_noise",
    "intrinsics_from_fov",
    "kinect_noise",
    "look_at",
    "no_noise",
    "orbit_cameras",
    "scan_depth",
]
