"""Chrome-ball light calibration: light directions from the highlight on a mirror sphere seen by an
orthographic camera (camera frame: x right, y down, z forward; directions point towards the light)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError


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
