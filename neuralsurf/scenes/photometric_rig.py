"""A synthetic photometric-stereo rig: a mesh seen by pinhole cameras under distant lights.

Everything is ray cast with Open3D (no rasteriser): the camera rays find the visible surface, and one
shadow ray per pixel and light finds cast shadows. Lights are fixed to the camera (as on a
DiLiGenT-style rig): their directions are given in each camera's frame (OpenCV: x right, y down,
z forward), pointing from the surface towards the light, so a light beside the camera has z < 0.

The image of a pixel under light l (unit intensity `intensity`) is

    I = intensity * (albedo * max(0, n . l) + specular(n, l, v)) * visible(l)

with n the shading normal (vertex normals interpolated across each triangle when `smooth`, else the
face normal), v the direction to the camera, `visible` 0 in a cast shadow, and an optional white
specular lobe (`SpecularLobe`: Blinn-Phong or Cook-Torrance with GGX, Schlick and Smith terms).
Sensor effects, in order: Gaussian noise of `noise_sigma`, clipping to [0, 1] (saturation), and
rounding to `bits`-bit levels. The ground-truth normal map is the shading normal in the camera frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import vertex_normals
from neuralsurf.scenes.scanner import intrinsics_from_fov, orbit_cameras
from neuralsurf.structures import Mesh, PhotometricCapture, check_intrinsics

SPECULAR_MODELS = ("blinn_phong", "cook_torrance")


@dataclass(frozen=True)
class SpecularLobe:
    """A white specular lobe added to the Lambertian term."""

    model: str = "blinn_phong"
    """"blinn_phong" (strength * (n . h)^shininess) or "cook_torrance" (strength * D F G / (4 n . v))."""
    strength: float = 0.5
    """Peak-scale factor of the lobe (the image of a white Lambertian surface facing the light is 1)."""
    shininess: float = 50.0
    """Blinn-Phong exponent."""
    roughness: float = 0.25
    """Cook-Torrance GGX roughness (alpha = roughness^2)."""
    f0: float = 0.04
    """Cook-Torrance Fresnel reflectance at normal incidence (Schlick)."""

    def __post_init__(self) -> None:
        if self.model not in SPECULAR_MODELS:
            raise ConfigError(f"specular model must be one of {SPECULAR_MODELS}, got {self.model!r}")
        if not (self.strength >= 0 and self.shininess > 0 and 0 < self.roughness <= 1 and 0 <= self.f0 <= 1):
            raise ConfigError(
                f"SpecularLobe needs strength >= 0, shininess > 0, roughness in (0, 1], f0 in [0, 1]; got {self}"
            )

    def __call__(self, n_dot_l: Tensor, n_dot_v: Tensor, n_dot_h: Tensor, v_dot_h: Tensor) -> Tensor:
        """Specular radiance [...] (times the light's intensity) from the cosines [...]; 0 where n . l <= 0."""
        lit = (n_dot_l > 0) & (n_dot_v > 0)
        if self.model == "blinn_phong":
            value = self.strength * n_dot_h.clamp_min(0) ** self.shininess
        else:
            alpha2 = self.roughness**4
            d = alpha2 / (math.pi * ((n_dot_h**2) * (alpha2 - 1) + 1) ** 2)
            f = self.f0 + (1 - self.f0) * (1 - v_dot_h.clamp(0, 1)) ** 5
            kk = self.roughness**2 / 2
            g = (n_dot_l / (n_dot_l * (1 - kk) + kk)) * (n_dot_v / (n_dot_v * (1 - kk) + kk))
            value = self.strength * d * f * g / (4 * n_dot_v.clamp_min(1e-6))
        return torch.where(lit, value, 0.0)


def cap_lights(n: int = 96, max_angle_deg: float = 40.0) -> Tensor:
    """Float64[Tensor, "n 3"]: DiLiGenT-like lights: n directions spread evenly (a golden-angle spiral)
    over the cap within `max_angle_deg` of the viewing axis, on the camera's side (z < 0)."""
    if not (isinstance(n, int) and n >= 3):
        raise ConfigError(f"n must be an integer >= 3 lights, got {n!r}")
    if not 0 < max_angle_deg < 90:
        raise ConfigError(f"max_angle_deg must lie in (0, 90), got {max_angle_deg}")
    i = torch.arange(n, dtype=torch.float64)
    cos_max = math.cos(math.radians(max_angle_deg))
    z = 1 - (i + 0.5) / n * (1 - cos_max)  # uniform in area over the cap
    radius = torch.sqrt(1 - z**2)
    phi = i * math.pi * (3 - math.sqrt(5))
    return torch.stack([radius * torch.cos(phi), radius * torch.sin(phi), -z], -1)


def ring_lights(n: int = 12, slant_deg: float = 45.0) -> Tensor:
    """Float64[Tensor, "n 3"]: n lights evenly around the viewing axis, `slant_deg` away from it (z < 0)."""
    if not (isinstance(n, int) and n >= 3):
        raise ConfigError(f"n must be an integer >= 3 lights, got {n!r}")
    if not 0 < slant_deg < 90:
        raise ConfigError(f"slant_deg must lie in (0, 90), got {slant_deg}")
    phi = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    s, c = math.sin(math.radians(slant_deg)), math.cos(math.radians(slant_deg))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), torch.full_like(phi, -c)], -1)


