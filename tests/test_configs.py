"""Every config composes and instantiates; every experiment runs a few steps; every experiment names its
observation and its data feeds it, each data config's feeds build; a mismatch or an unselected observation's
options are clear errors, as are bad names."""

import functools
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

from neuralsurf.cli import (
    build_observations,
    check_feeds,
    experiment_settings,
    observation_configs,
    without_feeds,
)
from neuralsurf.errors import ConfigError
from neuralsurf.geometry import cloud_from_mesh
from neuralsurf.io import write_point_cloud
from neuralsurf.models import OccupancyNetwork
from neuralsurf.observations import Observation
from neuralsurf.rooms import RoomSettings
from neuralsurf.scenes import Scene, Sphere, data_root

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))
MODELS = sorted(p.stem for p in (CONFIGS / "model").glob("*.yaml"))
DATA = sorted(p.stem for p in (CONFIGS / "data").glob("*.yaml"))
OBSERVATIONS = sorted(p.stem for p in (CONFIGS / "observation").glob("*.yaml"))

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
    scene = instantiate(without_feeds(cfg).data)
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
    if cfg.data._target_.endswith("rgbd_scene"):  # an RGB-D folder: a few frames of a wall
        cfg.data.update(path=str(write_7scenes_plane(tmp_path / "capture")), hold_out_every=0)
    metrics = train(cfg)
    assert (tmp_path / "mesh.ply").is_file() and (tmp_path / "metrics.json").is_file()
    if isinstance(instantiate(cfg.model), RoomSettings):  # a room's voxel fit: one solve, no training loop
        assert metrics["steps"] == 0 and metrics["fit_seconds"] > 0
        return
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
# observations: each experiment names its own, each data config says what it feeds


def compose_with_choices(overrides: list[str]):
    """(train.py's config, its group choices) for these overrides."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides, return_hydra_config=True)
    return cfg, dict(cfg.hydra.runtime.choices)


def option_entries(option: str) -> set[str]:
    """The cfg.observation entries that observation=<option> defines: the keys of its file."""
    return set(OmegaConf.load(CONFIGS / "observation" / f"{option}.yaml"))


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_names_its_observation_and_its_data_feeds_it(experiment):
    """Each experiment selects its observation in its defaults (or those of the experiment it extends); it sets
    options of that observation only; its data lists that observation in `feeds`."""
    named = experiment_settings(experiment)["observations"]
    assert named and set(named) <= set(OBSERVATIONS), f"experiment={experiment} names no observation: {named}"
    cfg, choices = compose_with_choices([f"experiment={experiment}"])
    check_feeds(cfg, choices)  # no ConfigError
    selected = observation_configs(cfg)
    assert set(selected) == set(cfg.observation) == set().union(*map(option_entries, named))
    assert all(isinstance(instantiate(entry, _convert_="all"), functools.partial) for entry in selected.values())
    assert set(experiment_settings(experiment)["tunes"]) <= set(selected)


@pytest.mark.parametrize("data", DATA)
def test_every_data_config_feeds_observations_that_exist(data):
    required = {"file": ["data.path=x"], "rgbd": ["data.path=x"], "shape_folder": ["data.source=x"]}.get(data, [])
    cfg, _ = compose_with_choices(["~experiment", f"data={data}", *required])
    assert cfg.data.feeds and set(cfg.data.feeds) <= set(OBSERVATIONS), cfg.data.feeds
    for option in cfg.data.feeds:
        fed, choices = compose_with_choices(["~experiment", f"data={data}", f"observation={option}", *required])
        check_feeds(fed, choices)
        assert set(observation_configs(fed)) == option_entries(option)
    assert "feeds" not in without_feeds(cfg).data and "feeds" in cfg.data  # a copy without it


def test_each_fed_observation_builds_from_its_data(tmp_path):
    """The pairs that `feeds` declares work: a small scene of each data config builds each observation it feeds
    (those that need no fetched data or optional package; the collections are trained in the experiment runs)."""
    cloud = tmp_path / "cloud.ply"
    write_point_cloud(cloud, cloud_from_mesh(Sphere(radius=0.3).mesh(), n=2000, noise=0.0, seed=0))
    cases = {"sphere": ["data.n_points=2000"], "file": [f"data.path={cloud}"],
             "rgbd": [f"data.path={write_7scenes_plane(tmp_path / 'capture')}", "data.hold_out_every=0",
                      "data.colors=false"]}
    for data, overrides in cases.items():
        cfg, _ = compose_with_choices(["~experiment", f"data={data}", *overrides])
        scene = instantiate(without_feeds(cfg).data)
        for option in cfg.data.feeds:
            fed, _ = compose_with_choices(["~experiment", f"data={data}", f"observation={option}", *overrides])
            observations = build_observations(fed, scene)
            assert observations and all(isinstance(o, Observation) for o in observations), (data, option)


def test_an_observation_the_data_does_not_feed_is_a_config_error_naming_the_fix():
    """`train.py data=rgbd data.path=<folder>` with the default experiment, which fits points: nothing is fitted
    quietly; the error names the experiment, the observation, the data, what it feeds and the fix."""
    cfg, choices = compose_with_choices(["data=rgbd", "data.path=x"])
    with pytest.raises(ConfigError) as error:
        check_feeds(cfg, choices)
    message = str(error.value)
    assert message.startswith("observation=points (experiment=bunny_sdf) does not fit data=rgbd, which feeds "
                              "depth_rays (data.feeds), not points.")
    assert "experiment=room (or bunny_depth, redkitchen_depth)" in message
    assert "observation=depth_rays '~observation.points'" in message
    fixed, choices = compose_with_choices(["experiment=room", "data.path=x"])
    check_feeds(fixed, choices)
    fixed, choices = compose_with_choices(["data=rgbd", "data.path=x", "observation=depth_rays", "~observation.points"])
    check_feeds(fixed, choices)
    assert set(observation_configs(fixed)) == {"rays"}
    with pytest.raises(ConfigError, match=r"observation=depth_rays,normal_maps \(experiment=bunny_depth_normals\) "
                                          r"does not fit data=bunny_depth, which feeds depth_rays \(data.feeds\), "
                                          r"not normal_maps"):
        check_feeds(*compose_with_choices(["experiment=bunny_depth_normals", "data=bunny_depth"]))


def test_the_move_onto_the_points_follows_the_points_observation():
    """train.py's point fit moves its mesh onto the points by the fit's held-out share; with the points observation
    dropped (as the feeds error suggests) the config still resolves, without the move; evaluate.py's likewise."""
    cfg, _ = compose_with_choices([])
    assert cfg.extract.onto_points == cfg.observation.points.held_out == 0.05
    cfg, _ = compose_with_choices(["data=rig_fusion", "observation=[depth_rays,normal_maps]", "~observation.points"])
    assert OmegaConf.to_container(cfg.extract, resolve=True)["onto_points"] is None
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        suite = compose(config_name="evaluate", overrides=["methods=[neural_sdf_fast]",
                                                           "~method.neural_sdf_fast.observations.points"])
    assert OmegaConf.to_container(suite.method.neural_sdf_fast.extract, resolve=True)["onto_points"] is None


