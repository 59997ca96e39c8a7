"""neuralsurf: neural implicit surfaces and classical baselines for 3D surface reconstruction."""

from neuralsurf import geometry, scenes
from neuralsurf.errors import (
    ConfigError,
    DeviceError,
    ExtractionError,
    FileFormatError,
    InputError,
    MissingDependencyError,
    NeuralsurfError,
)
from neuralsurf.structures import Mesh, Normalization, PointCloud

__version__ = "0.1.0"