def checker_albedo(period: float, low: float = 0.3, high: float = 0.9) -> Callable[[Tensor], Tensor]:
    """A 3D checkerboard texture: world points [m, 3] -> albedo [m], `low` or `high` in cubes of side `period`."""
    if not period > 0:
        raise ConfigError(f"period must be positive (world units), got {period}")

    def albedo(points: Tensor) -> Tensor:
        parity = torch.floor(points / period).long().sum(-1) % 2
        return torch.where(parity == 0, low, high).to(points.dtype)

    return albedo


def _albedo_values(albedo, points: Tensor, faces: Tensor, bary: Tensor, mesh: Mesh) -> Tensor:
    """Albedo [m] or [m, 3] at the hit points."""
    if callable(albedo):
        values = torch.as_tensor(albedo(points)).to(points)
    elif isinstance(albedo, str):
        if albedo != "vertex" or mesh.vertex_colors is None:
            raise ConfigError(
                f"albedo={albedo!r}: the only named albedo is 'vertex' (the mesh's vertex colours), "
                f"and it needs a mesh with vertex_colors"
            )
        colors = mesh.vertex_colors.detach().double().cpu()[mesh.faces.cpu()[faces]]  # (m, 3 corners, 3)
        values = (bary[:, :, None] * colors).sum(1).to(points)
    else:
        values = torch.as_tensor(albedo, dtype=points.dtype)
        if values.ndim == 0:
            values = values.expand(len(points))
        elif values.shape == (3,):
            values = values.expand(len(points), 3)
        else:
            raise ConfigError(
                f"albedo must be a number, an RGB triple, 'vertex' or a callable, got shape "
                f"{tuple(values.shape)}"
            )
    if values.shape not in ((len(points),), (len(points), 3)) or (values < 0).any():
        raise InputError(
            f"albedo values must be non-negative with shape (m,) or (m, 3), got {tuple(values.shape)}"
        )
    return values


