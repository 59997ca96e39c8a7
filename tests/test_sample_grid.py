"""ns.sample_grid: a field on a regular grid, returned and written as .npz (analytic sphere oracle)."""

import numpy as np
import pytest
import torch

import neuralsurf as ns
from neuralsurf.errors import ConfigError, FileFormatError, InputError

CENTER = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
RADIUS = 0.4
BOX = [[-0.2, -0.7, -0.3], [0.8, 0.3, 0.4]]  # 1.0 x 1.0 x 0.7


def sphere(x: torch.Tensor) -> torch.Tensor:
    return (x.double() - CENTER).norm(dim=-1).float() - RADIUS


def test_values_are_the_sphere_sdf_at_the_grid_points(tmp_path):
    samples = ns.sample_grid(sphere, 20, bounds=BOX, path=tmp_path / "grid.npz")
    assert samples.values.shape == (21, 21, 15) and samples.values.dtype == torch.float32
    assert samples.spacing == pytest.approx(0.05)
    lo, hi = samples.bounds
    assert torch.all(lo <= torch.tensor(BOX[0], dtype=torch.float64) + 1e-12)  # covers the box ...
    assert torch.all(hi >= torch.tensor(BOX[1], dtype=torch.float64) - 1e-12)
    assert torch.all(hi - lo < torch.tensor(BOX[1]) - torch.tensor(BOX[0]) + samples.spacing)  # ... by < 1 cell
    exact = (samples.points() - CENTER).norm(dim=-1) - RADIUS
    assert torch.allclose(samples.values.double(), exact, atol=1e-6)
    assert float(samples.values.min()) == pytest.approx(-RADIUS, abs=samples.spacing)  # the centre is sampled
    with np.load(tmp_path / "grid.npz", allow_pickle=False) as data:
        assert sorted(data.files) == ["bounds", "spacing", "values"]
        assert np.array_equal(data["values"], samples.values.numpy())
        assert np.array_equal(data["bounds"], samples.bounds.numpy()) and float(data["spacing"]) == samples.spacing
    assert [p.name for p in tmp_path.iterdir()] == ["grid.npz"]


def test_bounds_default_to_the_fields_and_chunks_do_not_change_values():
    class Field(torch.nn.Module):
        bounds = torch.tensor(BOX)

        def forward(self, x):
            return sphere(x)

    whole = ns.sample_grid(Field(), 16)
    chunked = ns.sample_grid(Field(), 16, chunk_size=7, progress=False)
    assert torch.equal(whole.values, chunked.values) and torch.equal(whole.bounds, chunked.bounds)


def test_bad_arguments_are_explained(tmp_path):
    with pytest.raises(InputError, match="no extraction box"):
        ns.sample_grid(sphere, 8)
    with pytest.raises(ConfigError, match="resolution must be an integer >= 2"):
        ns.sample_grid(sphere, 1, bounds=BOX)
    with pytest.raises(InputError, match="one value per point"):
        ns.sample_grid(lambda x: x, 8, bounds=BOX)
    (tmp_path / "a_file").write_text("")
    with pytest.raises(FileFormatError, match="cannot write"):
        ns.sample_grid(sphere, 8, bounds=BOX, path=tmp_path / "a_file" / "grid.npz")
