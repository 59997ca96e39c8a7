"""neuralsurf: neural implicit surfaces and classical baselines for 3D surface reconstruction."""

from neuralsurf import (
    baselines,
    cameras,
    geometry,
    io,
    losses,
    metrics,
    models,
    observations,
    photometric,
    scenes,
)
from neuralsurf.checkpoints import load_field
from neuralsurf.errors import (
    CheckpointError,
    ConfigError,
    DeviceError,
    DownloadError,
    ExtractionError,
    FileFormatError,
    InputError,
    MissingDependencyError,
    NeuralsurfError,
)
from neuralsurf.extract import GridSamples, extract_mesh, sample_grid
from neuralsurf.structures import DepthFrames, Mesh, Normalization, PointCloud
from neuralsurf.training import FitResult, fit

__version__ = "0.3.0"  # the one version source: pyproject.toml reads it

__all__ = [
    # subpackages of the public API
    "baselines", "cameras", "geometry", "io", "losses", "metrics", "models", "observations", "photometric", "scenes",
    # structures
    "DepthFrames", "Mesh", "Normalization", "PointCloud",
    # fitting and extraction
    "FitResult", "fit", "load_field", "GridSamples", "extract_mesh", "sample_grid",
    # errors
    "NeuralsurfError", "CheckpointError", "ConfigError", "DeviceError", "DownloadError", "ExtractionError", "FileFormatError", "InputError",
    "MissingDependencyError",
    "__version__",
]
