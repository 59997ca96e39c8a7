"""Photometric stereo and normal integration, batched in PyTorch (CPU or CUDA: the inputs' device).

Frames: the project's camera frame (OpenCV: x right, y down, z forward). Light directions point from
the surface towards the light; normals facing the camera have z < 0. Pixel (u, v) = (column, row).

Photometric stereo (Woodham 1980): a Lambertian pixel of albedo rho and normal n under a distant light
l of unit intensity reads I = rho max(0, n . l). With every light lit, g = rho n solves the linear
least squares L g = I (`least_squares_stereo`, the DiLiGenT baseline). Shadows (I = 0 where n . l > 0 for
a cast shadow, or the clamp for an attached one) and highlights (I above the Lambertian value) break
it; `trimmed_stereo` drops the darkest and brightest observations of each pixel, `robust_stereo`
starts there and iterates reweighted least squares (Tukey weights on the residual relative to the
albedo, zero weight where the current normal faces away from the light).

Normal integration: `integrate_least_squares` (the gradient field's least-squares surface, centred
differences) and `integrate_bilateral` (bilateral normal integration, Cao et al., ECCV 2022: one-sided
differences reweighted so that the surface may break at depth discontinuities). Orthographic
(no K: depth in units of `pixel_size`, up to an offset) or perspective (K: log-depth, depth up to a
scale). Both are sparse linear least squares, solved directly (SciPy's SuperLU).

Chrome-ball calibration: light directions from the highlight on a mirror sphere.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import PhotometricCapture, check_intrinsics

# ----------------------------------------------------------------------------------------------
# photometric stereo


@dataclass(frozen=True)
class PhotometricStereoResult:
    """Normals and albedo recovered by photometric stereo, per pixel of one view."""

    normals: Tensor
    """Float[Tensor, "h w 3"]: unit normals in the camera frame (z < 0 faces the camera); 0 where not solved."""
    albedo: Tensor
    """Float[Tensor, "h w 3"] or Float[Tensor, "h w"]: Lambertian albedo (per channel for colour images)."""
    confidence: Tensor
    """Float[Tensor, "h w"]: in [0, 1]; 1 - the relative residual of the fit, times the share of
    usable observations kept (robust methods); 0 where not solved."""
    mask: Tensor
    """Bool[Tensor, "h w"]: pixels solved (inside the input mask, with at least 3 usable observations)."""
    inliers: Tensor
    """Float[Tensor, "h w"]: number of observations (weights summed) the final fit used."""


def _check_inputs(images: Tensor, lights: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    images = torch.as_tensor(images)
    if not images.is_floating_point():
        images = images.float()
    if images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[-1] != 3):
        raise InputError(f"images must be (n, h, w) or (n, h, w, 3), got {tuple(images.shape)}")
    lights = torch.as_tensor(lights, device=images.device).to(images.dtype)
    if lights.shape != (images.shape[0], 3):
        raise InputError(
            f"lights must be (n, 3) with one direction per image: {images.shape[0]} images, got lights of "
            f"shape {tuple(lights.shape)}"
        )
    if images.shape[0] < 3:
        raise InputError(f"photometric stereo needs at least 3 lights, got {images.shape[0]}")
    if not torch.isfinite(lights).all():
        raise InputError(f"lights hold NaN or inf (rows {_bad_rows(lights)}): check the light directions file")
    norms = lights.norm(dim=-1, keepdim=True)
    if (norms < 1e-8).any():
        raise InputError("a light direction is zero; give unit directions towards each light")
    h, w = images.shape[1:3]
    if mask is None:
        mask = torch.ones(h, w, dtype=torch.bool, device=images.device)
    mask = torch.as_tensor(mask, device=images.device).bool()
    if mask.shape != (h, w):
        raise InputError(f"mask must be (h, w) = {(h, w)}, got {tuple(mask.shape)}")
    finite = torch.isfinite(images.sum(0))  # one pass; a NaN or inf in any image stays in the sum
    finite = finite.all(-1) if images.ndim == 4 else finite
    if not finite[mask].all():
        raise InputError(f"images hold NaN or inf at {int((~finite & mask).sum())} masked pixels: give finite "
                         f"intensities, or leave those pixels out of the mask")
    _check_exposure(images, mask)
    return images, lights / norms, mask


SATURATED_SHARE = 0.1
"""Share of the masked intensities at their image's maximum above which the images count as clipped."""


def _check_exposure(images: Tensor, mask: Tensor) -> None:
    """InputError for an empty mask or images black inside it; a warning when more than
    SATURATED_SHARE of the masked intensities of images[n, h, w(, 3)] sit at their image's maximum
    (a clipped, saturated exposure: the Lambertian fit turns such pixels towards the camera)."""
    h, w = mask.shape
    if not mask.any():
        raise InputError(f"the mask is empty (0 of {h} x {w} pixels): nothing to solve; check the mask "
                         f"(mask.png: white where the object is) or pass mask=None for every pixel")
    masked = images[:, mask]  # (n, p) or (n, p, 3)
    peak = masked.reshape(len(masked), -1).amax(dim=1)  # each image's brightest masked intensity
    if not (peak > 0).any():
        raise InputError(f"every image is black inside the mask ({int(mask.sum())} pixels, all intensities <= 0): "
                         f"check the exposure, the light intensities and that the files are the capture's")
    at_peak = masked >= peak.reshape(-1, *[1] * (masked.ndim - 1)) * (1 - 1e-6)
    share = float(at_peak[peak > 0].float().mean())
    if share > SATURATED_SHARE:
        pixels = int(at_peak.reshape(len(masked), masked.shape[1], -1).any(-1).any(0).sum())
        warnings.warn(f"{share:.0%} of the masked intensities sit at their image's maximum ({pixels} of "
                      f"{masked.shape[1]} pixels in at least one image): the images look saturated (clipped), "
                      f"and the normals of those pixels will face the camera; lower the exposure, or leave "
                      f"saturated pixels out of the mask", stacklevel=4)


