"""Supervision for fits: each kind of observation samples its own batches and returns its loss terms."""

from neuralsurf.observations.base import NotObserved, Observation, Sampler, union_bounds
from neuralsurf.observations.normals import NormalBatch, NormalMaps
from neuralsurf.observations.points import PointSamples
from neuralsurf.observations.rays import DepthRays, RayBatch

__all__ = ["DepthRays", "NormalBatch", "NormalMaps", "NotObserved", "Observation", "PointSamples", "RayBatch", "Sampler", "union_bounds"]