def render_photometric(
    mesh: Mesh,
    lights: Tensor | None = None,
    cam_to_world: Tensor | None = None,
    K: Tensor | None = None,
    *,
    n_views: int = 1,
    width: int = 256,
    height: int = 256,
    fov_deg: float = 30.0,
    albedo=0.8,
    specular: SpecularLobe | None = None,
    shadows: bool = True,
    attached_shadows: bool = True,
    smooth: bool = True,
    intensity: float = 1.0,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    seed: int = 0,
) -> list[PhotometricCapture]:
    """Render `mesh` under directional lights from one or several pinhole cameras.

    Args:
        mesh: the object (world frame), non-empty.
        lights: Float[Tensor, "n 3"] unit directions towards the lights in each camera's frame
            (default `cap_lights(96)`, DiLiGenT-like).
        cam_to_world: Float[Tensor, "v 4 4"] (or 4x4) OpenCV poses; default `orbit_cameras` of
            `n_views` views around the mesh (the object fills the narrower field of view).
        K: Float[Tensor, "3 3"] (or "v 3 3") intrinsics; default from `fov_deg` (vertical, centred).
        width, height: image size in pixels.
        albedo: a number (grey images), an RGB triple, "vertex" (the mesh's vertex colours,
            interpolated) or a callable world points [m, 3] -> [m] or [m, 3] (e.g. `checker_albedo`).
        specular: a `SpecularLobe`, or None for a Lambertian surface.
        shadows: cast shadows by ray casting towards each light.
        attached_shadows: clamp the Lambertian term at 0 where the surface faces away from the light
            (physical). False renders albedo * n . l unclamped, negative values included: an idealised
            shadow-free sensor for testing solvers (clipping by noise or `bits` brings the clamp back).
        smooth: shade with interpolated vertex normals (else face normals).
        intensity: radiance scale of every light.
        noise_sigma: standard deviation of additive Gaussian sensor noise (image units, 1 = white).
        bits: quantise to this many bits (8 or 16) after clipping to [0, 1]; None: no quantisation
            (and no clipping unless there is noise).
        seed: seed of the noise.
    Returns:
        One PhotometricCapture per view: images Float[n, h, w] (grey albedo) or [n, h, w, 3], the
        lights, mask (pixels that see the mesh), ground-truth normals [h, w, 3] in the camera frame,
        z-depth [h, w] in world units (0 off the object), K and cam_to_world.
    """
    import open3d as o3d

    if not isinstance(mesh, Mesh) or mesh.is_empty:
        raise InputError(f"render_photometric needs a non-empty neuralsurf Mesh, got {type(mesh).__name__}")
    lights = cap_lights() if lights is None else torch.as_tensor(lights, dtype=torch.float64)
    if lights.ndim != 2 or lights.shape[1] != 3 or len(lights) == 0:
        raise InputError(f"lights must be (n, 3) directions, got {tuple(lights.shape)}")
    lights = torch.nn.functional.normalize(lights, dim=-1)
    if bits is not None and bits not in (8, 16):
        raise ConfigError(f"bits must be 8, 16 or None, got {bits!r}")
    if not noise_sigma >= 0:
        raise ConfigError(f"noise_sigma must be >= 0, got {noise_sigma}")
    for name, value in (("width", width), ("height", height)):
        if not (isinstance(value, (int, np.integer)) and value >= 2):
            raise ConfigError(f"{name} must be an integer number of pixels >= 2, got {value!r}")
    vertices = mesh.vertices.detach().double().cpu()
    faces = mesh.faces.cpu()
    center = vertices.mean(0)  # float32 ray casting, re-centred for precision
    if cam_to_world is None:
        lo, hi = vertices.min(0).values, vertices.max(0).values
        box_center = (lo + hi) / 2
        radius = float((vertices - box_center).norm(dim=-1).max())
        cam_to_world = orbit_cameras(box_center, radius, int(n_views), fov_deg, width / height)
    pose = torch.as_tensor(cam_to_world, dtype=torch.float64)
    pose = pose[None] if pose.shape == (4, 4) else pose
    if pose.ndim != 3 or pose.shape[1:] != (4, 4):
        raise InputError(f"cam_to_world must be 4x4 or (v, 4, 4), got {tuple(pose.shape)}")
    K = intrinsics_from_fov(width, height, fov_deg) if K is None else torch.as_tensor(K, dtype=torch.float64)
    K = K.expand(len(pose), 3, 3) if K.shape == (3, 3) else K
    if K.shape != (len(pose), 3, 3):
        raise InputError(f"K must be 3x3 or (v={len(pose)}, 3, 3), got {tuple(K.shape)}")
    check_intrinsics(K, width, height)

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((vertices - center).float().numpy()), o3d.core.Tensor(faces.numpy().astype(np.uint32))
    )
    face_normals = mesh.face_normals().detach().double().cpu()
    corner_normals = None  # (f, 3, 3)
    if smooth:
        corner_normals = torch.from_numpy(vertex_normals(mesh.vertices.detach().double().cpu().numpy(),
                                                         mesh.faces.cpu().numpy()))[faces]
    size = float((vertices.max(0).values - vertices.min(0).values).norm())
    generator = torch.Generator().manual_seed(int(seed))
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    captures = []
    for k, p in zip(K, pose):
        y = (v - k[1, 2]) / k[1, 1]
        x = (u - k[0, 2] - k[0, 1] * y) / k[0, 0]
        ray = torch.nn.functional.normalize(
            torch.stack([x, y, torch.ones_like(x)], -1), dim=-1
        )  # camera frame
        world_ray = ray @ p[:3, :3].T
        origin = (p[:3, 3] - center).expand_as(world_ray)
        hit = scene.cast_rays(o3d.core.Tensor(torch.cat([origin, world_ray], -1).float().numpy()))
        t = torch.from_numpy(hit["t_hit"].numpy()).double()
        mask = torch.isfinite(t)
        face = torch.from_numpy(hit["primitive_ids"].numpy().astype(np.int64))[mask]
        uv = torch.from_numpy(hit["primitive_uvs"].numpy()).double()[mask]
        bary = torch.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)  # weights of the 3 corners
        geometric = face_normals[face]
        normal = (bary[:, :, None] * corner_normals[face]).sum(1) if smooth else geometric.clone()
        normal = torch.nn.functional.normalize(normal, dim=-1)
        to_camera = -world_ray[mask]
        facing = torch.where((geometric * to_camera).sum(-1, keepdim=True) < 0, -1.0, 1.0)  # seen from behind
        geometric, normal = geometric * facing, normal * facing
        points = origin[mask] + t[mask, None] * world_ray[mask]  # re-centred world frame
        values = _albedo_values(albedo, points + center, face, bary, mesh)
        world_lights = lights @ p[:3, :3].T  # (n, 3)
        offset = points + 1e-4 * size * geometric
        images = torch.zeros(len(lights), height, width, *values.shape[1:], dtype=torch.float64)
        for i, light in enumerate(world_lights):
            n_dot_l = normal @ light
            shading = n_dot_l.clamp_min(0) if attached_shadows else n_dot_l
            radiance = values * (shading[:, None] if values.ndim == 2 else shading)
            if specular is not None:
                half = torch.nn.functional.normalize(light + to_camera, dim=-1)
                lobe = specular(
                    n_dot_l, (normal * to_camera).sum(-1), (normal * half).sum(-1), (to_camera * half).sum(-1)
                )
                radiance = radiance + (lobe[:, None] if values.ndim == 2 else lobe)
            if shadows:
                rays = torch.cat([offset, light.expand_as(offset)], -1).float().numpy()
                occluded = torch.from_numpy(scene.test_occlusions(o3d.core.Tensor(rays)).numpy())
                # a shadow ray leaving a surface that faces away from the light is in attached shadow anyway
                radiance = torch.where(occluded.reshape(-1, *([1] * (radiance.ndim - 1))), 0.0, radiance)
            images[i][mask] = intensity * radiance
        if noise_sigma > 0:
            images = images + noise_sigma * torch.randn(
                images.shape, generator=generator, dtype=torch.float64
            )
        if noise_sigma > 0 or bits is not None:
            images = images.clamp(0, 1)
        if bits is not None:
            levels = 2**bits - 1
            images = torch.round(images * levels) / levels
        normal_map = torch.zeros(height, width, 3, dtype=torch.float64)
        normal_map[mask] = normal @ p[:3, :3]  # world -> camera: R^T n
        depth = torch.where(mask, t * ray[..., 2], 0.0)
        captures.append(
            PhotometricCapture(
                images=images.float(),
                light_directions=lights.float(),
                mask=mask,
                normals=normal_map.float(),
                K=k.float(),
                depth=depth.float(),
                cam_to_world=p.float(),
            )
        )
    return captures


