"""Checkpoints: a saved field loads back without Hydra, and nothing read from a file can choose code to run."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from neuralsurf.checkpoints import load_field, save_checkpoint
from neuralsurf.errors import CheckpointError, ConfigError
from neuralsurf.models import SDFMLP, HashGrid
from neuralsurf.models.spec import build_model, model_spec
from neuralsurf.observations import PointSamples
from neuralsurf.scenes import Sphere
from neuralsurf.training import fit

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY = {"steps": 5, "device": "cpu", "progress": False, "image_every": 0}


def tiny_fit(**options):
    torch.manual_seed(0)
    model = SDFMLP(width=16, depth=2, skip_layers=(), weight_norm=False,
                   encoding=HashGrid(levels=3, log2_table_size=10, max_resolution=32))
    cloud = Sphere(center=(1.0, 0.0, 0.0), radius=2.0).sample_surface(1000, seed=0)
    return fit(model, PointSamples(cloud, batch_size=128, n_near=2000, n_free=500), **TINY, **options)


def test_a_saved_field_loads_back_with_the_same_values(tmp_path):
    result = tiny_fit(run_dir=tmp_path / "run")
    query = torch.randn(100, 3)
    expected = result.field(query).detach()
    result.save(tmp_path / "field.pt")
    for path in (tmp_path / "field.pt", tmp_path / "run" / "checkpoints" / "last.pt"):
        field = load_field(path)
        assert torch.equal(field(query).detach(), expected)
        assert torch.allclose(field.bounds, result.field.bounds)


CRAFTED_CONFIG = {
    "model": {"_target_": "builtins.open", "file": "{out}", "mode": "w"},
    "trainer": {"sampling": {"box": {"_target_": "os.makedirs", "name": "{out}_dir"}}},
}
CRAFTED_SPECS = [
    {"class": "builtins.open", "arguments": {"file": "{out}", "mode": "w"}},
    {"class": "SDFMLP", "arguments": {"encoding": {"_target_": "numpy.save", "file": "{out}", "arr": [1]}}},
    {"class": "SDFMLP", "arguments": {"encoding": {"class": "os.makedirs", "arguments": {"name": "{out}"}}}},
    {"class": "SDFMLP", "arguments": {"__init__": 1}},
]


def crafted(tmp_path: Path, spec) -> tuple[Path, Path]:
    """A checkpoint whose stored config and model spec name functions that would create `out`."""
    out = tmp_path / "pwned"
    fill = lambda value: {k: fill(v) for k, v in value.items()} if isinstance(value, dict) else (
        value.format(out=out) if isinstance(value, str) else value)
    state = tiny_fit().model.state_dict()
    path = tmp_path / "last.pt"
    save_checkpoint(path, {"model": state, "model_spec": fill(spec) if spec else None, "config": fill(CRAFTED_CONFIG),
                           "normalization": {"center": torch.zeros(3, dtype=torch.float64),
                                             "scale": torch.tensor(1.0, dtype=torch.float64)}, "margin": 0.05})
    return path, out


@pytest.mark.parametrize("spec", [None, *CRAFTED_SPECS])
def test_a_crafted_checkpoint_runs_nothing_and_is_a_clear_error(tmp_path, spec):
    path, _ = crafted(tmp_path, spec)
    with pytest.raises(CheckpointError):
        load_field(path)
    assert not list(tmp_path.glob("pwned*"))


def test_a_crafted_checkpoint_through_evaluate_creates_no_file(tmp_path):
    from neuralsurf.cli import evaluate

    path, _ = crafted(tmp_path, CRAFTED_SPECS[0])
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("evaluate", overrides=["suite=tiny", "methods=[neural_sdf]", f"method.neural_sdf.checkpoint={path}",
                                             "render=false"])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path / "eval")
    rows = evaluate(cfg)
    assert rows[0]["status"] == "failed" and "CheckpointError" in rows[0]["reason"]
    assert not list(tmp_path.glob("pwned*"))


def test_model_specs_are_plain_data_and_rebuild_the_same_model():
    model = SDFMLP(width=16, depth=3, skip_layers=(1,), encoding=HashGrid(levels=2, log2_table_size=8))
    spec = model_spec(model)
    assert spec["class"] == "SDFMLP" and spec["arguments"]["encoding"]["class"] == "HashGrid"
    rebuilt = build_model(spec)
    rebuilt.load_state_dict(model.state_dict())
    x = torch.randn(10, 3)
    assert torch.equal(rebuilt(x), model(x))
    with pytest.raises(CheckpointError, match="not a neuralsurf model"):
        build_model({"class": "Module", "arguments": {}})


def compose_train(overrides):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=sphere_sdf", "data.n_points=500", "trainer.steps=2",
                                          "trainer.progress=false", "trainer.image_every=0", "extract.resolution=16",
                                          "observation.points.batch_size=64", "observation.points.n_near=1000",
                                          "observation.points.n_free=200", "device=cpu", *overrides])
    OmegaConf.set_struct(cfg, False)
    return cfg


@pytest.mark.slow
def test_resuming_a_run_made_with_other_settings_names_the_keys(tmp_path):
    from neuralsurf.cli import train

    cfg = compose_train([])
    cfg.run_dir = str(tmp_path)
    train(cfg)
    mesh = (tmp_path / "mesh.ply").read_bytes()
    other = compose_train(["data.n_points=600", "observation.points.batch_size=32"])
    other.run_dir = str(tmp_path)
    with pytest.raises(ConfigError, match=r"data\.n_points, observation\.points\.batch_size.*resume=false"):
        train(other)
    assert (tmp_path / "mesh.ply").read_bytes() == mesh  # the old run's outputs are untouched
    same = compose_train(["trainer.log_every=1"])  # bookkeeping only: resumes
    same.run_dir = str(tmp_path)
    with pytest.warns(UserWarning, match="nothing to train"):
        assert train(same)["steps"] == 2


@pytest.mark.parametrize("steps", ["abc", 1.5, 0])
def test_a_bad_step_count_is_a_clear_error(tmp_path, steps):
    from neuralsurf.cli import train

    cfg = compose_train([f"trainer.steps={steps}"])
    cfg.run_dir = str(tmp_path)
    with pytest.raises(ConfigError, match="integer steps"):
        train(cfg)
