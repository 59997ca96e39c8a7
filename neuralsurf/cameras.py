"""Cameras and depth images: pixel rays, back-projection and projection, depth-map normals, depth frames
as rays and as point clouds, resampling, striding and reading depth at points, quaternions, and the
depth sensor (Kinect v1 noise, rendered depth). Pure batched tensor functions of `structures` types.

Pixel convention (OpenCV): pixel (u, v) is column u, row v, and its centre lies at the integer
coordinates (u, v); a camera-frame point (x, y, z) lands at u = fx x / z + cx, v = fy y / z + cy.
Poses are camera-to-world 4x4 matrices; depth is z-depth in metres, 0 where missing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import InputError
from neuralsurf.structures import DepthFrames, Mesh, PointCloud, float_colors

__all__ = [
    "Rays",
    "backproject_depth",
    "backproject_depth_to_camera",
    "box_span",
    "depth_normals",
    "depth_rays",
    "depth_to_cloud",
    "frame_readings",
    "kinect_sigma",
    "pixel_grid",
    "pixel_rays",
    "project_points",
    "quaternion_to_matrix",
    "render_depth",
    "resample_depth",
    "stride_frames",
    "strided_hits",
]

# ---------------------------------------------------------------------------------------------
# pixels and rays: back-projection, projection


def pixel_grid(height: int, width: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """Float[Tensor, "h w 2"]: (u, v) = (column, row) of every pixel centre (integers)."""
    rows = torch.arange(height, dtype=dtype, device=device)
    columns = torch.arange(width, dtype=dtype, device=device)
    v, u = torch.meshgrid(rows, columns, indexing="ij")
    return torch.stack([u, v], dim=-1)


def box_span(origins: Tensor, directions: Tensor, bounds: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distances Float[Tensor, "r"] of rays (origins, directions Float[Tensor, "r 3"]) through the
    box Float[Tensor, "2 3"] (slab test; entry 0 for an origin inside); exit <= entry where a ray misses it."""
    inverse = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0, t1 = (bounds[0] - origins) * inverse, (bounds[1] - origins) * inverse
    return torch.minimum(t0, t1).amax(-1).clamp_min(0.0), torch.maximum(t0, t1).amin(-1)


def pixel_rays(K: Tensor, height: int, width: int) -> Tensor:
    """Float[Tensor, "... h w 3"]: camera-frame rays K^-1 (u, v, 1) of every pixel centre (z = 1), for
    intrinsics K Float[Tensor, "... 3 3"] (a zero skew K[0, 1] is not assumed: it is used), in K's dtype
    and device."""
    uv = pixel_grid(height, width, K.dtype, K.device)  # (h, w, 2)
    fx, fy, cx, cy, skew = (K[..., i, j][..., None, None] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2), (0, 1)))
    y = (uv[..., 1] - cy) / fy
    x = (uv[..., 0] - cx - skew * y) / fx
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def backproject_depth_to_camera(depth: Tensor, K: Tensor) -> Tensor:
    """Camera-frame points of depth images (OpenCV: x right, y down, z forward): `pixel_rays` times depth.

    Args:
        depth: Float[Tensor, "n h w"] z-depth (0 = invalid).
        K: Float[Tensor, "n 3 3"] intrinsics.
    Returns:
        Float[Tensor, "n h w 3"]: (x, y, z) with z = depth; invalid pixels give (0, 0, 0).
    """
    return pixel_rays(K.to(depth), depth.shape[1], depth.shape[2]) * depth[..., None]


def backproject_depth(frames: DepthFrames) -> Tensor:
    """World-frame points of every pixel of every frame.

    Args:
        frames: DepthFrames with depth (n, h, w), K (n, 3, 3), cam_to_world (n, 4, 4).
    Returns:
        Float[Tensor, "n h w 3"] in the frames' dtype and device: the point seen at the centre of
        pixel (u, v) (integer coordinates, OpenCV convention) at its z-depth. Pixels with depth 0
        map to their camera's centre; select valid points with `frames.depth > 0`.
    """
    camera = backproject_depth_to_camera(frames.depth, frames.K)
    pose = frames.cam_to_world.to(camera)
    return torch.einsum("nij,nhwj->nhwi", pose[:, :3, :3], camera) + pose[:, None, None, :3, 3]


