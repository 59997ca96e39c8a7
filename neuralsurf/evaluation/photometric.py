"""Photometric methods of the benchmark.

- `photometric_normals` (configs ps_least_squares, ps_robust): photometric stereo on every capture of
  a scene; it returns a `NormalMapResult`, not a mesh, which the runner scores by angular error
  against the ground-truth normals (`score_normal_maps`) and, with `integrate`, by the depth error
  of the integrated normal map against the rig's depth (scale-aligned, perspective).
- neural_depth, neural_depth_normals: `methods.fit_and_extract` of the depth frames as rays,
  optionally with the scene's photometric normal maps (`NormalMaps`).
- `nehab_tsdf`: each depth map fused with its normal map (Nehab et al. 2005), then TSDF fusion.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from neuralsurf.baselines.nehab import fuse_frames
from neuralsurf.cameras import pixel_rays
from neuralsurf.errors import InputError
from neuralsurf.evaluation.methods import NotApplicable, tsdf
from neuralsurf.evaluation.render import colormap, labelled_row
from neuralsurf.evaluation.store import row_stem
from neuralsurf.photometric import (
    INTEGRATORS,
    angular_error,
    continuous_pieces,
    depth_error,
    photometric_stereo,
)
from neuralsurf.scenes import Scene
from neuralsurf.structures import Mesh


@dataclass(frozen=True)
class NormalMapResult:
    """Normal maps estimated for the views of a scene (a method's output instead of a mesh)."""

    normals: tuple[Tensor, ...]
    """Float[Tensor, "h w 3"] per view: estimated unit normals, camera frame (0 = not solved)."""
    truth: tuple[Tensor | None, ...]
    """Float[Tensor, "h w 3"] per view: ground-truth normals (None when unknown)."""
    mask: tuple[Tensor, ...]
    """Bool[Tensor, "h w"] per view: the object's pixels (where it is scored)."""
    depth: tuple[Tensor | None, ...] = ()
    """Float[Tensor, "h w"] per view: depth integrated from the estimate (up to scale), or empty."""
    true_depth: tuple[Tensor | None, ...] = ()
    """Float[Tensor, "h w"] per view: the rig's z-depth (0 off the object), or empty."""
    sizes: tuple[float, ...] = ()
    """Per view with depth: the object's size (longest side of the box of its back-projected pixels)."""
    pieces: tuple[Tensor | None, ...] = ()
    """Int64[Tensor, "h w"] per view with depth: `continuous_pieces` of the truth (None without true normals)."""


def _check_photometric(scene: Scene) -> None:
    if getattr(scene, "photometric", None) is None:
        raise NotApplicable(f"scene {scene.name!r} has no photometric captures (images under known lights)")


def photometric_normals(scene: Scene, *, method: str = "robust", integrate: str | None = "least_squares",
                        options: dict[str, Any] | None = None, seed: int = 0, run_dir=None,
                        config=None) -> NormalMapResult:
    """Photometric stereo (`neuralsurf.photometric.photometric_stereo`, `method` least_squares, trimmed
    or robust) on every capture of the scene; with `integrate` (least_squares or bilateral) and a
    capture with K and depth, the estimated normals are also integrated to depth."""

    _check_photometric(scene)

    normals, truth, masks, depth, true_depth, sizes, pieces = [], [], [], [], [], [], []
    for capture in scene.photometric:
        result = photometric_stereo(capture, method, **(options or {}))
        mask = capture.pixel_mask()
        if capture.normals is not None:
            mask = mask & (capture.normals.norm(dim=-1) > 0.5)
        normals.append(result.normals)
        truth.append(capture.normals)
        masks.append(mask)
        if integrate is not None and capture.K is not None and capture.depth is not None:
            solved = mask & result.mask
            depth.append(INTEGRATORS[integrate](result.normals, solved, K=capture.K).depth)
            true_depth.append(torch.where(solved, capture.depth, 0.0))
            pieces.append(None if capture.normals is None else
                          continuous_pieces(capture.depth, capture.normals, mask, K=capture.K))
            seen = capture.depth > 0
            rays = pixel_rays(torch.as_tensor(capture.K, dtype=torch.float64).cpu(), capture.height, capture.width)
            points = rays[seen] * capture.depth[seen, None].double()
            sizes.append(float((points.max(0).values - points.min(0).values).max()))
    return NormalMapResult(tuple(normals), tuple(truth), tuple(masks), tuple(depth), tuple(true_depth), tuple(sizes),
                           tuple(pieces))


def score_normal_maps(result: NormalMapResult) -> dict[str, float]:
    """normal_error_mean_deg / normal_error_median_deg over the pixels of every view with a ground
    truth (unsolved pixels count as 90 deg), normal_coverage (share solved); with integrated depth,
    integration_depth_error (mean |dz| after the least-squares scale, as a fraction of the object's
    size, `NormalMapResult.sizes`) and its median; with ground-truth normals too,
    integration_depth_error_pieces (each `continuous_pieces` piece aligned on its own: what normals can
    determine) and integration_piece_coverage (the share of the scored pixels in a kept piece)."""

    errors, solved = [], []
    for estimate, truth, mask in zip(result.normals, result.truth, result.mask):
        if truth is None:
            continue
        error = angular_error(estimate, truth, mask)
        errors.append(error.errors_deg[error.mask])
        solved.append((estimate.norm(dim=-1) > 0)[error.mask])
    if not errors:
        raise InputError("no view has ground-truth normals: nothing to score the normal maps against")
    angles = torch.cat(errors).double()
    scores = {"normal_error_mean_deg": float(angles.mean()), "normal_error_median_deg": float(angles.median()),
              "normal_coverage": float(torch.cat(solved).float().mean()), "n_pixels": len(angles)}
    if result.depth:
        pieces = result.pieces or (None,) * len(result.depth)
        absolute, by_piece, in_pieces, piece_views_pixels = [], [], 0, 0
        for estimate, truth, size, view_pieces in zip(result.depth, result.true_depth, result.sizes, pieces,
                                                      strict=True):
            mask = (truth > 0) & (estimate > 0)
            aligned = depth_error(estimate, truth, mask, align="scale")
            absolute.append((aligned.aligned - truth).abs()[mask].double() / size)
            if view_pieces is not None:
                aligned = depth_error(estimate, truth, mask, align="scale", pieces=view_pieces)
                inside = mask & (view_pieces >= 0)
                by_piece.append((aligned.aligned - truth).abs()[inside].double() / size)
                in_pieces, piece_views_pixels = in_pieces + int(inside.sum()), piece_views_pixels + int(mask.sum())
        values = torch.cat(absolute)
        scores["integration_depth_error"] = float(values.mean())
        scores["integration_depth_error_median"] = float(values.median())
        if by_piece:
            scores["integration_depth_error_pieces"] = float(torch.cat(by_piece).mean())
            scores["integration_piece_coverage"] = in_pieces / piece_views_pixels
    return scores


def _normal_image(normals: Tensor, mask: Tensor) -> np.ndarray:
    """Normals as RGB ((n + 1) / 2 with y and z flipped: up is green, towards the viewer is blue)."""
    n = normals.detach().double().cpu() * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    image = torch.where(mask.cpu()[..., None], (n + 1) / 2, torch.ones_like(n))
    return (image.clamp(0, 1).numpy() * 255).astype(np.uint8)


def normal_map_picture(result: NormalMapResult, scene_name: str, method: str, run_dir: str | Path,
                       max_views: int = 3, max_error_deg: float = 20.0) -> str:
    """renders/<scene>__<method>.png: per view (up to `max_views`), ground truth | estimate | angular
    error (blue 0 .. red >= `max_error_deg`); returns the path relative to `run_dir`."""

    images, labels = [], []
    for i, (estimate, truth, mask) in enumerate(zip(result.normals, result.truth, result.mask)):
        if i >= max_views:
            break
        if truth is not None:
            images.append(_normal_image(truth, mask))
            labels.append(f"{scene_name} view {i}: true normals")
        images.append(_normal_image(estimate, mask & (estimate.norm(dim=-1) > 0)))
        labels.append(f"{method}")
        if truth is not None:
            error = angular_error(estimate, truth, mask)
            colors = colormap(error.errors_deg.double().numpy() / max_error_deg)
            image = np.where(mask.cpu().numpy()[..., None], colors, 1.0)
            images.append((np.clip(image, 0, 1) * 255).astype(np.uint8))
            labels.append(f"error (red >= {max_error_deg:g} deg)")
    path = Path("renders") / f"{row_stem(scene_name, method)}.png"
    (Path(run_dir) / path).parent.mkdir(parents=True, exist_ok=True)
    labelled_row(images, labels).save(Path(run_dir) / path)
    return str(path)


def nehab_tsdf(scene: Scene, *, position_weight: float = 0.1, max_depth_jump: float = 0.05,
               min_confidence: float = 0.0, voxel_fraction: float = 1 / 256, truncation_voxels: float = 4.0,
               margin_fraction: float = 0.05, device: str = "auto", weighting: str = "constant", seed: int = 0,
               run_dir=None, config=None) -> Mesh:
    """Each depth frame fused with its photometric normal map at the normal map's resolution (Nehab et
    al. 2005, `fuse_frames`, lambda = `position_weight`), then TSDF fusion of the fused frames with
    the settings of the `tsdf` method (box and voxel from the scene's back-projected input)."""

    if scene.frames is None or not scene.depth_input:
        raise NotApplicable(f"scene {scene.name!r} has no depth frames to fuse")
    if getattr(scene, "normal_maps", None) is None or getattr(scene, "photometric", None) is None:
        raise NotApplicable(f"scene {scene.name!r} has no photometric normal maps to fuse with its depth")
    normals = torch.stack([r.normals for r in scene.normal_maps])
    confidence = torch.stack([r.confidence * r.mask for r in scene.normal_maps])
    confidence = torch.where(confidence > min_confidence, confidence, 0.0)
    K = torch.stack([c.K for c in scene.photometric])
    fused = fuse_frames(scene.frames, normals, K, confidence, position_weight, max_depth_jump)
    return tsdf(replace(scene, frames=fused), voxel_fraction=voxel_fraction, truncation_voxels=truncation_voxels,
                margin_fraction=margin_fraction, device=device, weighting=weighting)


__all__ = ["NormalMapResult", "nehab_tsdf", "normal_map_picture", "photometric_normals",
           "score_normal_maps"]