def test_evaluate_s_neural_sdf_fast_fits_as_train_py_s_default():
    """One setting: evaluate.py's neural_sdf_fast is train.py's default point fit (experiment=bunny_sdf) in all that
    decides the result (a suite may cap its steps); only the progress bar and the images differ."""
    train, _ = compose_with_choices(["data=file", "data.path=x"])
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        method = compose(config_name="evaluate", overrides=["~suite", "scenes=[sphere]",
                                                                      "methods=[poisson]"]).method.neural_sdf_fast
    for group in ("model", "optimizer"):
        assert train[group] == method[group], group
    assert train.observation.points == method.observations.points
    assert OmegaConf.to_container(train.extract, resolve=True) == OmegaConf.to_container(method.extract, resolve=True)
    differ = {key for key in train.trainer if train.trainer[key] != method.trainer[key]}
    assert differ == {"progress", "image_every"}, differ


def test_options_of_an_observation_that_is_not_selected_are_a_config_error():
    """observation= on the command line replaces the experiment's; the experiment's options of the one replaced are
    not dropped quietly."""
    cfg, choices = compose_with_choices(["data=rgbd", "data.path=x", "observation=depth_rays"])
    with pytest.raises(ConfigError, match=r"observation.points \(batch_size, near_gradient, n_near, n_free, held_out\) "
                                          r"sets "
                                          r"options of observation=points, which is not selected \(observation="
                                          r"depth_rays is\): drop them with '~observation.points' or choose an "
                                          r"experiment that selects depth_rays: experiment=bunny_depth"):
        check_feeds(cfg, choices)
    with pytest.raises(ConfigError, match="no observation is selected"):
        observation_configs(compose_with_choices(["~observation.points"])[0])


def test_a_data_config_that_does_not_say_what_it_feeds_is_a_config_error():
    cfg, choices = compose_with_choices(["data=sphere", "~data.feeds"])
    with pytest.raises(ConfigError, match="data=sphere does not say which observations it feeds"):
        check_feeds(cfg, choices)


def test_feeds_stay_out_of_what_evaluate_instantiates():
    """evaluate.py's priors scenes and methods nest the collection data configs: their feeds are a declaration,
    not an argument of the collection (nor part of a row's settings)."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=priors_folder", "folder.source=x"])
    assert cfg.folder.feeds and cfg.scene.shapes_cloud.collection.feeds
    stripped = without_feeds(cfg)
    assert "feeds" not in OmegaConf.to_yaml(stripped, resolve=True)
    assert instantiate(stripped.method.deepsdf.collection).source == "x"


@pytest.mark.subprocess
def test_train_py_refuses_an_observation_the_data_does_not_feed_before_building_anything(tmp_path):
    folder = write_7scenes_plane(tmp_path / "capture")
    command = [sys.executable, "train.py", "data=rgbd", f"data.path={folder}", f"hydra.run.dir={tmp_path / 'run'}",
               "device=cpu"]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300, check=False)
    output = done.stdout + done.stderr
    assert done.returncode == 1, output[-3000:]
    assert "ConfigError: observation=points (experiment=bunny_sdf) does not fit data=rgbd" in output
    assert "Traceback" not in output and "scene " not in output  # nothing was built
    assert not list((tmp_path / "run").glob("mesh.*")) and not (tmp_path / "run" / "checkpoints").exists()


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