def _bad_rows(values: Tensor) -> list[int]:
    """Indices (at most 5) of the rows of values [n, ...] holding NaN or inf."""
    return (~torch.isfinite(values.flatten(start_dim=1)).all(-1)).nonzero()[:5, 0].tolist()


def _gather(images: Tensor, mask: Tensor) -> tuple[Tensor, Tensor | None]:
    """Grey observations [n, p] of the masked pixels, and colour ones [n, p, 3] (or None)."""
    n = images.shape[0]
    full = bool(mask.all())  # no copy when every pixel is solved
    if images.ndim == 4:
        color = images.reshape(n, -1, 3) if full else images[:, mask]  # (n, p, 3)
        return color.mean(-1), color
    return (images.reshape(n, -1) if full else images[:, mask]), None


def _solve_sym3(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Solve p symmetric 3x3 systems a [p, 3, 3] x = b [p, 3] by the adjugate; returns x and det [p]."""
    r0, r1, r2 = a[:, 0], a[:, 1], a[:, 2]
    c12, c20, c01 = torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)
    det = (r0 * c12).sum(-1)
    x = (b[:, :1] * c12 + b[:, 1:2] * c20 + b[:, 2:] * c01) / torch.where(det.abs() > 0, det, 1.0)[:, None]
    return x, det


def _weighted_fit(gray: Tensor, lights: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Per-pixel weighted least squares of g: weights [n, p], gray [n, p] -> g [p, 3], well-posed [p]."""
    outer = (lights[:, :, None] * lights[:, None, :]).reshape(-1, 9)  # (n, 9)
    a = (weights.T @ outer).reshape(-1, 3, 3)
    b = (weights * gray).T @ lights
    g, det = _solve_sym3(a, b)
    # well posed: at least 3 observations and the kept lights not (nearly) coplanar; unit lights make
    # the trace of a the summed weight
    count = a.diagonal(dim1=1, dim2=2).sum(-1)
    scale = (count / 3).clamp_min(1e-12)
    ok = (count >= 3 - 1e-4) & (det.abs() > 1e-6 * scale**3)
    return torch.where(ok[:, None], g, 0.0), ok


def _pixel_outputs(
    g: Tensor,
    ok: Tensor,
    gray: Tensor,
    color: Tensor | None,
    lights: Tensor,
    weights: Tensor,
    usable: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Per-pixel outputs of a weighted fit g [p, 3]: normal [p, 3], albedo [p] or [p, 3] (per channel),
    confidence [p], solved [p] and summed weight [p]."""
    rho = g.norm(dim=-1)
    ok = ok & (rho > 0)
    normal = g / rho.clamp_min(1e-12)[:, None]
    shading = lights @ normal.T  # (n, p)
    weighted_shading = weights * shading
    # per-channel albedo: weighted least squares of I_c = rho_c s over the observations kept
    s2 = (weighted_shading * shading).sum(0).clamp_min(1e-12)
    if color is not None:
        albedo = torch.einsum("np,npc->pc", weighted_shading, color) / s2[:, None]
    else:
        albedo = rho
    residual = (weights * (gray - rho[None] * shading) ** 2).sum(0)
    energy = (weights * gray**2).sum(0).clamp_min(1e-12)
    confidence = (1 - (residual / energy).sqrt()).clamp(0, 1)
    kept = weights.sum(0)
    if usable is not None:  # share of the usable observations the robust fit kept
        confidence = confidence * (kept / usable.clamp_min(1)).clamp(0, 1)
    confidence = torch.where(ok, confidence, 0.0)
    normal = torch.where(ok[:, None], normal, 0.0)
    albedo = torch.where(ok[:, None] if albedo.ndim == 2 else ok, albedo, 0.0)
    return normal, albedo, confidence, ok, kept


def _assemble(mask: Tensor, outputs: tuple[Tensor, ...]) -> PhotometricStereoResult:
    """Per-pixel outputs of the masked pixels -> (h, w, ...) maps (a reshape when every pixel is solved)."""
    h, w = mask.shape
    if bool(mask.all()):
        return PhotometricStereoResult(*(t.reshape(h, w, *t.shape[1:]) for t in outputs))
    return _maps(mask, *outputs)


def _by_chunks(gray: Tensor, color: Tensor | None, chunk: int | None, fit) -> tuple[Tensor, ...]:
    """Run `fit(gray [n, q], color [n, q, 3] | None) -> per-pixel outputs` over chunks of q pixels and
    concatenate (bounds the memory of the (n, q) temporaries; None: all pixels at once)."""
    p = gray.shape[1]
    if chunk is not None and not (isinstance(chunk, int) and chunk > 0):
        raise ConfigError(f"chunk_pixels must be a positive integer or None, got {chunk!r}")
    if chunk is None or chunk >= p:
        return fit(gray, color)
    parts = [
        fit(
            gray[:, i : i + chunk].contiguous(),
            None if color is None else color[:, i : i + chunk].contiguous(),
        )
        for i in range(0, p, chunk)
    ]
    return tuple(torch.cat(values) for values in zip(*parts))


def least_squares_stereo(
    images: Tensor, lights: Tensor, mask: Tensor | None = None
) -> PhotometricStereoResult:
    """Lambertian photometric stereo by linear least squares over every light (Woodham 1980).

    Args:
        images: Float[Tensor, "n h w"] or Float[Tensor, "n h w 3"] linear intensities (colour images
            are solved on their channel mean; albedo per channel).
        lights: Float[Tensor, "n 3"] directions towards the lights, camera frame (normalised here).
        mask: Bool[Tensor, "h w"] pixels to solve; None: all.
    Returns:
        PhotometricStereoResult on the images' device.
    """
    images, lights, mask = _check_inputs(images, lights, mask)
    n, h, w = images.shape[:3]
    color = images.ndim == 4
    lights64 = lights.double()
    if torch.linalg.matrix_rank(lights64) < 3:
        raise InputError(
            "the light directions are coplanar (rank < 3); photometric stereo needs 3 independent lights"
        )
    gram64 = lights64.T @ lights64
    pseudo_inverse = torch.linalg.solve(gram64, lights64.T).to(images.dtype)  # (3, n)
    gram = gram64.to(images.dtype)
    full = bool(mask.all())
    # one matrix product solves every pixel and channel: (3, n) @ (n, p * channels), a view when unmasked
    flat = images.reshape(n, -1) if full else images[:, mask].reshape(n, -1)
    solution = pseudo_inverse @ flat
    if color:
        per_channel = solution.reshape(3, -1, 3)  # g_c of each channel; the grey g is their mean (linear)
        g = per_channel.mean(-1)
        gray = flat.reshape(n, -1, 3).mean(-1)
    else:
        g, gray = solution, flat
    rho = g.norm(dim=0)
    ok = rho > 0
    normal = g / rho.clamp_min(1e-12)
    gram_normal = gram @ normal  # (3, p)
    if color:  # per-channel albedo: least squares of I_c = rho_c (n . l) = n^T A g_c / n^T A n
        albedo = (gram_normal[..., None] * per_channel).sum(0) / (gram_normal * normal).sum(0).clamp_min(
            1e-12
        )[:, None]
    else:
        albedo = rho
    energy = (gray * gray).sum(0)
    residual = (energy - (g * (gram @ g)).sum(0)).clamp_min(0)  # |I - L g|^2 at the least-squares optimum
    confidence = torch.where(ok, (1 - (residual / energy.clamp_min(1e-12)).sqrt()).clamp(0, 1), 0.0)
    normal, albedo = torch.where(ok, normal, 0.0).T, torch.where(ok[:, None] if color else ok, albedo, 0.0)
    inliers = torch.full_like(rho, float(n))
    if full:
        return PhotometricStereoResult(
            normal.reshape(h, w, 3),
            albedo.reshape(h, w, *albedo.shape[1:]),
            confidence.reshape(h, w),
            ok.reshape(h, w),
            inliers.reshape(h, w),
        )
    return _maps(mask, normal, albedo, confidence, ok, inliers)


def _maps(
    mask: Tensor, normal: Tensor, albedo: Tensor, confidence: Tensor, ok: Tensor, inliers: Tensor
) -> PhotometricStereoResult:
    """Scatter per-pixel values of the masked pixels into (h, w, ...) maps (0 elsewhere)."""
    h, w = mask.shape

    def scatter(values: Tensor) -> Tensor:
        out = torch.zeros((h, w, *values.shape[1:]), dtype=values.dtype, device=values.device)
        out[mask] = values
        return out

    return PhotometricStereoResult(
        scatter(normal), scatter(albedo), scatter(confidence), scatter(ok), scatter(inliers)
    )


def _trim_weights(gray: Tensor, dark_fraction: float, bright_fraction: float) -> Tensor:
    """Float[Tensor, "n p"]: 1 for observations ranked between the darkest and brightest cut, else 0."""
    n = gray.shape[0]
    low, high = math.floor(dark_fraction * n), math.floor(bright_fraction * n)
    by_pixel = gray.T.contiguous()  # (p, n): selection along contiguous memory is several times faster
    if n - low - high < 3:
        raise ConfigError(
            f"trimming {low} dark and {high} bright of {n} observations leaves fewer than 3; "
            f"lower dark_fraction ({dark_fraction}) or bright_fraction ({bright_fraction})"
        )
    keep = torch.ones_like(gray, dtype=torch.bool)
    if low > 0:
        keep &= gray > torch.kthvalue(by_pixel, low, dim=1).values[None]
    if high > 0:
        keep &= gray < torch.kthvalue(by_pixel, n - high + 1, dim=1).values[None]
    # ties (e.g. many pixels exactly 0 in shadow) may remove more; never fewer than needed
    return keep.to(gray.dtype)


def _check_fractions(dark_fraction: float, bright_fraction: float) -> None:
    for name, value in (("dark_fraction", dark_fraction), ("bright_fraction", bright_fraction)):
        if not 0 <= value < 1:
            raise ConfigError(f"{name} must lie in [0, 1), got {value}")


def trimmed_stereo(
    images: Tensor,
    lights: Tensor,
    mask: Tensor | None = None,
    dark_fraction: float = 0.3,
    bright_fraction: float = 0.1,
    chunk_pixels: int | None = None,
) -> PhotometricStereoResult:
    """Photometric stereo on the middle of each pixel's observations: the darkest `dark_fraction`
    (shadows) and brightest `bright_fraction` (highlights) are left out, the rest fit by least squares.

    Args and returns as `least_squares_stereo`; `chunk_pixels` pixels are solved at a time (None: all;
    a chunk bounds the memory of the (n, chunk) temporaries).
    """
    _check_fractions(dark_fraction, bright_fraction)
    images, lights, mask = _check_inputs(images, lights, mask)
    gray, color = _gather(images, mask)

    def fit(gray: Tensor, color: Tensor | None) -> tuple[Tensor, ...]:
        weights = _trim_weights(gray, dark_fraction, bright_fraction)
        g, ok = _weighted_fit(gray, lights, weights)
        return _pixel_outputs(g, ok, gray, color, lights, weights)

    return _assemble(mask, _by_chunks(gray, color, chunk_pixels, fit))


def robust_stereo(
    images: Tensor,
    lights: Tensor,
    mask: Tensor | None = None,
    iterations: int = 10,
    scale: float = 0.1,
    dark_fraction: float = 0.3,
    bright_fraction: float = 0.1,
    shadow_threshold: float = 0.02,
    chunk_pixels: int | None = None,
) -> PhotometricStereoResult:
    """Photometric stereo robust to shadows and highlights: trimmed least squares, then iteratively
    reweighted least squares.

    Each iteration weighs an observation by Tukey's biweight (1 - (r / (scale rho))^2)^2 of its residual
    r = I - rho n . l relative to the pixel's albedo rho (0 beyond `scale` rho: highlights and cast
    shadows drop out), and by 0 where the current normal faces away from the light (n . l <= 0: an
    attached shadow, which the linear model cannot fit) or where the pixel is darker than
    `shadow_threshold` times its brightest observation (a shadow).

    Args:
        images, lights, mask: as `least_squares_stereo`.
        iterations: reweighting steps after the trimmed start.
        scale: residual, as a fraction of the albedo, beyond which an observation gets no weight.
        dark_fraction, bright_fraction: the trimmed start (`trimmed_stereo`).
        shadow_threshold: observations below this fraction of the pixel's brightest are shadows.
        chunk_pixels: pixels solved at a time (None: all at once; a chunk bounds the temporaries' memory).
    Returns:
        PhotometricStereoResult; confidence counts the share of lit, unshadowed observations kept.
    """
    _check_fractions(dark_fraction, bright_fraction)
    if not (isinstance(iterations, int) and iterations >= 0):
        raise ConfigError(f"iterations must be a non-negative integer, got {iterations!r}")
    if not scale > 0:
        raise ConfigError(f"scale must be a positive fraction of the albedo, got {scale}")
    images, lights, mask = _check_inputs(images, lights, mask)
    gray, color = _gather(images, mask)

    def fit(gray: Tensor, color: Tensor | None) -> tuple[Tensor, ...]:
        lit = (gray > shadow_threshold * gray.amax(0, keepdim=True)).to(gray.dtype)
        weights = _trim_weights(gray, dark_fraction, bright_fraction) * lit
        g, ok = _weighted_fit(gray, lights, weights)
        for _ in range(iterations):
            predicted = lights @ g.T  # (n, p) = rho n . l
            rho = g.norm(dim=-1).clamp_min(1e-12)
            # Tukey weights (1 - (r / (scale rho))^2)^2, in place over the (n, p) observations
            weights = torch.sub(gray, predicted).div_(scale * rho[None]).square_()
            weights = weights.neg_().add_(1).clamp_(min=0).square_()
            weights.mul_(lit).masked_fill_(predicted <= 0, 0.0)
            g_new, ok_new = _weighted_fit(gray, lights, weights)
            g = torch.where(ok_new[:, None], g_new, g)  # a pixel whose reweighted fit degenerates keeps its g
        usable = (lit * (lights @ g.T > 0).to(gray.dtype)).sum(0)
        return _pixel_outputs(g, ok, gray, color, lights, weights, usable=usable)

    return _assemble(mask, _by_chunks(gray, color, chunk_pixels, fit))


METHODS = {"least_squares": least_squares_stereo, "trimmed": trimmed_stereo, "robust": robust_stereo}
"""Photometric-stereo methods by name (for configs): each `(images, lights, mask, **options)`."""


def photometric_stereo(
    capture: PhotometricCapture, method: str = "robust", **options
) -> PhotometricStereoResult:
    """Run one of `METHODS` on a capture's images, lights and mask (on the capture's device)."""
    if method not in METHODS:
        raise ConfigError(f"unknown photometric-stereo method {method!r}; choose one of {sorted(METHODS)}")
    return METHODS[method](capture.images, capture.light_directions, capture.mask, **options)


def render_lambertian(normals: Tensor, albedo: Tensor, lights: Tensor) -> Tensor:
    """Images of a Lambertian surface, I = albedo max(0, n . l), without cast shadows.

    Args:
        normals: Float[Tensor, "h w 3"] unit normals (0 = background, renders 0).
        albedo: Float[Tensor, "h w"] or Float[Tensor, "h w 3"].
        lights: Float[Tensor, "n 3"] unit directions towards the lights.
    Returns:
        Float[Tensor, "n h w"] or Float[Tensor, "n h w 3"] (the albedo's channels).
    """
    shading = torch.einsum("nk,hwk->nhw", lights.to(normals), normals).clamp_min(0)
    return shading[..., None] * albedo[None] if albedo.ndim == 3 else shading * albedo[None]


@dataclass(frozen=True)
class AngularError:
    """Angle between estimated and true normals, over the pixels where both are given."""

    mean_deg: float
    median_deg: float
    errors_deg: Tensor
    """Float[Tensor, "h w"]: per-pixel angle in degrees (0 outside `mask`)."""
    mask: Tensor
    """Bool[Tensor, "h w"]: pixels compared."""


def angular_error(estimate: Tensor, truth: Tensor, mask: Tensor | None = None) -> AngularError:
    """Mean and median angle in degrees between normal maps estimate, truth [h, w, 3], over `mask`
    (default: where both are non-zero). Pixels where the estimate is zero (unsolved) count as 90 deg."""
    if estimate.shape != truth.shape or estimate.shape[-1] != 3:
        raise InputError(
            f"normal maps must both be (h, w, 3), got {tuple(estimate.shape)} and {tuple(truth.shape)}"
        )
    truth = truth.to(estimate)
    if mask is None:
        mask = truth.norm(dim=-1) > 0
    mask = mask.to(estimate.device).bool()
    if not mask.any():
        raise InputError("no pixel to compare: the mask (or the true normal map) is empty")
    a = torch.nn.functional.normalize(estimate.double(), dim=-1)
    b = torch.nn.functional.normalize(truth.double(), dim=-1)
    # atan2 of |a x b| and a . b: accurate for small angles, unlike acos
    angles = torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1)))
    angles = torch.where(estimate.norm(dim=-1) > 0, angles, torch.full_like(angles, 90.0))
    angles = torch.where(mask, angles, 0.0)
    picked = angles[mask]
    return AngularError(float(picked.mean()), float(picked.median()), angles.float(), mask)


# ----------------------------------------------------------------------------------------------
# chrome-ball light calibration


@dataclass(frozen=True)
class ChromeBallCalibration:
    """Light directions from the highlights on a mirror sphere (orthographic viewer along +z)."""

    directions: Tensor
    """Float[Tensor, "n 3"]: unit directions towards the lights, camera frame."""
    highlights: Tensor
    """Float[Tensor, "n 2"]: (u, v) pixel of each highlight's centroid."""
    center: Tensor
    """Float[Tensor, "2"]: (u, v) of the sphere's centre in the image."""
    radius: float
    """Sphere radius in pixels."""


def sphere_from_mask(mask: Tensor) -> tuple[Tensor, float]:
    """Centre (u, v) [2] and radius (pixels) of the disc a sphere's mask [h, w] covers: the centroid of
    the mask and the radius of a disc of its area."""
    mask = torch.as_tensor(mask).bool()
    if mask.sum() < 10:
        raise InputError(f"the chrome-ball mask has {int(mask.sum())} pixels; it must cover the sphere")
    v, u = torch.nonzero(mask, as_tuple=True)
    center = torch.stack([u.double().mean(), v.double().mean()])
    return center, math.sqrt(float(mask.sum()) / math.pi)


def reflect_view(normals: Tensor) -> Tensor:
    """Float[Tensor, "... 3"]: directions towards the light that a mirror with unit `normals` [..., 3]
    (camera frame) reflects into an orthographic camera: l = 2 (n . v) n - v with v = (0, 0, -1)."""
    view = torch.tensor([0.0, 0.0, -1.0], dtype=normals.dtype, device=normals.device)
    return 2 * (normals * view).sum(-1, keepdim=True) * normals - view


def calibrate_chrome_ball(images: Tensor, mask: Tensor, threshold: float = 0.5) -> ChromeBallCalibration:
    """Light directions from images of a mirror sphere, one light each.

    The sphere is the disc of `mask` (`sphere_from_mask`). In each image the highlight is the
    connected blob of pixels inside the disc at least `threshold` times as bright as the brightest one
    (the blob holding that pixel); its centroid (u, v), weighted by the intensity above the threshold
    (uniform over a saturated blob), gives the sphere normal
    n = ((u - cu) / r, (v - cv) / r, -sqrt(1 - ...)) and the light is the view direction reflected
    about it (`reflect_view`; the viewer is orthographic, along +z).

    Args:
        images: Float[Tensor, "n h w"] or Float[Tensor, "n h w 3"]; mask: Bool[Tensor, "h w"] of the sphere.
    Returns:
        ChromeBallCalibration.
    """
    from scipy import ndimage

    images = torch.as_tensor(images).float().cpu()
    images = images.mean(-1) if images.ndim == 4 else images
    mask = torch.as_tensor(mask).bool().cpu()
    if images.ndim != 3 or images.shape[1:] != mask.shape:
        raise InputError(
            f"images must be (n, h, w[, 3]) matching the mask {tuple(mask.shape)}, got {tuple(images.shape)}"
        )
    if not 0 < threshold <= 1:
        raise ConfigError(f"threshold must lie in (0, 1], got {threshold}")
    center, radius = sphere_from_mask(mask)
    v, u = torch.meshgrid(torch.arange(mask.shape[0]), torch.arange(mask.shape[1]), indexing="ij")
    inside = ((u - center[0]) ** 2 + (v - center[1]) ** 2) < (0.98 * radius) ** 2
    inside &= mask
    highlights = []
    for i, image in enumerate(images):
        values = torch.where(inside, image, 0.0)
        peak = float(values.max())
        if peak <= 0:
            raise InputError(f"image {i} of the chrome ball is black inside the sphere: no highlight to find")
        labels, _ = ndimage.label((values >= threshold * peak).numpy())
        brightest = np.unravel_index(int(values.argmax()), values.shape)
        blob = torch.from_numpy(labels == labels[brightest])
        weight = (
            torch.where(blob, values - threshold * peak, 0.0).double() + 1e-12 * blob
        )  # saturated: uniform
        highlights.append(torch.stack([(weight * u).sum(), (weight * v).sum()]) / weight.sum())
    highlights = torch.stack(highlights)
    xy = (highlights - center) / radius
    z = -(1 - (xy**2).sum(-1)).clamp_min(0).sqrt()
    normals = torch.cat([xy, z[:, None]], -1)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    return ChromeBallCalibration(reflect_view(normals).float(), highlights.float(), center.float(), radius)


# ----------------------------------------------------------------------------------------------
# normal integration


@dataclass(frozen=True)
class NormalIntegration:
    """A depth map integrated from a normal map."""

    depth: Tensor
    """Float[Tensor, "h w"]: perspective: z-depth up to a global scale (median 1 over the mask);
    orthographic: relative depth in units of `pixel_size`, up to an offset (mean 0 over the mask);
    0 outside the mask."""
    mask: Tensor
    """Bool[Tensor, "h w"]: pixels integrated."""
    iterations: int
    """Reweighting iterations run (0 for least squares)."""


def _gradients(normals: Tensor, mask: Tensor, K: Tensor | None, pixel_size: float, max_slope: float):
    """Target derivatives (p along u, q along v) of depth (orthographic) or log-depth (perspective)."""
    n = normals.double().cpu().numpy()
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    h, w = mask.shape
    if K is None:
        denominator = nz
        px, qy = -nx * pixel_size, -ny * pixel_size
        lateral = np.ones((h, w))
    else:
        K = np.asarray(torch.as_tensor(K, dtype=torch.float64).cpu())
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
        denominator = nx * x + ny * y + nz  # n . r with r = (x, y, 1)
        px, qy = -nx / K[0, 0], -ny / K[1, 1]
        lateral = np.full((h, w), K[0, 0])  # log-depth difference * f = depth difference in pixel footprints
    # grazing normals (n . r -> 0) give unbounded slopes: limit them to `max_slope` (in pixel footprints)
    limit = max_slope / (lateral if K is not None else 1.0 / pixel_size)
    safe = np.where(np.abs(denominator) > 1e-12, denominator, -1e-12)
    p = np.clip(px / safe, -limit, limit)
    q = np.clip(qy / safe, -limit, limit)
    return p, q, (lateral if K is not None else np.full((h, w), 1.0 / pixel_size))


def _check_integration_inputs(normals: Tensor, mask: Tensor | None, K) -> tuple[Tensor, Tensor]:
    normals = torch.as_tensor(normals)
    if normals.ndim != 3 or normals.shape[-1] != 3:
        raise InputError(f"normals must be an (h, w, 3) normal map, got {tuple(normals.shape)}")
    finite = torch.isfinite(normals).all(-1).cpu()
    if mask is None:
        mask = ~finite | (normals.norm(dim=-1) > 0).cpu()
    mask = torch.as_tensor(mask).bool().cpu()
    if mask.shape != normals.shape[:2]:
        raise InputError(f"mask must be (h, w) = {tuple(normals.shape[:2])}, got {tuple(mask.shape)}")
    if not finite[mask].all():
        raise InputError(f"normals hold NaN or inf at {int((~finite & mask).sum())} masked pixels: mark pixels "
                         f"without a normal by a zero normal or leave them out of the mask")
    if mask.sum() < 2:
        raise InputError("the mask holds fewer than 2 pixels: nothing to integrate")
    if K is not None:
        if tuple(torch.as_tensor(K).shape) != (3, 3):
            raise InputError(f"K must be 3x3, got {tuple(torch.as_tensor(K).shape)}")
        check_intrinsics(torch.as_tensor(K, dtype=torch.float64)[None], normals.shape[1], normals.shape[0])
    return normals, mask


def _unknown_index(mask: np.ndarray) -> np.ndarray:
    """Int64[ndarray, "h w"]: each mask pixel's unknown (0, 1, ... in row-major order), -1 elsewhere."""
    index = np.full(mask.shape, -1, dtype=np.int64)
    index[mask] = np.arange(int(mask.sum()))
    return index


def _pairs(
    mask: np.ndarray, index: np.ndarray, axis: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel pairs (a, b) with b the next pixel along `axis` (1: u, 0: v), both in the mask: flat
    positions in the image and unknown indices."""
    if axis == 1:
        both = mask[:, :-1] & mask[:, 1:]
        rows, cols = np.nonzero(both)
        a, b = rows * mask.shape[1] + cols, rows * mask.shape[1] + cols + 1
    else:
        both = mask[:-1] & mask[1:]
        rows, cols = np.nonzero(both)
        a, b = rows * mask.shape[1] + cols, (rows + 1) * mask.shape[1] + cols
    return a, b, index.ravel()[a], index.ravel()[b]


def _solve(matrix, rhs: np.ndarray, refinements: int = 3) -> np.ndarray:
    """Solve the normal equations of a difference system (symmetric, positive semi-definite: each
    connected region's depth is free up to a constant) by a sparse LU factorisation after a tiny
    Tikhonov term (1e-9 of the mean diagonal) that fixes those constants, then remove the term's bias by
    iterative refinement against the unregularised system."""
    from scipy.sparse import identity
    from scipy.sparse.linalg import splu

    epsilon = 1e-9 * float(matrix.diagonal().mean())
    factor = splu(
        (matrix + epsilon * identity(matrix.shape[0], format="csr")).tocsc(), permc_spec="MMD_AT_PLUS_A"
    )
    solution = factor.solve(rhs)
    for _ in range(refinements):
        solution = solution + factor.solve(rhs - matrix @ solution)
    return solution


def _finish(t: np.ndarray, mask: Tensor, K, iterations: int, dtype) -> NormalIntegration:
    if K is None:
        values = t - t.mean()
    else:
        values = np.exp(t - np.median(t))
    depth = np.zeros(mask.shape)
    depth[mask.numpy()] = values
    return NormalIntegration(torch.from_numpy(depth).to(dtype), mask, iterations)


def integrate_least_squares(
    normals: Tensor,
    mask: Tensor | None = None,
    K: Tensor | None = None,
    pixel_size: float = 1.0,
    max_slope: float = 50.0,
) -> NormalIntegration:
    """Depth from a normal map by least squares: for each pair of neighbouring mask pixels, the depth
    difference (log-depth under perspective) should be the mean of their two target derivatives.

    Args:
        normals: Float[Tensor, "h w 3"] unit normals, camera frame (z < 0 faces the camera).
        mask: Bool[Tensor, "h w"]; None: where the normals are non-zero.
        K: Float[Tensor, "3 3"] for a perspective camera; None: orthographic, pixels `pixel_size` apart.
        max_slope: derivatives are limited to this many depth units per pixel footprint (grazing normals).
    Returns:
        NormalIntegration (depth up to scale under perspective, up to an offset under orthographic).
    """
    from scipy.sparse import coo_matrix

    normals, mask = _check_integration_inputs(normals, mask, K)
    m = mask.numpy()
    index = _unknown_index(m)
    p, q, _ = _gradients(normals, mask, K, pixel_size, max_slope)
    rows, cols, vals, rhs = [], [], [], []
    count = 0
    for axis, target in ((1, p.ravel()), (0, q.ravel())):
        a, b, ia, ib = _pairs(m, index, axis)
        e = np.arange(count, count + len(a))
        rows += [e, e]
        cols += [ib, ia]
        vals += [np.ones(len(a)), -np.ones(len(a))]
        rhs.append((target[a] + target[b]) / 2)
        count += len(a)
    A = coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(count, int(m.sum()))
    ).tocsr()
    b = np.concatenate(rhs)
    t = _solve((A.T @ A).tocsr(), A.T @ b)
    return _finish(t, mask, K, 0, normals.dtype if normals.is_floating_point() else torch.float32)


def integrate_bilateral(
    normals: Tensor,
    mask: Tensor | None = None,
    K: Tensor | None = None,
    pixel_size: float = 1.0,
    k: float = 0.5,
    iterations: int = 100,
    tolerance: float = 1e-4,
    max_slope: float = 50.0,
) -> NormalIntegration:
    """Discontinuity-preserving depth from a normal map: bilateral normal integration (BiNI, Cao et
    al., ECCV 2022).

    Every pixel asks its forward and backward differences along u and v to equal its own derivative.
    The two sides along an axis share a unit weight by a sigmoid of the difference of their squared
    depth jumps, w+ = sigmoid(k ((D- z)^2 - (D+ z)^2)), w- = 1 - w+, so that at a discontinuity the
    side across the jump loses its weight; weights and depth are updated in turn (reweighted least
    squares) until the energy changes by less than `tolerance` (relative). Depth jumps are measured in
    pixel footprints (log-depth differences times the focal length under perspective), so `k` means
    the same in both camera models. A pixel with one neighbour along an axis uses that side alone.

    Args: as `integrate_least_squares`, plus the sharpness `k`, `iterations` and `tolerance`.
    Returns:
        NormalIntegration.
    """
    from scipy.sparse import coo_matrix, diags

    if not k > 0:
        raise ConfigError(f"k must be positive, got {k}")
    normals, mask = _check_integration_inputs(normals, mask, K)
    m = mask.numpy()
    n_unknowns = int(m.sum())
    index = _unknown_index(m)
    p, q, footprint = _gradients(normals, mask, K, pixel_size, max_slope)
    footprint = footprint.ravel()
    # one-sided difference operators: rows = (pixel, direction), forward and backward per axis
    blocks = []  # per axis: D [pairs x unknowns] (t_b - t_a), pixels a and b, their targets, footprint
    for axis, target in ((1, p.ravel()), (0, q.ravel())):
        a, b, ia, ib = _pairs(m, index, axis)
        e = np.arange(len(a))
        D = coo_matrix(
            (np.r_[np.ones(len(a)), -np.ones(len(a))], (np.r_[e, e], np.r_[ib, ia])),
            shape=(len(a), n_unknowns),
        ).tocsr()
        blocks.append((D, ia, ib, target[a], target[b], footprint[a]))
    t = np.zeros(n_unknowns)
    done, energy_before = 0, None
    for done in range(1, iterations + 1):
        system, rhs, terms = None, np.zeros(n_unknowns), []
        for D, ia, ib, target_a, target_b, scale in blocks:
            if done == 1:  # start from equal weights: 0.5 per side where both exist
                w_forward = np.full(n_unknowns, 0.5)
                has_forward = np.zeros(n_unknowns, bool)
                has_backward = np.zeros(n_unknowns, bool)
                has_forward[ia], has_backward[ib] = True, True
            else:
                jump = (D @ t) * scale  # pair (a -> b) depth difference in pixel footprints
                forward_jump, backward_jump = np.zeros(n_unknowns), np.zeros(n_unknowns)
                has_forward = np.zeros(n_unknowns, bool)
                has_backward = np.zeros(n_unknowns, bool)
                forward_jump[ia], has_forward[ia] = jump, True  # the pair is pixel a's forward side
                backward_jump[ib], has_backward[ib] = jump, True  # and pixel b's backward side
                w_forward = 1.0 / (1.0 + np.exp(-np.clip(k * (backward_jump**2 - forward_jump**2), -50, 50)))
            w_forward = np.where(has_backward, w_forward, 1.0)
            w_backward = np.where(has_forward, 1.0 - w_forward, 1.0)
            # forward equation of a: t_b - t_a = p_a (weight wf[a]); backward one of b: t_b - t_a = p_b
            # (weight wb[b]); their sum is one equation of weight wf + wb towards the weighted target
            wf, wb = w_forward[ia], w_backward[ib]
            weight = wf + wb
            target = (wf * target_a + wb * target_b) / np.where(weight > 0, weight, 1.0)
            part = D.T @ diags(weight) @ D
            system = part if system is None else system + part
            rhs += D.T @ (weight * target)
            terms.append((D, wf, wb, target_a, target_b))
        t = _solve(system.tocsr(), rhs)
        energy = sum(
            float((wf * (D @ t - ta) ** 2 + wb * (D @ t - tb) ** 2).sum()) for D, wf, wb, ta, tb in terms
        )
        if energy_before is not None and abs(energy - energy_before) <= tolerance * abs(energy_before):
            break
        energy_before = energy
    return _finish(t, mask, K, done, normals.dtype if normals.is_floating_point() else torch.float32)


INTEGRATORS = {"least_squares": integrate_least_squares, "bilateral": integrate_bilateral}
"""Normal-integration methods by name (for configs): each `(normals, mask, K, **options) -> NormalIntegration`."""


@dataclass(frozen=True)
class DepthError:
    """Depth error after aligning an estimate that is known up to scale and/or offset."""

    mean_abs: float
    """Mean absolute difference over the mask, in the truth's units."""
    aligned: Tensor
    """Float[Tensor, "h w"]: the estimate after alignment (0 outside the mask)."""
    scale: float
    offset: float


def continuous_pieces(
    depth: Tensor,
    normals: Tensor,
    mask: Tensor | None = None,
    K: Tensor | None = None,
    pixel_size: float = 1.0,
    tolerance: float = 0.5,
    max_slope: float = 3.0,
    min_fraction: float = 0.01,
) -> Tensor:
    """The pieces of a true depth map that normal integration can recover, each up to its own scale
    (perspective) or offset (orthographic): a part seen only across an occluding contour, such as an
    ear in front of the body, is joined to the rest by no normal, so no integrator can place it.

    Neighbouring mask pixels are joined where their depth step (log-depth under perspective) is the one
    their normals predict (the mean of their target derivatives, as `integrate_least_squares` uses)
    within `tolerance` pixel footprints, and the predicted slope is at most `max_slope` footprints per
    pixel (grazing rims, where normals fix no step, join nothing). Pieces are the connected components
    of the joined pixels; those under `min_fraction` of the mask are dropped (-1).

    Args:
        depth: Float[Tensor, "h w"] true z-depth (orthographic: depth in the units of `pixel_size`).
        normals: Float[Tensor, "h w 3"] true unit normals, camera frame.
        mask: Bool[Tensor, "h w"]; None: depth > 0.
        K: Float[Tensor, "3 3"] for a perspective camera; None: orthographic.
    Returns:
        Int64[Tensor, "h w"]: a piece index per pixel (0 the largest), -1 outside every kept piece.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    depth, normals = torch.as_tensor(depth), torch.as_tensor(normals)
    if depth.ndim != 2 or tuple(normals.shape[:2]) != tuple(depth.shape):
        raise InputError(f"depth must be an (h, w) map of the normals' size, got {tuple(depth.shape)} "
                         f"and normals {tuple(normals.shape)}")
    if mask is None:
        mask = (depth > 0) | ~torch.isfinite(depth)
    normals, mask = _check_integration_inputs(normals, mask, K)
    if not torch.isfinite(depth[mask]).all():
        raise InputError("depth holds NaN or inf inside the mask: leave those pixels out of the mask")
    m = mask.numpy()
    index = _unknown_index(m)
    z = depth.double().cpu().numpy()
    t = np.log(np.where(m, z, 1.0)) if K is not None else np.where(m, z, 0.0)
    p, q, footprint = _gradients(normals, mask, K, pixel_size, math.inf)  # unclipped: steep pairs are tested below
    rows, cols = [], []
    for axis, target in ((1, p.ravel()), (0, q.ravel())):
        a, b, ia, ib = _pairs(m, index, axis)
        predicted = (target[a] + target[b]) / 2
        scale = footprint.ravel()[a]
        step = t.ravel()[b] - t.ravel()[a]
        joined = (np.abs(step - predicted) * scale <= tolerance) & (np.abs(predicted) * scale <= max_slope)
        rows.append(ia[joined])
        cols.append(ib[joined])
    n = int(m.sum())
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    _, labels = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    counts = np.bincount(labels)
    order = np.argsort(-counts, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    kept = counts >= min_fraction * n
    pieces = np.full(m.shape, -1, dtype=np.int64)
    pieces[m] = np.where(kept[labels], rank[labels], -1)
    return torch.from_numpy(pieces)


def _alignment(e: Tensor, t: Tensor, align: str) -> tuple[float, float]:
    """Least-squares (scale, offset) taking estimate values e [n] to truth t [n] under `align`."""
    if align == "scale":
        return float((e * t).sum() / (e * e).sum().clamp_min(1e-30)), 0.0
    if align == "offset":
        return 1.0, float((t - e).mean())
    if align == "scale_offset":
        design = torch.stack([e, torch.ones_like(e)], -1)
        solution = torch.linalg.lstsq(design, t[:, None]).solution[:, 0]
        return float(solution[0]), float(solution[1])
    return 1.0, 0.0


def depth_error(
    estimate: Tensor, truth: Tensor, mask: Tensor | None = None, align: str = "scale", pieces: Tensor | None = None
) -> DepthError:
    """Mean absolute error of depth estimate [h, w] against truth [h, w] over `mask` (default: truth > 0)
    after the least-squares alignment `align`: "scale" (s * estimate; perspective integration),
    "offset" (estimate + o; orthographic integration), "scale_offset" (s * estimate + o) or "none".

    With `pieces` (Int[Tensor, "h w"], `continuous_pieces`), each piece is aligned on its own and the
    mean runs over the mask's pixels in a piece (>= 0); `scale` and `offset` are then those of the lowest
    piece index scored (0, the largest, for `continuous_pieces`)."""
    if estimate.shape != truth.shape or estimate.ndim != 2:
        raise InputError(
            f"depth maps must both be (h, w), got {tuple(estimate.shape)} and {tuple(truth.shape)}"
        )
    if align not in ("scale", "offset", "scale_offset", "none"):
        raise ConfigError(f"align must be 'scale', 'offset', 'scale_offset' or 'none', got {align!r}")
    truth = truth.to(estimate.device)
    mask = (truth > 0) if mask is None else torch.as_tensor(mask, device=estimate.device).bool()
    if pieces is None:
        pieces = torch.zeros(mask.shape, dtype=torch.int64)
    elif tuple(pieces.shape) != tuple(mask.shape):
        raise InputError(f"pieces must be (h, w) = {tuple(mask.shape)}, got {tuple(pieces.shape)}")
    pieces = torch.where(mask, torch.as_tensor(pieces, device=estimate.device), -1)
    scored = pieces >= 0
    if not scored.any():
        raise InputError("no pixel to compare: the mask is empty")
    if not (torch.isfinite(estimate[scored]).all() and torch.isfinite(truth[scored]).all()):
        raise InputError("the depth maps hold NaN or inf inside the mask: leave those pixels out of the mask")
    aligned = torch.zeros(mask.shape, dtype=torch.float64, device=estimate.device)
    alignments = []
    for piece in torch.unique(pieces[scored]).tolist():  # ascending
        inside = pieces == piece
        e = estimate[inside].double()
        alignments.append(_alignment(e, truth[inside].double(), align))
        aligned[inside] = e * alignments[-1][0] + alignments[-1][1]
    scale, offset = alignments[0]
    return DepthError(
        float((aligned[scored] - truth[scored].double()).abs().mean()), aligned.to(estimate.dtype), scale, offset
    )


__all__ = [
    "INTEGRATORS",
    "METHODS",
    "AngularError",
    "ChromeBallCalibration",
    "DepthError",
    "NormalIntegration",
    "PhotometricStereoResult",
    "angular_error",
    "calibrate_chrome_ball",
    "continuous_pieces",
    "depth_error",
    "integrate_bilateral",
    "integrate_least_squares",
    "least_squares_stereo",
    "photometric_stereo",
    "reflect_view",
    "render_lambertian",
    "robust_stereo",
    "sphere_from_mask",
    "trimmed_stereo",
]
