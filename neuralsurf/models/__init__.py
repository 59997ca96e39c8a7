"""Neural fields: forward(x[..., 3], latent=None) -> value[...] in the unit frame."""

from neuralsurf.models.encodings import FourierFeatures, HashGrid
from neuralsurf.models.field import NormalizedField
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.models.latent import AutoDecoder, LatentCodes, LatentConditioned
from neuralsurf.models.occupancy import CBNDecoder, ConditionalBatchNorm, OccupancyNetwork, PointNetEncoder
from neuralsurf.models.refined import RefinedSDF
from neuralsurf.models.sdf_mlp import SDFMLP, Sine

__all__ = ["SDFMLP", "FourierFeatures", "HashGrid", "NormalizedField", "RefinedSDF", "Sine", "VoxelSDF"]
__all__ += ["AutoDecoder", "CBNDecoder", "ConditionalBatchNorm", "LatentCodes", "LatentConditioned", "OccupancyNetwork",
            "PointNetEncoder"]
