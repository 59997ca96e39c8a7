"""evaluate.py suite=priors: the issue's scene and method names, scene sets scored as one row each, a
prior trained once per evaluation (or read from a checkpoint)."""

import json
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from neuralsurf.errors import ConfigError
from neuralsurf.priors import ShapeCollection, clipped_to_cube

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

COLLECTION = {"classes": "[lamp]", "n_test": 1, "n_sdf": 2000, "n_occ": 1000, "n_surface": 3000,
              "mesh_resolution": 32, "workers": 0}


def compose_priors(tmp_path, overrides=()):
    tiny = []
    for group, name in [("scene", "shapes_cloud"), ("scene", "shapes_one_view"), ("method", "deepsdf"),
                        ("method", "occupancy_network")]:
        root = tmp_path / ("test_shapes" if group == "scene" else "train_shapes")
        tiny += [f"{group}.{name}.collection.{k}={v}" for k, v in {**COLLECTION, "root": root}.items()]
    for method in ("deepsdf", "occupancy_network"):
        tiny += [f"method.{method}.collection.n_train=2", f"method.{method}.trainer.steps=5",
                 f"++method.{method}.refine={{resolution:24,steps:20}}",
                 f"method.{method}.resolution=32", f"method.{method}.trainer.checkpoint_every=5"]
    tiny += ["method.deepsdf.latent_steps=3", "method.deepsdf.observation.shapes.shapes_per_batch=2",
             "method.occupancy_network.observation.occupancy.shapes_per_batch=2", "scene.shapes_one_view.width=64",
             "scene.shapes_one_view.height=48", "n_samples=2000", "render_size=64", "device=cpu"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=priors", *tiny, *overrides])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path / "run")
    return cfg


def test_the_priors_suite_composes_its_scenes_and_methods():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=priors"])
    assert list(cfg.scenes) == ["shapes_cloud", "shapes_one_view"]
    assert list(cfg.methods) == ["deepsdf", "occupancy_network", "neural_sdf", "poisson", "tsdf"]
    assert cfg.scene.shapes_cloud.n_points == 3000


def test_priors_suite_scores_each_scene_set_as_one_row_with_per_shape_values(tmp_path):
    from neuralsurf.cli import evaluate

    rows = evaluate(compose_priors(tmp_path, ["methods=[deepsdf,occupancy_network,tsdf]"]))
    status = {(r["method"], r["scene"]): r["status"] for r in rows}
    assert status == {("deepsdf", "shapes_cloud"): "ok", ("occupancy_network", "shapes_cloud"): "ok",
                      ("tsdf", "shapes_cloud"): "skipped", ("deepsdf", "shapes_one_view"): "ok",
                      ("occupancy_network", "shapes_one_view"): "ok", ("tsdf", "shapes_one_view"): "ok"}
    run = tmp_path / "run"
    saved = json.loads((run / "results.json").read_text())["rows"]
    for row in (r for r in saved if r["status"] == "ok"):
        assert row["shapes"] == 1 and [s["shape"] for s in row["per_shape"]] == ["lamp_test_0000"]
        assert row["chamfer_l1_exact"] == pytest.approx(row["per_shape"][0]["chamfer_l1_exact"])
        assert row["seconds"] > 0 and row["peak_rss_mb"] > 0 and (run / row["render"]).is_file()
        if row["method"] != "tsdf":  # the priors' meshes are closed (clipped to the unit cube)
            assert row["pred_watertight"] == 1.0 and 0 <= row["iou"] <= 1
    one_view = next(r for r in saved if (r["method"], r["scene"]) == ("deepsdf", "shapes_one_view"))
    assert (run / one_view["class_render"]).is_file()  # input | completion | ground truth, one line per class
    # the per-class answer: each prior against TSDF of the same view (k/n shapes won), in results.md
    assert "| shapes_one_view | lamp | deepsdf | 1 |" in (run / "results.md").read_text()
    assert "Per class" in (run / "report.html").read_text()
    # each prior was trained once (5 steps), then reused for the second scene
    priors = sorted((run / "fits").glob("prior_*/checkpoints/last.pt"))
    assert len(priors) == 2
    assert "per_shape" not in (run / "results.csv").read_text().splitlines()[0].split(",")  # lists: JSON only


def test_a_root_holding_another_collection_is_refused(tmp_path):
    ShapeCollection(classes=("lamp",), n_train=1, n_test=0, n_sdf=500, n_occ=100, n_surface=500,
                    mesh_resolution=24, workers=0, root=str(tmp_path)).build(progress=False)
    with pytest.raises(ConfigError, match="another shape collection"):
        ShapeCollection(classes=("lamp",), n_train=2, n_test=0, n_sdf=500, n_occ=100, n_surface=500,
                        mesh_resolution=24, workers=0, root=str(tmp_path)).build(progress=False)


def test_a_field_clipped_to_the_cube_keeps_its_sign_inside_and_is_the_box_distance_outside():
    x = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.54, 0.0, 0.0], [0.6, 0.6, 0.6]])
    inside = clipped_to_cube(lambda p: -torch.ones(p.shape[:-1]), half=0.525)(x)  # a field negative everywhere
    assert inside[:2].tolist() == pytest.approx([-0.525, -0.025])  # still inside, up to the cube's faces
    assert float(inside[2]) == pytest.approx(0.015, abs=1e-6) and inside[3] > 0  # outside the cube: the box's distance
    outside = clipped_to_cube(lambda p: torch.ones(p.shape[:-1]), half=0.525)(x)
    assert outside[:2].tolist() == [1.0, 1.0]


def test_the_build_command_makes_the_collection_that_train_py_finds(tmp_path):
    from neuralsurf.priors.__main__ import main

    main(["build", "--out", str(tmp_path), "--classes", "lamp", "--n-train", "1", "--n-test", "1", "--workers", "0",
          "--n-sdf", "500", "--n-occ", "100", "--n-surface", "500", "--mesh-resolution", "24"])
    collection = ShapeCollection(classes=("lamp",), n_train=1, n_test=1, n_sdf=500, n_occ=100, n_surface=500,
                                 mesh_resolution=24, root=str(tmp_path))
    assert collection.build(progress=False) == tmp_path  # the same collection: nothing refused, nothing rebuilt
    assert [s.name for s in collection.test_shapes()] == ["lamp_test_0000"]


def test_a_trained_prior_is_named_by_what_it_was_trained_on_not_by_the_test_split_or_the_build():
    from neuralsurf.evaluation.methods import prior_settings

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=priors_folder", "folder.source=/shapes"])
    method = OmegaConf.to_container(cfg.method.deepsdf, resolve=True)
    other = json.loads(json.dumps(method))
    other["collection"].update(n_test=1, workers=0, root="/elsewhere")
    assert prior_settings(other) == prior_settings(method)
    other["collection"]["n_train"] = 3
    assert prior_settings(other) != prior_settings(method)
    assert prior_settings(method)["trainer"] == method["trainer"]
