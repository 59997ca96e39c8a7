import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ["NEURALSURF_DATA"]).expanduser() if os.environ.get("NEURALSURF_DATA") else None
"""The folder of real captures, from NEURALSURF_DATA only; None when it is not set."""
os.environ.setdefault("NEURALSURF_PROGRESS", "0")  # no progress bars in test output (neuralsurf.progress)


@pytest.fixture(autouse=True)
def _few_threads():
    torch.set_num_threads(2)


@pytest.fixture
def shared_data() -> Path:
    """The folder of real captures ($NEURALSURF_DATA); skips when it is not set or not a folder."""
    if SHARED_DATA is None:
        pytest.skip("NEURALSURF_DATA is not set; point it at the folder of real captures to run this test")
    if not SHARED_DATA.is_dir():
        pytest.skip(f"NEURALSURF_DATA={str(SHARED_DATA)!r} is not a folder; point it at the real captures")
    return SHARED_DATA


# ----------------------------------------------------------------------------- analytic oracles

class AnalyticField(torch.nn.Module):
    """An analytic SDF (x[..., 3] -> sdf[...]) as a module, where the code under test takes a model."""

    def __init__(self, sdf) -> None:
        super().__init__()
        self.sdf = sdf

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.sdf(x)


@pytest.fixture(scope="session")
def sphere():
    """The tests' analytic sphere (`neuralsurf.scenes.Sphere`): centre 0, radius 0.3, inside the unit
    box; exact `sdf`, `mesh(subdivisions)` and `sample_surface(n, seed)`."""
    from neuralsurf.scenes import Sphere

    return Sphere(radius=0.3)


@pytest.fixture(scope="session")
def sphere_field(sphere) -> AnalyticField:
    """The sphere's exact SDF as a model (unit frame)."""
    return AnalyticField(sphere.sdf)


@pytest.fixture(scope="session")
def sphere_samples(sphere):
    """5,000 exact surface samples of the sphere with their outward normals (seed 1)."""
    return sphere.sample_surface(5000, seed=1)


@pytest.fixture
def analytic_field():
    """`analytic_field(sdf)`: any analytic SDF as a model (AnalyticField)."""
    return AnalyticField
