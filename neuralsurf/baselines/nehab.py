"""Depth maps fused with normal maps (Nehab, Rusinkiewicz, Davis & Ramamoorthi, SIGGRAPH 2005).

"Efficiently combining positions and normals for precise 3D geometry": a range scanner measures
positions with low-frequency accuracy and high-frequency noise; photometric stereo measures normals
with the opposite character. Nehab et al. solve one sparse linear least-squares problem for the
depth of every pixel: the positions stay close to the measured ones, and the surface's tangents
are perpendicular to the measured normals.

Perspective form used here (OpenCV camera, z forward). Pixel (u, v) has the camera ray
r(u, v) = K^-1 (u, v, 1) (z component 1) and the unknown z-depth z(u, v), so its point is z r. Then

    E(z) = lambda * sum_p |r_p|^2 (z_p - z0_p)^2                  (distance along the ray)
         + (1 - lambda) * sum_(p,q) c_pq (n_pq . (z_q r_q - z_p r_p))^2   (tangents _|_ normals)

over neighbouring pixels p, q (right and down), with n_pq the normalised mean of their normals and
c_pq the product of their confidences. Both terms are linear in z: the minimiser solves the sparse
normal equations (SciPy's direct solver). Unlike the paper, the normals are used as given (the
paper first corrects the low frequencies of the photometric normals with the smoothed range
normals; robust photometric stereo on a calibrated rig has little such bias). Pixels across a depth
discontinuity of the measured depth get no tangent row.

A depth map of lower resolution than the normal map (a Kinect beside a camera) is first resampled
to the normal map's pixels (`cameras.resample_depth`: bilinear where the four neighbours are valid and
close in depth, else missing).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from neuralsurf.cameras import pixel_rays, resample_depth
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import DepthFrames


def fuse_depth_normals(depth: Tensor, normals: Tensor, K: Tensor, confidence: Tensor | None = None,
                       position_weight: float = 0.1, max_depth_jump: float = 0.05) -> Tensor:
    """Nehab et al. 2005: the z-depth closest to `depth` whose tangents are perpendicular to `normals`.

    Args:
        depth: Float[Tensor, "h w"] measured z-depth (metres, 0 = missing), at the normals' pixels
            (`resample_depth` a lower-resolution map first).
        normals: Float[Tensor, "h w 3"] unit normals in the camera frame (0 = missing).
        K: Float[Tensor, "3 3"] intrinsics of both.
        confidence: Float[Tensor, "h w"] in [0, 1] weighting each normal (None: 1 where it exists).
        position_weight: lambda in (0, 1]: the weight of the positions against the tangents.
        max_depth_jump: neighbours whose measured depths differ by more than this fraction are
            across a discontinuity: no tangent row joins them.
    Returns:
        Float[Tensor, "h w"] (depth's dtype): the fused z-depth where the depth was measured, 0 elsewhere.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    if not 0 < position_weight <= 1:
        raise ConfigError(f"position_weight (Nehab's lambda) must lie in (0, 1], got {position_weight}")
    depth = torch.as_tensor(depth)
    normals = torch.as_tensor(normals)
    h, w = depth.shape[-2:]
    if depth.ndim != 2 or normals.shape != (h, w, 3):
        raise InputError(f"fuse_depth_normals needs depth (h, w) and normals (h, w, 3) of one view, got "
                         f"{tuple(depth.shape)} and {tuple(normals.shape)}")
    z0 = depth.double().cpu().numpy()
    n = torch.nn.functional.normalize(normals.double().cpu(), dim=-1).numpy()
    has_normal = np.linalg.norm(normals.double().cpu().numpy(), axis=-1) > 0.5
    c = (np.ones((h, w)) if confidence is None else torch.as_tensor(confidence).double().cpu().numpy()) * has_normal
    valid = z0 > 0
    if not valid.any():
        raise InputError("fuse_depth_normals: every depth pixel is missing (0); nothing to fuse")
    index = np.full((h, w), -1, dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    rays = pixel_rays(torch.as_tensor(K, dtype=torch.float64).cpu(), h, w).numpy()
    m = int(valid.sum())
    rows, cols, vals, rhs = [], [], [], []
    # positions: sqrt(lambda) |r| (z - z0)
    e = np.arange(m)
    scale = np.sqrt(position_weight) * np.linalg.norm(rays[valid], axis=-1)
    rows.append(e)
    cols.append(e)
    vals.append(scale)
    rhs.append(scale * z0[valid])
    count = m
    for axis in (0, 1):
        sl_a = (slice(0, h - 1), slice(None)) if axis == 0 else (slice(None), slice(0, w - 1))
        sl_b = (slice(1, h), slice(None)) if axis == 0 else (slice(None), slice(1, w))
        za, zb = z0[sl_a], z0[sl_b]
        weight = c[sl_a] * c[sl_b]
        pair = valid[sl_a] & valid[sl_b] & (weight > 0) & (np.abs(za - zb) <= max_depth_jump * np.maximum(za, zb))
        if not pair.any():
            continue
        normal = n[sl_a][pair] + n[sl_b][pair]
        normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        root = np.sqrt((1 - position_weight) * weight[pair])
        e = np.arange(count, count + int(pair.sum()))
        count += len(e)
        # n . (z_b r_b - z_a r_a) = 0
        rows += [e, e]
        cols += [index[sl_b][pair], index[sl_a][pair]]
        vals += [root * (normal * rays[sl_b][pair]).sum(-1), -root * (normal * rays[sl_a][pair]).sum(-1)]
        rhs.append(np.zeros(len(e)))
    A = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(count, m)).tocsr()
    b = np.concatenate(rhs)
    z = spsolve((A.T @ A).tocsc(), A.T @ b)
    out = np.zeros((h, w))
    out[valid] = z
    return torch.from_numpy(out).to(depth.dtype if depth.is_floating_point() else torch.float32)


def fuse_frames(frames: DepthFrames, normals: Tensor, K: Tensor, confidence: Tensor | None = None,
                position_weight: float = 0.1, max_depth_jump: float = 0.05) -> DepthFrames:
    """Every frame of `frames` fused with its normal map (`fuse_depth_normals`) at the normal maps'
    resolution.

    Args:
        frames: v depth frames (any resolution) with the poses of the normal maps' cameras.
        normals: Float[Tensor, "v h w 3"] camera-frame unit normals (0 = missing).
        K: Float[Tensor, "v 3 3"] (or "3 3") intrinsics of the normal maps.
        confidence: Float[Tensor, "v h w"] or None.
    Returns:
        DepthFrames (v, h, w) with the fused depth, K and the frames' poses.
    """
    normals = torch.as_tensor(normals)
    if normals.ndim != 4 or normals.shape[0] != len(frames) or normals.shape[-1] != 3:
        raise InputError(f"fuse_frames needs one normal map (h, w, 3) per frame: {len(frames)} frames, normals "
                         f"of shape {tuple(normals.shape)}")
    v, h, w = normals.shape[:3]
    K = torch.as_tensor(K, dtype=torch.float32)
    K = K.expand(v, 3, 3) if K.shape == (3, 3) else K
    fused = []
    for i in range(v):
        up = resample_depth(frames.depth[i], frames.K[i], K[i], h, w, max_depth_jump)
        fused.append(fuse_depth_normals(up, normals[i], K[i], None if confidence is None else confidence[i],
                                        position_weight, max_depth_jump).float())
    return DepthFrames(torch.stack(fused), K.float(), frames.cam_to_world.float())


__all__ = ["fuse_depth_normals", "fuse_frames"]