__all__ = [
    "SPECULAR_MODELS",
    "SpecularLobe",
    "cap_lights",
    "checker_albedo",
    "render_photometric",
    "ring_lights",
    "vertex_normals",
]


# ----------------------------------------------------------------------------------------------
# analytic views with depth discontinuities (normal-integration oracles)


@dataclass(frozen=True)
class Primitive:
    """A convex solid or a plane for `raycast_primitives`, in the camera frame.

    kind "box": centre, `half` (3 half-extents along the box axes) and `rotation` (3x3, columns the box
    axes); "ball": centre and radius `half[0]`; "plane": the plane through `centre` with normal `half`."""

    kind: str
    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _hits(primitive: Primitive, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameter t [m] (inf for a miss) and outward unit normal [m, 3] of rays [m, 3] from the origin."""
    c = np.asarray(primitive.centre, dtype=np.float64)
    if primitive.kind == "ball":
        r = primitive.half[0]
        b = rays @ c
        a = (rays * rays).sum(-1)
        disc = b**2 - a * (c @ c - r * r)
        t = np.where(disc >= 0, (b - np.sqrt(np.clip(disc, 0, None))) / a, np.inf)
        t = np.where(t > 0, t, np.inf)
        normal = (np.where(np.isfinite(t), t, 0.0)[:, None] * rays - c) / r
        return t, normal
    if primitive.kind == "plane":
        n = np.asarray(primitive.half, dtype=np.float64)
        n = n / np.linalg.norm(n)
        along = rays @ n
        with np.errstate(divide="ignore"):
            t = np.where(np.abs(along) > 1e-12, (c @ n) / along, np.inf)
        t = np.where(t > 0, t, np.inf)
        return t, np.where(along[:, None] < 0, n, -n) * np.ones_like(rays)
    if primitive.kind == "box":
        R = np.asarray(primitive.rotation, dtype=np.float64)
        half = np.asarray(primitive.half, dtype=np.float64)
        o, d = R.T @ -c, rays @ R  # ray origin and directions in the box frame
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d
        near = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
        far = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
        entry, axis = near.max(-1), near.argmax(-1)
        hit = (entry <= far.min(-1)) & (entry > 0)
        local = np.zeros_like(rays)
        local[np.arange(len(rays)), axis] = -np.sign(d[np.arange(len(rays)), axis])
        return np.where(hit, entry, np.inf), local @ R.T
    raise ConfigError(f"unknown primitive kind {primitive.kind!r}; use 'box', 'ball' or 'plane'")


def raycast_primitives(primitives: list[Primitive], K: Tensor, width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """Exact z-depth [h, w], unit normals [h, w, 3] (facing the camera, z < 0 when seen head-on) and mask
    [h, w] of the nearest of `primitives` along each pixel's ray (pixel (u, v) at integer coordinates)
    of a pinhole camera at the origin with intrinsics K [3, 3]."""
    K = np.asarray(torch.as_tensor(K, dtype=torch.float64))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    depth = np.full(len(rays), np.inf)
    normals = np.zeros_like(rays)
    for primitive in primitives:
        t, n = _hits(primitive, rays)
        nearer = t < depth
        depth[nearer], normals[nearer] = t[nearer], n[nearer]
    mask = np.isfinite(depth)
    normals /= np.clip(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12, None)
    return (
        torch.from_numpy(np.where(mask, depth, 0.0).reshape(height, width)),
        torch.from_numpy(normals.reshape(height, width, 3)),
        torch.from_numpy(mask.reshape(height, width)),
    )


def _rotation(yaw_deg: float, pitch_deg: float) -> tuple[tuple[float, ...], ...]:
    """Rotation about the camera's y axis by yaw, then about x by pitch (rows of the 3x3 matrix)."""
    a, b = math.radians(yaw_deg), math.radians(pitch_deg)
    yaw = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    pitch = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    return tuple(map(tuple, (pitch @ yaw).tolist()))


def _turn_down(primitive: Primitive, degrees: float, pivot: tuple[float, float, float] = (0.0, 0.0, 3.0)) -> Primitive:
    """`primitive` turned about the camera's x axis through `pivot` so that its up side (-y) tilts
    towards the camera by `degrees` (a view from above)."""
    P = np.asarray(_rotation(0.0, degrees))
    c = np.asarray(pivot)
    centre = tuple((P @ (np.asarray(primitive.centre) - c) + c).tolist())
    if primitive.kind == "plane":
        return Primitive("plane", centre, tuple((P @ np.asarray(primitive.half)).tolist()))
    return Primitive(primitive.kind, centre, primitive.half, tuple(map(tuple, (P @ np.asarray(primitive.rotation)).tolist())))


DISCONTINUITY_SCENES = ("step", "sphere_on_plane", "stacked_boxes", "leaning_boxes", "box_on_ground")
"""Names of `discontinuity_scene`'s views."""


def discontinuity_scene(name: str, size: int = 128, fov_deg: float = 40.0) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A perspective view (size x size, vertical field of view `fov_deg`) of analytic solids with depth
    discontinuities where one occludes another, for normal-integration tests:

    - "step": a tilted plane behind a tilted slab that covers the left of the view (the slab's side
      face is hidden: a pure step);
    - "sphere_on_plane": a sphere in front of a tilted plane (an occluding contour with grazing normals);
    - "stacked_boxes": a box on a box on a ground plane, turned and seen from above, about 0.3 in front
      of a wall (creases; the boxes' far edges occlude the wall). The wall is what makes the view well posed:
      with the lower box's top seen against the ground instead, which is parallel to it, that top
      scaled about the camera onto the ground (the upper box with it) and broken from the box's front
      faces keeps every normal and breaks as many pixel pairs, so normals could not tell the two apart;
    - "leaning_boxes": the same boxes tipped 10 degrees about the camera's x axis (in opposite senses)
      and about 1.3 in front of the wall: their tops are seen against the ground but are not parallel to it;
    - "box_on_ground": one turned box on a ground plane before a wall, seen obliquely.

    Returns:
        depth Float64[h, w], normals Float64[h, w, 3], mask Bool[h, w] (every pixel sees a surface) and K [3, 3].
    """
    K = intrinsics_from_fov(size, size, fov_deg).double()
    tilted = Primitive("plane", (0.0, 0.0, 4.0), (0.25, -0.15, -1.0))
    if name == "step":
        slab = Primitive("box", (-1.6, 0.0, 2.4), (1.5, 3.0, 0.2), _rotation(-12.0, 8.0))
        primitives = [tilted, slab]
    elif name == "sphere_on_plane":
        primitives = [tilted, Primitive("ball", (0.15, 0.1, 2.5), (0.6, 0.0, 0.0))]
    elif name in ("stacked_boxes", "leaning_boxes"):
        lean = 10.0 if name == "leaning_boxes" else 0.0
        ground = Primitive("plane", (0.0, 0.6, 0.0), (0.0, -1.0, 0.0))
        lower = Primitive("box", (0.0, 0.3, 3.0), (0.6, 0.3, 0.45), _rotation(25.0, lean))
        upper = Primitive("box", (0.1, -0.15, 3.0), (0.3, 0.15, 0.3), _rotation(-20.0, -lean))
        wall = Primitive("plane", (0.0, 0.0, 5.0 if lean else 4.0), (0.1, 0.0, -1.0))
        primitives = [_turn_down(p, 25.0) for p in (ground, wall, lower, upper)]
    elif name == "box_on_ground":
        ground = Primitive("plane", (0.0, 0.4, 0.0), (0.0, -1.0, 0.0))
        box = Primitive("box", (0.0, 0.1, 3.0), (0.5, 0.3, 0.4), _rotation(35.0, 0.0))
        wall = Primitive("plane", (0.0, 0.0, 4.5), (-0.2, 0.0, -1.0))
        primitives = [_turn_down(p, 20.0) for p in (ground, wall, box)]
    else:
        raise ConfigError(f"unknown discontinuity scene {name!r}; choose one of {DISCONTINUITY_SCENES}")
    depth, normals, mask = raycast_primitives(primitives, K, size, size)
    return depth, normals, mask, K


def degrade_normals(normals: Tensor, mask: Tensor, sigma: float = 0.01, bits: int | None = 8, seed: int = 0) -> Tensor:
    """A measured-like normal map: Gaussian noise of `sigma` on each component, renormalised, then stored
    as `bits`-bit RGB ((n + 1) / 2 rounded to 2^bits - 1 levels, as normal-map images are) and read back.

    Args:
        normals: Float[Tensor, "h w 3"] unit normals; mask: Bool[Tensor, "h w"] (0 outside).
    Returns:
        Float[Tensor, "h w 3"] unit normals, 0 outside the mask.
    """
    if sigma < 0:
        raise ConfigError(f"sigma must be non-negative, got {sigma}")
    generator = torch.Generator().manual_seed(seed)
    noisy = normals + sigma * torch.randn(normals.shape, generator=generator, dtype=normals.dtype)
    noisy = torch.nn.functional.normalize(noisy, dim=-1)
    if bits is not None:
        levels = 2**bits - 1
        noisy = torch.nn.functional.normalize(torch.round((noisy + 1) / 2 * levels) / levels * 2 - 1, dim=-1)
    return torch.where(mask[..., None], noisy, 0.0)
