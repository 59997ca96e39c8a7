"""neuralsurf: neural implicit surfaces and classical baselines for 3D surface reconstruction."""

from neuralsurf import baselines, geometry, io, losses, metrics, models, observations, photometric, scenes
from neuralsurf.errors import (
    ConfigError,
    DeviceError,
    ExtractionError,
    FileFormatError,
    InputError,
    MissingDependencyError,
    NeuralsurfError,
)
from neuralsurf.extract import GridSamples, extract_mesh, sample_grid
from neuralsurf.structures import DepthFrames, Mesh, Normalization, PointCloud
from neuralsurf.training import FitResult, fit, load_field

__version__ = "0.1.0"
