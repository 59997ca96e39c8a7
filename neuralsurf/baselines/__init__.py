"""Classical baselines: same inputs (neuralsurf.structures), same Mesh out, same metrics."""

from neuralsurf.baselines.poisson import reconstruct_poisson
from neuralsurf.baselines.registration import (
    Registration,
    evaluate_registration,
    register_global,
    register_icp,
    register_meshes,
    register_multiway,
)
from neuralsurf.baselines.tsdf import FusionSettings, TSDFVolume, depth_bounds

__all__ = [
    "FusionSettings",
    "Registration",
    "TSDFVolume",
    "depth_bounds",
    "evaluate_registration",
    "reconstruct_poisson",
    "register_global",
    "register_icp",
    "register_meshes",
    "register_multiway",
]
