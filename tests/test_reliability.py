"""Bad input as a new user or an attacker would give it: each is a clear error or a warning."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from small_models import tiny_model

from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.io import write_point_cloud
from neuralsurf.observations import PointSamples
from neuralsurf.scenes import Sphere
from neuralsurf.structures import PointCloud
from neuralsurf.training import fit

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
QUICK = {"steps": 3, "device": "cpu", "progress": False, "image_every": 0}


def small(cloud, **options):
    return PointSamples(cloud, **{"batch_size": 64, "n_near": 500, "n_free": 100, "winding_points": 100, **options})


def test_zero_length_normals_are_an_error_or_replaced_with_a_warning():
    cloud = Sphere(radius=1.0).sample_surface(500, seed=0)
    with pytest.raises(InputError, match="all 500 normals"):
        fit(tiny_model(width=16, depth=2, levels=0), small(cloud.with_normals(torch.zeros(500, 3))), **QUICK)
    normals = cloud.normals.clone()
    normals[:10] = 0
    with pytest.raises(InputError, match="10 of 500 normals have zero length"):
        fit(tiny_model(width=16, depth=2, levels=0), small(cloud.with_normals(normals), normals="given"), **QUICK)
    with pytest.warns(UserWarning, match="replaced by estimated"):
        fit(tiny_model(width=16, depth=2, levels=0), small(cloud.with_normals(normals)), **QUICK)


def test_collinear_points_are_a_clear_error():
    line = PointCloud(torch.linspace(0, 1, 50)[:, None] * torch.tensor([[1.0, 2.0, 3.0]]))
    with pytest.raises(InputError, match="collinear"):
        fit(tiny_model(width=16, depth=2, levels=0), small(line), **QUICK)


def test_a_diverged_fit_says_so():
    cloud = Sphere(radius=1.0).sample_surface(500, seed=0)
    torch.manual_seed(0)
    with pytest.warns(UserWarning, match="loss rose .* diverged"), \
            pytest.raises(NeuralsurfError, match="the fit diverged: .* constant .* lower the learning rate"):
        fit(tiny_model(width=16, depth=2, levels=0), small(cloud), steps=20, log_every=5, device="cpu", progress=False,
            image_every=0, optimizer=lambda groups: torch.optim.Adam(groups, lr=1e9), encoding_lr=1e9)


def test_sphere_experiment_on_a_file_of_ones_own(tmp_path):
    from neuralsurf.cli import train

    write_point_cloud(tmp_path / "ball.ply", Sphere(radius=1.0).sample_surface(800, seed=0))
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=sphere_sdf", "data=file", f"data.path={tmp_path / 'ball.ply'}",
                                          "trainer.steps=2", "trainer.progress=false", "trainer.image_every=0",
                                          "observation.points.batch_size=64", "observation.points.n_near=500",
                                          "observation.points.n_free=100", "extract.resolution=16", "device=cpu"])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path / "run")
    assert train(cfg)["steps"] == 2


def test_stray_points_of_a_file_are_dropped_with_a_warning_unless_asked_to_keep_them(tmp_path):
    """Oracle: a sphere's 5,000 points and 4 points placed far from it (and from each other); a cloud whose density
    falls tenfold across it keeps every point."""
    from neuralsurf.geometry import isolated_points
    from neuralsurf.scenes.recipes import file_scene

    sphere = Sphere(radius=0.3).sample_surface(5000, seed=0)
    stray = torch.tensor([[2.0, 0, 0], [0, -2.5, 0], [1.5, 1.5, 1.5], [0.9, 0.0, 0.0]], dtype=torch.float64)
    cloud = PointCloud(torch.cat([sphere.points, stray]), torch.cat([sphere.normals, torch.eye(3, 3).repeat(2, 1)[:4]
                                                                    .double()]))
    assert isolated_points(cloud.points).nonzero().flatten().tolist() == [5000, 5001, 5002, 5003]
    write_point_cloud(tmp_path / "scan.ply", cloud)
    with pytest.warns(UserWarning, match=r"4 of 5004 points lie far .* \(data.drop_isolated=false keeps them\)"):
        assert torch.equal(file_scene(tmp_path / "scan.ply").cloud.points, sphere.points)
    assert len(file_scene(tmp_path / "scan.ply", drop_isolated=False).cloud) == 5004
    g = torch.Generator().manual_seed(0)
    x = 10 ** torch.rand(20_000, generator=g, dtype=torch.float64)  # spacing grows tenfold along x
    plane = torch.stack([x, (torch.rand(20_000, generator=g, dtype=torch.float64) - 0.5) * x, torch.zeros_like(x)], 1)
    assert not isolated_points(plane).any()


@pytest.mark.parametrize("name", ["../escape", "a/b", ".hidden"])
def test_scene_names_cannot_write_outside_the_run_directory(tmp_path, name):
    from neuralsurf.evaluation import run_benchmark

    with pytest.raises(ConfigError, match="file names"):
        run_benchmark({name: lambda: None}, {"m": lambda: None}, tmp_path / "run", render=False)
    assert not (tmp_path / "escape").exists()


def test_a_run_directory_under_a_file_is_a_clear_error(tmp_path):
    from neuralsurf.cli import check_run_dir_argument

    (tmp_path / "taken").write_text("a file")
    with pytest.raises(SystemExit, match="is a file, not a folder"):
        check_run_dir_argument(["experiment=bunny_sdf", f"hydra.run.dir={tmp_path / 'taken' / 'run'}"])
    check_run_dir_argument([f"hydra.run.dir={tmp_path / 'free' / 'run'}"])  # a new folder is fine


def test_a_capture_shorter_than_the_hold_out_period_holds_none_out_with_a_warning(sphere):
    from neuralsurf.scenes import scan_depth
    from neuralsurf.scenes.recipes import depth_scene

    frames = scan_depth(sphere.mesh(), n_views=4, width=32, height=24)
    with pytest.warns(UserWarning, match="4 frames, fewer than hold_out_every=10: none held out"):
        scene = depth_scene("short", frames, hold_out_every=10)
    assert scene.held_out is None and len(scene.frames) == 4
    assert len(depth_scene("long", frames, hold_out_every=2).held_out) == 2
    with pytest.raises(ConfigError, match="hold_out_every=1"):
        depth_scene("all", frames, hold_out_every=1)
