"""Scoring a learned prior: completions of held-out shapes from noisy clouds, and the means of
per-shape metrics (train.py's prior metrics; evaluate.py's scene-set rows)."""

from __future__ import annotations

import math

import numpy as np
from torch import nn

from neuralsurf.errors import NeuralsurfError
from neuralsurf.geometry import noisy_cloud
from neuralsurf.metrics import evaluate_mesh
from neuralsurf.priors.collection import TestShape
from neuralsurf.priors.completion import complete_cloud, extract_unit
from neuralsurf.structures import Mesh


def score_completions(prior: nn.Module, shapes: list[TestShape], *, n_points: int = 3000, noise: float = 0.005,
                      latent_steps: int = 200, resolution: int = 64, n_samples: int = 20_000, seed: int = 0,
                      device: str = "cpu") -> tuple[dict[str, float], list[dict], Mesh | None]:
    """Complete each shape from `n_points` noisy surface points and score its mesh (`evaluate_mesh`).
    Returns (means of the numeric metrics, with "shapes" and "failed" counts; per-shape metrics; the
    first shape's mesh). A shape without a surface counts with IoU 0 and F-scores 0."""
    per_shape, first = [], None
    for i, shape in enumerate(shapes):
        cloud = noisy_cloud(shape.surface, n_points, noise, seed + i)
        try:
            mesh = extract_unit(complete_cloud(prior, cloud, latent_steps=latent_steps, seed=seed, device=device),
                                resolution)
            metrics = {k: float(v) for k, v in evaluate_mesh(mesh, shape.mesh, n_samples=n_samples, seed=seed).items()}
            first = mesh if first is None else first
        except NeuralsurfError as error:
            metrics = {"iou": 0.0, "fscore_1%": 0.0, "fscore_0.5%": 0.0, "failed": str(error)[:200]}
        per_shape.append({"shape": shape.name, **metrics})
    return mean_metrics(per_shape), per_shape, first


def mean_metrics(per_shape: list[dict]) -> dict[str, float]:
    """Means of every numeric metric over the shapes that have it (NaN skipped), plus "shapes" and
    "failed" counts."""
    keys = {k for row in per_shape for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    means = {}
    for key in sorted(keys):
        values = [row[key] for row in per_shape if isinstance(row.get(key), (int, float)) and not math.isnan(row[key])]
        means[key] = float(np.mean(values)) if values else math.nan
    return {**means, "shapes": len(per_shape), "failed": sum("failed" in row for row in per_shape)}
