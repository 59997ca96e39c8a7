"""Every config composes and instantiates; every experiment runs a few steps; bad names fail clearly."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from hydra.utils import instantiate
from omegaconf import OmegaConf

from neuralsurf.losses import LossWeights
from neuralsurf.scenes import Scene

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))
MODELS = sorted(p.stem for p in (CONFIGS / "model").glob("*.yaml"))

# tiny settings for smoke runs: a few steps, small pools, coarse extraction
TINY = [
    "trainer.steps=3", "trainer.batch_size=64", "trainer.log_every=1", "trainer.image_every=3",
    "trainer.progress=false", "trainer.sampling.n_near=2000", "trainer.sampling.n_free=500",
    "extract.resolution=32", "data.n_points=3000", "device=cpu",
]


def compose_train(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


@pytest.mark.parametrize("model", MODELS)
def test_every_model_config_instantiates_and_runs(model):
    cfg = compose_train([f"model={model}"])
    net = instantiate(cfg.model, _convert_="all")
    assert net(torch.zeros(4, 3)).shape == (4,)


def test_data_and_loss_configs_instantiate():
    cfg = compose_train(["data=sphere", "data.n_points=500"])
    scene = instantiate(cfg.data)
    assert isinstance(scene, Scene) and len(scene.cloud) == 500 and scene.ground_truth is not None
    assert isinstance(instantiate(cfg.loss), LossWeights)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_runs_a_few_steps(experiment, tmp_path):
    pytest.importorskip("pymeshlab", reason="the bunny experiments need neuralsurf[data]")
    from neuralsurf.cli import train

    cfg = compose_train([f"experiment={experiment}", *TINY])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path)
    metrics = train(cfg)
    assert (tmp_path / "mesh.ply").is_file() and (tmp_path / "metrics.json").is_file()
    assert (tmp_path / "checkpoints" / "last.pt").is_file()
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    assert metrics["steps"] == 3 and metrics["chamfer_l1"] > 0


def test_unknown_experiment_is_a_clear_error():
    with pytest.raises(HydraException, match="Could not find 'experiment/no_such_thing'"):
        compose_train(["experiment=no_such_thing"])
