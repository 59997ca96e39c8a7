"""Coarse-to-fine extraction of an occupancy field at probability 0.2 (Occupancy Networks' MISE
threshold) gives the dense grid's mesh while evaluating a fraction of its points."""

import math

import numpy as np
import torch

from neuralsurf.extract import extract_mesh
from neuralsurf.geometry import knn
from neuralsurf.priors import Shape, ShapeRecord

THRESHOLD = 0.2
TEMPERATURE = 0.01
"""The occupancy logit changes by 1 per 0.01 of the unit frame: slope k = 100, as sharp as a trained
network's (its probability goes from 0.27 to 0.73 within 1 % of the shape's size)."""
RESOLUTION = 128
BOUNDS = np.array([[-0.55] * 3, [0.55] * 3])


class Counted:
    """An occupancy network's field from an analytic shape: p(x) = sigmoid(-sdf(x) / TEMPERATURE),
    field = logit(THRESHOLD) - logit(p) (negative where p > THRESHOLD); counts the points evaluated."""

    def __init__(self, shape: Shape):
        self.shape, self.points = shape, 0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        self.points += x.shape[:-1].numel()
        logit = -self.shape.sdf(x.double()) / TEMPERATURE
        return (math.log(THRESHOLD / (1 - THRESHOLD)) - logit).float()


def _distance(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest distance from a point of a (Float[n, 3]) to its nearest neighbour in b."""
    return float(knn(a.double(), b.double(), 1)[0].max())


def test_coarse_to_fine_matches_the_dense_grid_on_an_occupancy_field_with_a_quarter_of_the_points():
    shape = Shape.from_record(ShapeRecord("chair", "test", 0))  # thin legs and a back: parts a coarse grid misses
    dense_field, sparse_field = Counted(shape), Counted(shape)
    dense = extract_mesh(dense_field, RESOLUTION, BOUNDS, coarse_to_fine=False, progress=False)
    # refine every cell whose corners come within margin * diagonal of the level; the field's slope is
    # 1 / TEMPERATURE, so margin = slope / 2 makes the skipped cells provably free of the surface
    sparse = extract_mesh(sparse_field, RESOLUTION, BOUNDS, coarse_to_fine=True, margin=0.5 / TEMPERATURE,
                          coarse_resolution=16, progress=False)
    voxel = float((BOUNDS[1] - BOUNDS[0]).max()) / RESOLUTION
    fraction = sparse_field.points / dense_field.points
    print(f"coarse-to-fine evaluated {sparse_field.points} of {dense_field.points} grid points ({fraction:.1%})")
    assert fraction < 0.25
    assert dense.is_watertight and sparse.is_watertight
    assert len(sparse.faces) == len(dense.faces)
    assert _distance(sparse.vertices, dense.vertices) <= voxel and _distance(dense.vertices, sparse.vertices) <= voxel
    # the surface is the 0.2 level: |sdf| there is TEMPERATURE * logit(0.8) outside the shape
    offset = TEMPERATURE * math.log(0.8 / 0.2)
    assert torch.allclose(shape.sdf(sparse.vertices.double()), torch.full((len(sparse.vertices),), offset,
                                                                          dtype=torch.float64), atol=voxel)
