import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NEURALSURF_DATA", REPO.parent / "shared" / "data"))
os.environ.setdefault("NEURALSURF_PROGRESS", "0")  # no progress bars in test output (neuralsurf.progress)


@pytest.fixture(autouse=True)
def _few_threads():
    torch.set_num_threads(2)


@pytest.fixture
def shared_data() -> Path:
    """The folder of real captures (NEURALSURF_DATA or ../shared/data); skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real captures not found at {SHARED_DATA}; set NEURALSURF_DATA to run this test")
    return SHARED_DATA