def project_points(points: Tensor, K: Tensor, cam_to_world: Tensor) -> tuple[Tensor, Tensor]:
    """Project world points into cameras (the inverse of `backproject_depth`).

    Args:
        points: Float[Tensor, "n m 3"] world points, m per camera (or "m 3" for one camera).
        K: Float[Tensor, "n 3 3"] (or "3 3"); cam_to_world: Float[Tensor, "n 4 4"] (or "4 4").
    Returns:
        uv Float[Tensor, "n m 2"]: pixel coordinates, centres at integers (round to index a pixel);
        z Float[Tensor, "n m"]: depth along the optical axis (<= 0 behind the camera, where uv is
        meaningless).
    """
    single = points.ndim == 2
    points, K, pose = (points[None], K[None], cam_to_world[None]) if single else (points, K, cam_to_world)
    pose, K = pose.to(points), K.to(points)
    rotation, translation = pose[:, :3, :3], pose[:, :3, 3]
    camera = torch.einsum("nji,nmj->nmi", rotation, points - translation[:, None])  # R^T (p - t)
    z = camera[..., 2]
    pixels = torch.einsum("nij,nmj->nmi", K, camera)
    uv = pixels[..., :2] / torch.where(z.abs() > 0, z, torch.ones_like(z))[..., None]
    return (uv[0], z[0]) if single else (uv, z)


