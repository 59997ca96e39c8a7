"""Registration of a frame's surface maps to a model's: projective point-to-plane ICP with robust kernels, coarse to
fine, optionally with grey-level (photometric) rows."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.baselines.registration.estimation import small_motion
from neuralsurf.baselines.tracking.maps import SurfaceMap
from neuralsurf.devices import CompiledOnCPU
from neuralsurf.errors import ConfigError


def moved_and_projected(points: Tensor, transform: Tensor, K: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Points Float[Tensor, "n 3"] moved by `transform` Float[Tensor, "4 4"] into a camera with intrinsics K, and
    their pixel coordinates u, v and 1 / z (Float[Tensor, "n"] each; 1 where z <= 0, which callers reject)."""
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    x, y, z = moved.unbind(1)
    inverse_z = 1 / torch.where(z > 0, z, 1.0)
    return moved, (K[0, 0] * x + K[0, 1] * y) * inverse_z + K[0, 2], K[1, 1] * y * inverse_z + K[1, 2], inverse_z


def photometric_rows(points: Tensor, grey: Tensor, transform: Tensor, target: Tensor, K: Tensor
                     ) -> tuple[Tensor, Tensor]:
    """Rows [J | r] Float[Tensor, "n 7"] of the grey-level residuals r_i = I(pi(q_i)) - g_i of source points p_i
    Float[Tensor, "n 3"] with grey levels g_i Float[Tensor, "n"], moved by `transform` Float[Tensor, "4 4"] to
    q_i in the camera (intrinsics K) of a target image I with its derivatives (`with_gradients`, Float[Tensor,
    "3 h w"], sampled bilinearly), linearised in a small motion (omega, t) of q_i as `point_to_plane_rows`:
    J_i = (q_i x d_i, d_i) with d_i = grad I . d pi / d q. Also Bool[Tensor, "n"]: q_i projects inside the image."""
    q, u, v, inverse_z = moved_and_projected(points, transform, K)
    x, y, z = q.unbind(1)
    h, w = target.shape[1:]
    inside = (z > 0) & (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
    where = torch.stack([u / (w - 1), v / (h - 1)], -1) * 2 - 1
    sampled = torch.nn.functional.grid_sample(target[None], where[None, None], align_corners=True)[0, :, 0]  # (3, n)
    value, du, dv = sampled
    fx, fy = K[0, 0] * inverse_z, K[1, 1] * inverse_z
    d = torch.stack([du * fx, dv * fy, -(du * fx * x + dv * fy * y) * inverse_z], 1)  # (n, 3)
    residual = torch.where(inside, value - grey, 0.0)
    return torch.cat([torch.linalg.cross(q, d), d, residual[:, None]], 1), inside


def photometric_equations(points: Tensor, grey: Tensor, transform: Tensor, target: Tensor, K: Tensor,
                          kernel_scale: float) -> Tensor:
    """Huber-weighted normal equations Float[Tensor, "7 7"] of `photometric_rows` (pixels outside the target weigh 0)."""
    rows, inside = photometric_rows(points, grey, transform, target, K)
    weights = robust_weights(rows[:, 6], "huber", kernel_scale) * inside
    return (rows * weights[:, None]).T @ rows


def robust_weights(residuals: Tensor, kernel: str, scale: float) -> Tensor:
    """IRLS weights Float[Tensor, "n"] of residuals Float[Tensor, "n"]: "huber" min(1, scale / |r|);
    "tukey" (1 - (r / scale)^2)^2 within `scale`, else 0; "none" 1."""
    r = residuals.abs()
    if kernel == "huber":
        return torch.where(r <= scale, 1.0, scale / r.clamp_min(1e-30))
    if kernel == "tukey":
        return torch.where(r <= scale, (1 - (r / scale) ** 2) ** 2, 0.0)
    if kernel == "none":
        return torch.ones_like(r)
    raise ConfigError(f"unknown robust kernel {kernel!r}; use 'huber', 'tukey' or 'none'")


def point_to_plane_rows(source: Tensor, target: Tensor, normals: Tensor) -> Tensor:
    """Rows [J | r] Float[Tensor, "n 7"] of point-to-plane ICP linearised at the identity: r_i = n_i . (p_i - q_i)
    and J_i = (p_i x n_i, n_i), the derivative of r_i by a small motion (omega, t): exp(omega) p_i + t. `source`,
    `target`, `normals`: Float[Tensor, "n 3"] matched points p, q and target normals n."""
    (px, py, pz), (nx, ny, nz) = source.unbind(1), normals.unbind(1)
    residual = ((source - target) * normals).sum(1)
    return torch.stack([py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx, nx, ny, nz, residual], 1)


def gauss_newton_step(system: Tensor) -> Tensor | None:
    """The motion Float64[Tensor, "4 4"] [exp(omega) t; 0 1] minimising sum w_i (J_i x + r_i)^2 from its normal
    equations `system` = sum w_i [J_i r_i]^T [J_i r_i] (Float[Tensor, "7 7"]; `small_motion`, in float64 numpy,
    which solves a 6 x 6 system in less time than one torch op takes to dispatch); None when the 6 x 6 block is
    degenerate (a plane or a line constrains fewer than six directions)."""
    equations = system.double().cpu().numpy()
    motion = small_motion(equations[:6, :6], equations[:6, 6], 1e-9)
    return None if motion is None else torch.from_numpy(motion).to(system.device)


def point_to_plane_update(source: Tensor, target: Tensor, normals: Tensor, weights: Tensor) -> Tensor | None:
    """One Gauss-Newton step Float64[Tensor, "4 4"] of point-to-plane ICP on matched points (`point_to_plane_rows`)
    with weights Float[Tensor, "n"] (0 for rejected pairs), or None if degenerate (`gauss_newton_step`)."""
    rows = point_to_plane_rows(source, target, normals)
    return gauss_newton_step((rows * weights[:, None]).T @ rows)


def projective_matches(points: Tensor, normals: Tensor, transform: Tensor, model_packed: Tensor, model_valid: Tensor,
                       model_K: Tensor, max_distance: float, min_cosine: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Projective data association: source points Float[Tensor, "n 3"] with normals Float[Tensor, "n 3"] (source
    camera frame), moved by `transform` Float[Tensor, "4 4"] into the model camera, each matched with the model
    pixel it projects to (nearest) in a model map given by its `SurfaceMap.packed`, `valid` and `K` (all in the
    points' dtype). Returns the moved points, the matched model points and normals (Float[Tensor, "n 3"] each),
    and the inliers Bool[Tensor, "n"]: found, within `max_distance` and with normals agreeing to `min_cosine`."""
    moved, u, v, _ = moved_and_projected(points, transform, model_K)
    u, v, z = torch.round(u), torch.round(v), moved[:, 2]
    turned = normals @ transform[:3, :3].T
    h, w = model_valid.shape
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    index = torch.where(inside, v * w + u, 0).long()
    found = inside & model_valid.reshape(-1)[index]
    matched = model_packed[index]  # (n, 6): point, normal
    target, target_normals = matched[:, :3], matched[:, 3:]
    close = (moved - target).square().sum(1) <= max_distance**2
    agree = (turned * target_normals).sum(1) >= min_cosine
    return moved, target, target_normals, found & close & agree


def icp_equations(points: Tensor, normals: Tensor, transform: Tensor, model_packed: Tensor, model_valid: Tensor,
                  model_K: Tensor, max_distance: float, min_cosine: float, kernel: str, kernel_scale: float
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """One ICP iteration's sums over source points Float[Tensor, "n 3"] and normals Float[Tensor, "n 3"] moved by
    `transform` Float[Tensor, "4 4"] and matched in a model map (`projective_matches`; its `packed` Float[Tensor, "h*w 6"],
    `valid` Bool[Tensor, "h w"] and `K`): the robustly weighted normal equations Float[Tensor, "7 7"]
    (`point_to_plane_rows`, `robust_weights`; rejected pairs weigh 0), the inlier count Int[Tensor, ""] and the
    inliers' sum of squared residuals Float[Tensor, ""] (one function, so that it compiles to one loop)."""
    moved, target, target_normals, inlier = projective_matches(points, normals, transform, model_packed, model_valid,
                                                               model_K, max_distance, min_cosine)
    rows = point_to_plane_rows(moved, target, target_normals)
    residual = rows[:, 6]
    weights = robust_weights(residual, kernel, kernel_scale) * inlier
    squares = (residual.square() * inlier).sum()
    return (rows * weights[:, None]).T @ rows, inlier.sum(), squares


@dataclass(frozen=True)
class FrameFit:
    """The result of registering one frame to its model."""

    transform: Tensor
    """Float64[Tensor, "4 4"]: source camera -> model camera."""
    inlier_share: float
    """Share of the source's valid finest-level points that are inliers at the start of the last Gauss-Newton
    step (the finest level's; once converged, within 0.1 mm and 1e-4 rad of `transform`)."""
    rmse: float
    """Point-to-plane RMSE (metres) of those inliers."""
    degenerate: bool
    """The finest level's normal equations were singular."""


@dataclass(frozen=True)
class GreyPair:
    """The grey levels of a registration's source and target frames, one per pyramid level (finest first)."""

    source: list[Tensor]
    """Float[Tensor, "h_l w_l"]: the source's grey levels at its `SurfaceMap`s' pixels."""
    target: list[Tensor]
    """Float[Tensor, "3 h_l w_l"]: the target's grey image and its derivatives (`with_gradients`), seen by the model maps' camera."""
    weight: float
    """Metres per unit of grey level: the photometric rows' weight against the point-to-plane rows."""
    kernel_scale: float = 0.1
    """Huber scale of the grey-level residuals."""


def register_maps(source: list[SurfaceMap], model: list[SurfaceMap], init: Tensor, iterations: tuple[int, ...],
                  kernel: str, kernel_scale: float, max_distance: float, min_cosine: float,
                  compiled: bool = False, grey: GreyPair | None = None) -> FrameFit:
    """Point-to-plane ICP of a source pyramid onto a model pyramid (lists finest first, same length),
    coarse to fine from `init` Float64[Tensor, "4 4"] (source camera -> model camera); `iterations[l]`
    Gauss-Newton steps at level l (finest first). `compiled`: on a CPU, `icp_equations` through torch.compile.
    `grey`: each step also aligns the source's grey levels with the target's (`photometric_equations`)."""
    transform = init.double().clone()
    degenerate, finest = False, None
    equations = _COMPILED_EQUATIONS.on(source[0].points.device, compiled)

    def sums(level: int, points: Tensor, normals: Tensor) -> tuple[Tensor, int, float]:
        target = model[level]
        system, count, squares = equations(points, normals, transform.to(points), target.packed, target.valid,
                                           target.K.to(points), max_distance, min_cosine, kernel, kernel_scale)
        return system, int(count), float(squares)

    for level in reversed(range(len(source))):
        src, valid = source[level], source[level].valid
        points, normals = src.points[valid], src.normals[valid]
        source_grey = None if grey is None else grey.source[level][valid]
        for _ in range(iterations[level]):
            system, count, squares = sums(level, points, normals)
            if level == 0:
                finest = count, squares, len(points)
            if grey is not None:
                system = system + grey.weight**2 * photometric_equations(
                    points, source_grey, transform.to(points), grey.target[level], src.K.to(points), grey.kernel_scale)
            update = None if count < 6 else gauss_newton_step(system)
            degenerate = update is None
            if degenerate:
                break
            transform = update @ transform
            if float(update[:3, 3].norm()) < 1e-4 and float((update[:3, :3].diagonal().sum() - 1) / 2) > 1 - 5e-9:
                break  # converged: the step moved less than 0.1 mm and turned less than 1e-4 rad
    if finest is None:  # no step at the finest level: its statistics at `transform`
        points = source[0].points[source[0].valid]
        finest = *sums(0, points, source[0].normals[source[0].valid])[1:], len(points)
    count, squares, n_points = finest
    return FrameFit(transform, count / max(n_points, 1), math.sqrt(squares / count) if count else math.inf, degenerate)


_COMPILED_EQUATIONS = CompiledOnCPU(icp_equations, "camera tracking")
