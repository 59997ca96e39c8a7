"""Every config composes and instantiates; every experiment runs a few steps; every data config, experiment
and observation combine into observations that instantiate; bad names fail clearly."""

import functools
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from hydra.utils import instantiate
from omegaconf import OmegaConf
from PIL import Image

from neuralsurf.cli import build_observations, observation_configs
from neuralsurf.errors import ConfigError
from neuralsurf.models import OccupancyNetwork
from neuralsurf.observations import DepthRays, Observation
from neuralsurf.rooms import RoomSettings
from neuralsurf.scenes import Scene, data_root

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))
MODELS = sorted(p.stem for p in (CONFIGS / "model").glob("*.yaml"))
DATA = sorted(p.stem for p in (CONFIGS / "data").glob("*.yaml"))
OBSERVATIONS = sorted(p.stem for p in (CONFIGS / "observation").glob("*.yaml"))
OBSERVATION_CHOICES = [*OBSERVATIONS, "[depth_rays,normal_maps]"]  # each option, and the fusion pair

# tiny settings for smoke runs: a few steps, small pools and inputs, coarse extraction
TINY = ["trainer.steps=3", "trainer.log_every=1", "trainer.image_every=3", "trainer.progress=false",
        "extract.resolution=32", "device=cpu"]
TINY_OBSERVATIONS = {"points": {"batch_size": 64, "n_near": 2000, "n_free": 500}, "rays": {"n_rays": 64},
                      "normals": {"n_pixels": 64}, "shapes": {"shapes_per_batch": 2, "samples_per_shape": 64},
                      "occupancy": {"shapes_per_batch": 2, "query_points": 64, "cloud_points": 50}}
TINY_DATA = {"n_points": 3000, "n_views": 4, "width": 64, "height": 48, "max_frames": 20,
             "classes": ["lamp"], "n_train": 2, "n_test": 1, "n_sdf": 2000, "n_occ": 1000, "n_surface": 3000,
             "mesh_resolution": 32, "workers": 0}
TINY_SCORE = {"shapes": 1, "n_points": 500, "latent_steps": 3}  # learned priors: completion of one test shape


def tiny(cfg):
    """`cfg` with the tiny observation and data settings of the keys it has."""
    OmegaConf.set_struct(cfg, False)
    for name, observation in cfg.observation.items():
        observation.update(TINY_OBSERVATIONS[name])
    cfg.data.update({k: v for k, v in TINY_DATA.items() if k in cfg.data})
    if "score" in cfg:
        cfg.score.update(TINY_SCORE)
    return cfg


def compose_train(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


@pytest.mark.parametrize("model", MODELS)
def test_every_model_config_instantiates_and_runs(model):
    cfg = compose_train([f"model={model}"])
    net = instantiate(cfg.model, _convert_="all")
    if isinstance(net, RoomSettings):  # a room's voxel fit: settings of a solve (tests/test_rooms.py)
        assert net == RoomSettings()
        return
    if not isinstance(net, torch.nn.Module):  # a learned prior's builder: sized by its collection
        net = net(n_shapes=2)
    latent = torch.zeros(net.latent_dim) if isinstance(net, OccupancyNetwork) else None
    assert net(torch.zeros(4, 3), latent).shape == (4,)


def test_data_observation_and_optimizer_configs_instantiate():
    cfg = compose_train(["data=sphere", "data.n_points=500"])
    scene = instantiate(cfg.data)
    assert isinstance(scene, Scene) and len(scene.cloud) == 500 and scene.ground_truth is not None
    observation = instantiate(cfg.observation.points)(scene)
    assert isinstance(observation, Observation) and observation.weights["surface"] == 3.0
    optimizer = instantiate(cfg.optimizer)([{"params": [torch.nn.Parameter(torch.zeros(2))]}])
    assert isinstance(optimizer, torch.optim.Adam) and optimizer.defaults["eps"] == 1e-15


@pytest.mark.parametrize("experiment", EXPERIMENTS)
@pytest.mark.slow
def test_every_experiment_runs_a_few_steps(experiment, tmp_path):
    from neuralsurf.cli import train

    cfg = tiny(compose_train([f"experiment={experiment}", *TINY]))
    if "bunny" in cfg.data._target_:
        pytest.importorskip("pymeshlab", reason="the bunny experiments need neuralsurf[data]")
    if "redkitchen" in cfg.data._target_ and not (data_root() / "7scenes_redkitchen_every10").is_dir():
        pytest.skip("the redkitchen frames are not here (set NEURALSURF_DATA)")
    cfg.run_dir = str(tmp_path)
    if "n_train" in cfg.data:  # a shape collection: built for the test, not in the user's cache
        cfg.data.root = str(tmp_path / "shapes")
    metrics = train(cfg)
    assert (tmp_path / "mesh.ply").is_file() and (tmp_path / "metrics.json").is_file()
    assert (tmp_path / "checkpoints" / "last.pt").is_file()
    assert list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))
    assert metrics["steps"] == 3
    if "shapes" in metrics:  # learned priors: means over the completed test shapes (IoU 0 where no surface)
        assert metrics["shapes"] == 1 and 0 <= metrics["iou"] <= 1
    else:
        assert metrics["chamfer_l1"] > 0 if "chamfer_l1" in metrics else 0 <= metrics["depth_completeness"] <= 1


def test_unknown_experiment_is_a_clear_error():
    with pytest.raises(HydraException, match="Could not find 'experiment/no_such_thing'"):
        compose_train(["experiment=no_such_thing"])


# ---------------------------------------------------------------------------------------------
# observations: data x experiment x observation


def observation_entries(choice: str) -> set[str]:
    """The cfg.observation entries that observation=<choice> defines: the keys of its file(s)."""
    return {key for option in choice.strip("[]").split(",") for key in OmegaConf.load(CONFIGS / "observation" /
                                                                                        f"{option}.yaml")}


