"""Photometric stereo (Woodham 1980), batched in PyTorch (CPU or CUDA: the inputs' device).

Frames: the project's camera frame (OpenCV: x right, y down, z forward). Light directions point from
the surface towards the light; normals facing the camera have z < 0. Pixel (u, v) = (column, row).

A Lambertian pixel of albedo rho and normal n under a distant light l of unit intensity reads
I = rho max(0, n . l). With every light lit, g = rho n solves the linear least squares L g = I
(`least_squares_stereo`, the DiLiGenT baseline). Shadows (I = 0 where n . l > 0 for a cast shadow, or
the clamp for an attached one) and highlights (I above the Lambertian value) break it; `trimmed_stereo`
drops the darkest and brightest observations of each pixel, `robust_stereo` starts there and iterates
reweighted least squares (Tukey weights on the residual relative to the albedo, zero weight where the
current normal faces away from the light).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import PhotometricCapture


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