def depth_normals(camera: Tensor, max_depth_jump: float, stride: int = 1) -> tuple[Tensor, Tensor]:
    """Normals of camera-frame depth points from their image neighbours, at every `stride`-th pixel.

    Args:
        camera: Float[Tensor, "n h w 3"] from `backproject_depth_to_camera`.
        max_depth_jump: neighbours whose depth differs by more than this fraction of the pixel's
            depth are across a discontinuity and not used.
        stride: evaluate at rows and columns 0, stride, 2 stride, ... (neighbours stay at +-1 pixel).
    Returns:
        normals Float[Tensor, "n h' w' 3"] unit, facing the camera (n . p < 0), and
        Bool[Tensor, "n h' w'"]: where a normal exists (a valid pixel with a usable neighbour both
        horizontally and vertically), with h' = ceil(h / stride), w' = ceil(w / stride). Central
        differences where both neighbours are usable, one-sided ones where only one is.
    """
    h, w = camera.shape[1:3]
    padded = torch.nn.functional.pad(camera.permute(0, 3, 1, 2), (1, 1, 1, 1)).permute(0, 2, 3, 1)
    centre = camera[:, ::stride, ::stride]
    z = centre[..., 2]

    def neighbour(dv: int, du: int) -> tuple[Tensor, Tensor]:
        other = padded[:, 1 + dv : 1 + dv + h : stride, 1 + du : 1 + du + w : stride]
        usable = (z > 0) & (other[..., 2] > 0) & ((other[..., 2] - z).abs() <= max_depth_jump * z)
        return other, usable

    def difference(forward: tuple[Tensor, Tensor], backward: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        (after, ok_after), (before, ok_before) = forward, backward
        one_sided = torch.where(ok_after[..., None], after - centre, centre - before)
        return torch.where((ok_after & ok_before)[..., None], after - before, one_sided), ok_after | ok_before

    du, has_u = difference(neighbour(0, 1), neighbour(0, -1))
    dv, has_v = difference(neighbour(1, 0), neighbour(-1, 0))
    normals = torch.linalg.cross(du, dv)
    length = normals.norm(dim=-1)
    has = has_u & has_v & (length > 0)
    sign = torch.where((normals * centre).sum(-1) > 0, -1.0, 1.0)  # face the camera at the origin
    normals = normals * (sign / torch.where(has, length, torch.ones_like(length)))[..., None]
    return normals, has


def depth_to_cloud(
    frames: DepthFrames,
    stride: int = 1,
    with_normals: bool = True,
    max_depth_jump: float = 0.05,
    chunk: int = 8,
) -> PointCloud:
    """One world-frame PointCloud of the valid pixels of all frames (with colours when the frames
    have them).

    Normals come from each pixel's image neighbours at full resolution: the cross product of the
    horizontal and vertical differences of the back-projected points (central where both
    neighbours are usable, one-sided otherwise), turned towards the camera and rotated into the
    world. A neighbour is usable when its depth is valid and within `max_depth_jump` (a fraction)
    of the pixel's depth. With `with_normals=True`, valid pixels without a usable neighbour both
    horizontally and vertically (isolated speckles) have no normal and are left out.

    Args:
        frames: DepthFrames (n, h, w).
        stride: keep every `stride`-th row and column (pixel (0, 0) always kept).
        with_normals: compute normals as above (else normals is None and every valid pixel is kept).
        max_depth_jump: relative depth difference that marks a discontinuity (0.05 = 5 %).
        chunk: frames processed at once (bounds memory; does not change the result).
    Returns:
        PointCloud with points (p, 3), normals (p, 3) or None, colours (p, 3) or None, in the
        frames' float32; points are ordered by frame, then row, then column.
    """
    if not isinstance(stride, int) or stride < 1:
        raise InputError(f"stride must be a positive integer (keep every stride-th pixel), got {stride!r}")
    if not max_depth_jump > 0:
        raise InputError(f"max_depth_jump must be a positive fraction of the depth, got {max_depth_jump}")
    points, normals, colors = [], [], []
    for start in range(0, len(frames), max(1, int(chunk))):
        part = slice(start, start + max(1, int(chunk)))
        camera = backproject_depth_to_camera(frames.depth[part], frames.K[part])
        keep = frames.depth[part, ::stride, ::stride] > 0
        if with_normals:
            local, has = depth_normals(camera, max_depth_jump, stride)
            keep = keep & has
        pose = frames.cam_to_world[part].to(camera)
        rotation = pose[:, None, None, :3, :3]
        world = (rotation @ camera[:, ::stride, ::stride, :, None])[..., 0] + pose[:, None, None, :3, 3]
        points.append(world[keep])
        if with_normals:
            normals.append((rotation @ local[..., None])[..., 0][keep])
        if frames.colors is not None:
            colors.append(float_colors(frames.colors[part, ::stride, ::stride][keep]))
    points = torch.cat(points)
    if len(points) == 0:
        raise InputError(
            "the depth frames have no valid pixel" + (" with a normal" if with_normals else "")
            + "; check that depth is in metres with 0 for missing readings"
        )
    normals = torch.cat(normals) if with_normals else None
    return PointCloud(points, normals, torch.cat(colors) if colors else None)


def resample_depth(depth: Tensor, K_depth: Tensor, K: Tensor, height: int, width: int,
                   max_depth_jump: float = 0.05) -> Tensor:
    """The z-depth of a camera seen through other intrinsics of the same pose (e.g. a half-resolution
    depth map at the pixels of a full-resolution normal map).

    Args:
        depth: Float[Tensor, "h' w'"] z-depth in metres, 0 = missing.
        K_depth: Float[Tensor, "3 3"] intrinsics of `depth`; K: those of the target pixels.
        height, width: target image size.
        max_depth_jump: where the four source neighbours' depths spread by more than this fraction
            of their mean (a discontinuity), the target pixel is missing.
    Returns:
        Float[Tensor, "height width"] (depth's dtype): bilinear z-depth where all four neighbours are
        valid and close, 0 elsewhere (z-depth is the same for both intrinsics: same pose, same z axis).
    """
    depth = torch.as_tensor(depth)
    if depth.ndim != 2:
        raise InputError(f"resample_depth takes one depth map (h, w), got shape {tuple(depth.shape)}")
    source = depth.double().cpu()
    rays = pixel_rays(torch.as_tensor(K, dtype=torch.float64).cpu(), height, width)  # (h, w, 3), z = 1
    Kd = torch.as_tensor(K_depth, dtype=torch.float64).cpu()
    pixels = rays @ Kd.T
    us, vs = pixels[..., 0], pixels[..., 1]
    h, w = source.shape
    u0, v0 = torch.floor(us).long(), torch.floor(vs).long()
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    u0c, v0c = u0.clamp(0, w - 2), v0.clamp(0, h - 2)
    corners = torch.stack([source[v0c, u0c], source[v0c, u0c + 1], source[v0c + 1, u0c], source[v0c + 1, u0c + 1]])
    a, b = us - u0c, vs - v0c
    weights = torch.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
    value = (weights * corners).sum(0)
    lo, hi = corners.min(0).values, corners.max(0).values
    ok = inside & (lo > 0) & (hi - lo <= max_depth_jump * corners.mean(0))
    return torch.where(ok, value, 0.0).to(depth.dtype if depth.is_floating_point() else torch.float32)


# ---------------------------------------------------------------------------------------------
# the depth sensor: noise and rendered depth


def kinect_sigma(z: Tensor) -> Tensor:
    """Axial noise of a Kinect v1 (Nguyen et al. 2012): z [...] metres -> standard deviation [...] metres."""
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def render_depth(
    mesh: Mesh, K: Tensor, cam_to_world: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Exact z-depth of `mesh` seen by pinhole cameras, by Open3D's ray casting.

    Args:
        mesh: non-empty Mesh (world frame); K: Float[Tensor, "n 3 3"]; cam_to_world: Float[Tensor, "n 4 4"].
    Returns:
        depth Float32[Tensor, "n h w"] (0 where the ray misses) and cos_incidence Float32[Tensor,
        "n h w"]: |cos| of the angle between the ray and the hit triangle's normal (0 on misses).
    """
    import open3d as o3d

    K, pose = K.double().cpu(), cam_to_world.double().cpu()
    center = mesh.vertices.detach().double().cpu().mean(0)  # float32 ray casting, re-centred for precision
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((mesh.vertices.detach().double().cpu() - center).float().numpy()),
        o3d.core.Tensor(mesh.faces.cpu().numpy().astype(np.uint32)),
    )
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    depth, cosine = [], []
    for k, p in zip(K, pose):  # one camera at a time bounds memory
        x = (u - k[0, 2] - k[0, 1] * (v - k[1, 2]) / k[1, 1]) / k[0, 0]
        y = (v - k[1, 2]) / k[1, 1]
        direction = torch.nn.functional.normalize(
            torch.stack([x, y, torch.ones_like(x)], -1), dim=-1
        )  # (h, w, 3)
        world = direction @ p[:3, :3].T
        origin = (p[:3, 3] - center).expand_as(world)
        hit = scene.cast_rays(o3d.core.Tensor(torch.cat([origin, world], -1).float().numpy()))
        t = torch.from_numpy(hit["t_hit"].numpy()).double()
        normal = torch.from_numpy(hit["primitive_normals"].numpy()).double()
        found = torch.isfinite(t)
        depth.append(torch.where(found, t * direction[..., 2], 0.0).float())
        cosine.append(torch.where(found, (normal * world).sum(-1).abs(), 0.0).float())
    return torch.stack(depth), torch.stack(cosine)


# ---------------------------------------------------------------------------------------------
# depth frames as rays; striding and reading them


@dataclass(frozen=True)
class Rays:
    """Rays of valid pixels in one frame of reference (world or unit)."""

    origins: Tensor
    """Float[Tensor, "r 3"]: camera centres."""
    directions: Tensor
    """Float[Tensor, "r 3"]: unit directions."""
    hit: Tensor
    """Float[Tensor, "r"]: distance along the ray to the measured surface."""
    sigma: Tensor
    """Float[Tensor, "r"]: sensor noise standard deviation along the ray at the hit."""
    cosine: Tensor
    """Float[Tensor, "r"]: |cos| between the ray and the depth map's normal at the hit (1 where unknown)."""
    normals: Tensor
    """Float[Tensor, "r 3"]: the depth map's normal at the hit, facing the camera, of length its confidence
    1 / (1 + (sigma / pixel spacing)^2)^2, pixel spacing = depth / fx (0 where unknown)."""


def depth_rays(frames: DepthFrames, sigma_of_depth=kinect_sigma, max_depth_jump: float = 0.05,
               chunk: int = 8, pixel_stride: int = 1) -> Rays:
    """World-frame rays of the valid pixels of `frames` at every `pixel_stride`-th row and column, ordered
    by frame, row, column.

    The measured z-depth becomes a distance along the ray (z |d| for the camera-frame direction
    d = K^-1 (u, v, 1)); `sigma_of_depth` maps z-depth to the axial noise sigma (metres), scaled
    the same way. Normals and their confidence come from the full-resolution depth map (neighbours one
    pixel away, `depth_normals`) whatever the stride. `chunk` frames are processed at once
    (bounds memory, same result). Raises InputError when no pixel is valid.
    """
    if not (frames.depth > 0).any():
        raise InputError(f"all {frames.depth.numel()} depth pixels of the {len(frames)} frames are missing (0); "
                         f"nothing to fit: check the depth scale (metres) and the invalid-value code")
    s = pixel_stride
    parts = []
    for start in range(0, len(frames), chunk):
        full, K = frames.depth[start : start + chunk], frames.K[start : start + chunk]
        rays = pixel_rays(K.to(full), full.shape[1], full.shape[2])  # camera rays at z = 1
        normals, has_normal = depth_normals(rays * full[..., None], max_depth_jump, s)
        depth = full[:, ::s, ::s]
        valid = depth > 0
        unit_depth = rays[:, ::s, ::s]
        length = unit_depth.norm(dim=-1)  # ray length per unit z-depth
        directions = unit_depth / length[..., None]
        cosine = torch.where(has_normal, (normals * directions).sum(-1).abs(), torch.ones_like(length))
        pose = frames.cam_to_world[start : start + chunk].to(depth)
        world = torch.einsum("nij,nhwj->nhwi", pose[:, :3, :3], directions)
        # a finite-difference normal is as good as the depth noise is small against the pixel spacing
        sigma, spacing = sigma_of_depth(depth), depth / K[:, 0, 0, None, None]
        confidence = has_normal / (1 + (sigma / spacing.clamp_min(1e-12)) ** 2) ** 2
        world_normals = torch.einsum("nij,nhwj->nhwi", pose[:, :3, :3], normals) * confidence[..., None]
        origins = pose[:, None, None, :3, 3].expand_as(world)
        parts.append(Rays(origins[valid], world[valid], (depth * length)[valid],
                          (sigma * length)[valid], cosine[valid], world_normals[valid]))
    return Rays(*(torch.cat([getattr(p, name) for p in parts]) for name in Rays.__dataclass_fields__))


def stride_frames(frames: DepthFrames, stride: int) -> DepthFrames:
    """`frames` at every `stride`-th pixel along both axes: pixel (i, j) of the result is pixel
    (stride i, stride j) of the frame, so the intrinsics' first two rows are divided by `stride`
    (the same rays; `stride` 1 returns `frames`)."""
    if stride == 1:
        return frames
    K = frames.K.clone()
    K[:, :2] /= stride
    return DepthFrames(frames.depth[:, ::stride, ::stride].contiguous(), K, frames.cam_to_world)


def strided_hits(frames: DepthFrames, pixel_stride: int = 1) -> Tensor:
    """Float64[Tensor, "n 3"]: world points of the valid readings of every `pixel_stride`-th pixel (both
    directions) of every frame."""
    parts = []
    for index in range(len(frames)):
        frame = stride_frames(frames[index : index + 1].to("cpu"), pixel_stride)
        parts.append(backproject_depth(frame)[frame.depth > 0].double())
    return torch.cat(parts)


def frame_readings(points: Tensor, depth: Tensor, K: Tensor, cam_to_world: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """World points Float64[Tensor, "n 3"] in depth images Float[Tensor, "f h w"] seen by K Float64[Tensor,
    "f 3 3"] at cam_to_world Float64[Tensor, "f 4 4"] -> (z, reading, seen), each [f, n]: the points' depth
    along each optical axis, the depth read at their nearest pixel (float64; 0 where not `seen`), and
    whether they project into the image in front of the camera."""
    height, width = depth.shape[-2:]
    uv, z = project_points(points.expand(len(depth), -1, -1), K, cam_to_world)
    pixel = uv.round().long()
    seen = (z > 0) & (pixel[..., 0] >= 0) & (pixel[..., 0] < width) & (pixel[..., 1] >= 0) & (pixel[..., 1] < height)
    flat = (pixel[..., 1].clamp(0, height - 1) * width + pixel[..., 0].clamp(0, width - 1))
    reading = torch.gather(depth.reshape(len(depth), -1).double(), 1, flat)
    return z, torch.where(seen, reading, 0.0), seen


# ---------------------------------------------------------------------------------------------
# poses


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternion (4,), normalised here -> Hamilton rotation matrix (3, 3), float64
    (scipy's `Rotation.from_quat`, whose default order is the same scalar-last one). InputError for a
    quaternion of zero length or with NaN."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all() or not np.linalg.norm(q) > 1e-12:
        raise InputError(f"quaternion (x y z w) {q.tolist()} is not a rotation (zero length, NaN or not 4 "
                         f"numbers); correct the pose")
    return Rotation.from_quat(q).as_matrix()
