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