def combination_problems(data: str, experiment: str, observation: str | None, tuned: set[str]) -> list[str]:
    """What is wrong with the observations of one combination (empty: none). `tuned`: the observation entries
    the experiment's own composition holds (the only ones a group switch may leave unused)."""
    overrides = [f"data={data}", f"experiment={experiment}"] + ([f"observation={observation}"] if observation else [])
    cfg = compose(config_name="train", overrides=overrides, return_hydra_config=True)
    where = " ".join(overrides)
    selected = observation_configs(cfg, overrides, dict(cfg.hydra.runtime.choices))
    problems = [f"{where}: observation.{name} has no _target_" for name, c in selected.items() if "_target_" not in c]
    problems += [f"{where}: observation.{name} does not instantiate as a partial"
                 for name, c in selected.items() if not isinstance(instantiate(c, _convert_="all"), functools.partial)]
    if observation is not None and set(selected) != observation_entries(observation):
        problems.append(f"{where}: builds {sorted(selected)}, not observation={observation}'s entries")
    problems += [f"{where}: observation.{name} is left over but not the experiment's tuning"
                 for name in set(cfg.observation) - set(selected) - tuned]
    return problems


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_data_and_observation_with_an_experiment_builds_selected_observations_only(experiment):
    """The experiment with every data config (the observation they select), and with every observation option
    given on the command line: the observations built are the selected ones, each with a _target_ and
    instantiating as a partial; what the experiment tunes for a group that is no longer selected is left over,
    nothing else. A command-line observation= overrides a data config's switch, so with one only the data
    configs that mention observations (and the default, bunny) can change the outcome."""
    touching = [d for d in DATA if d == "bunny" or "observation" in (CONFIGS / "data" / f"{d}.yaml").read_text()]
    problems, combinations = [], 0
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        tuned = set(compose(config_name="train", overrides=[f"experiment={experiment}"]).observation)
        for data in DATA:
            for observation in [None, *OBSERVATION_CHOICES] if data in touching else [None]:
                problems += combination_problems(data, experiment, observation, tuned)
                combinations += 1
    assert combinations == len(DATA) + len(touching) * len(OBSERVATION_CHOICES) and not problems, problems
    assert {"bunny_depth", "redkitchen", "rgbd"} <= set(touching)  # the depth data configs switch to depth_rays


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_uses_all_of_its_observation_settings(experiment):
    cfg = compose_train([f"experiment={experiment}"])
    assert all("_target_" in entry for entry in cfg.observation.values()), OmegaConf.to_yaml(cfg.observation)
    assert set(observation_configs(cfg, [], {})) == set(cfg.observation)


def test_a_depth_data_config_leaves_the_experiments_point_settings_unused_and_says_so(tmp_path, caplog):
    """`train.py data=rgbd data.path=<folder> model=sdf_hashgrid` (default experiment bunny_sdf, tuned for points)."""
    cfg = compose_train(["data=rgbd", f"data.path={write_7scenes_plane(tmp_path)}", "data.hold_out_every=0",
                         "model=sdf_hashgrid"])
    assert set(cfg.observation) == {"rays", "points"} and "_target_" not in cfg.observation.points
    with caplog.at_level(logging.INFO, logger="neuralsurf"):
        observations = build_observations(cfg, instantiate(cfg.data))
    assert len(observations) == 1 and isinstance(observations[0], DepthRays)
    assert "observation.points (batch_size, near_gradient, n_near, n_free) left unused" in caplog.text


def test_an_override_of_an_observation_that_is_not_selected_is_a_config_error():
    overrides = ["data=rgbd", "data.path=x", "observation.points.batch_size=10"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides, return_hydra_config=True)
    with pytest.raises(ConfigError, match=r"observation.points.batch_size=10 sets options of observation 'points', "
                                          r"which is not selected: the selected observation is 'rays' "
                                          r"\(observation=depth_rays, data=rgbd\)"):
        observation_configs(cfg, overrides, dict(cfg.hydra.runtime.choices))
    assert set(observation_configs(cfg, overrides[:2], dict(cfg.hydra.runtime.choices))) == {"rays"}


@pytest.mark.subprocess
def test_train_py_reports_an_override_of_an_unselected_observation_in_one_line(tmp_path):
    folder = write_7scenes_plane(tmp_path / "capture")
    command = [sys.executable, "train.py", "data=rgbd", f"data.path={folder}", "data.hold_out_every=0",
               "model=sdf_hashgrid", "observation.points.batch_size=10", f"hydra.run.dir={tmp_path / 'run'}", "device=cpu"]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    output = done.stdout + done.stderr
    assert done.returncode == 1, output[-3000:]
    assert "ConfigError: observation.points.batch_size=10 sets options of observation 'points'" in output
    assert "TypeError" not in output and "Traceback" not in output


def write_7scenes_plane(root: Path, n: int = 2) -> Path:
    """n 64x48 depth frames (16-bit millimetres) of a wall 1.5 m in front of cameras 10 cm apart, in the
    7-Scenes layout (camera-intrinsics.txt + frames/frame-XXXXXX.{depth.png,color.png,pose.txt}); returns root."""
    (root / "frames").mkdir(parents=True)
    np.savetxt(root / "camera-intrinsics.txt", [[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    for i in range(n):
        stem = root / "frames" / f"frame-{i:06d}"
        Image.fromarray(np.full((48, 64), 1500, dtype=np.uint16)).save(f"{stem}.depth.png")
        Image.fromarray(np.zeros((48, 64, 3), dtype=np.uint8)).save(f"{stem}.color.png")
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        np.savetxt(f"{stem}.pose.txt", pose)
    return root
