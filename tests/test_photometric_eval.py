"""evaluate.py suite=photometric: the suite composes with the issue's names; photometric stereo rows are
scored by angular error with a picture; the fusion methods run on a tiny rig_fusion."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def compose_evaluate(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="evaluate", overrides=overrides)


def run(tmp_path, overrides):
    from neuralsurf.cli import evaluate

    cfg = compose_evaluate(["suite=photometric", "n_samples=2000", "render_size=48", "device=cpu", *overrides])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path)
    return evaluate(cfg)


def test_photometric_suite_composes_its_scenes_and_methods():
    cfg = compose_evaluate(["suite=photometric"])
    assert list(cfg.scenes) == ["rig_lambertian", "rig_specular", "bunny_specular_ps", "rig_fusion"]
    assert list(cfg.methods) == ["ps_least_squares", "ps_robust", "neural_depth", "neural_depth_normals",
                                 "nehab_tsdf", "tsdf"]
    OmegaConf.to_container(cfg, resolve=True)
    observations = cfg.method.neural_depth_normals.observations
    assert observations.normals._target_ == "neuralsurf.observations.NormalMaps.from_scene"
    assert list(cfg.method.neural_depth.observations) == ["rays"] and list(observations) == ["rays", "normals"]


def test_photometric_stereo_rows_on_a_small_rig(tmp_path):
    pytest.importorskip("pymeshlab", reason="the rig scenes render the bunny (neuralsurf[data])")
    rows = run(tmp_path, ["scenes=[rig_lambertian]", "methods=[ps_least_squares,ps_robust,tsdf]",
                          "scene.rig_lambertian.size=64", "scene.rig_lambertian.n_lights=16"])
    by_method = {r["method"]: r for r in rows}
    assert by_method["tsdf"]["status"] == "skipped"  # no depth frames: a photometric-only scene
    ls, robust = by_method["ps_least_squares"], by_method["ps_robust"]
    assert ls["status"] == robust["status"] == "ok", (ls.get("reason"), robust.get("reason"))
    for row in (ls, robust):
        assert 0 <= row["normal_error_median_deg"] <= row["normal_error_mean_deg"] < 5
        assert 0 < row["integration_depth_error"] < 0.05  # integrated rig depth, fraction of the bunny's size
        assert 0 < row["integration_depth_error_pieces"] < 0.05 and 0.8 < row["integration_piece_coverage"] <= 1
        assert (tmp_path / row["render"]).is_file()
    # attached shadows break least squares at the rim; the robust method drops them
    assert robust["normal_error_mean_deg"] < ls["normal_error_mean_deg"]
    report = (tmp_path / "report.html").read_text()
    assert "normal err mean deg" in report and report.count("data:image/png;base64") >= 2


@pytest.mark.slow
def test_fusion_methods_run_on_a_tiny_rig_fusion(tmp_path):
    pytest.importorskip("pymeshlab", reason="rig_fusion renders the bunny (neuralsurf[data])")
    tiny_fit = {"trainer.steps": 3, "trainer.log_every": 1, "extract.resolution": 32, "extract.coarse_to_fine": False,
                "save_checkpoint": False, "observations.rays.n_rays": 64, "observations.rays.n_uniform": 64,
                "model.encoding.log2_table_size": 12, "model.encoding.levels": 4}
    overrides = [f"method.{m}.{k}={v}" for m in ("neural_depth", "neural_depth_normals") for k, v in tiny_fit.items()]
    overrides += ["method.neural_depth_normals.observations.normals.n_pixels=64"]
    rows = run(tmp_path, ["scenes=[rig_fusion]", "methods=[neural_depth,neural_depth_normals,nehab_tsdf,ps_robust]",
                          "scene.rig_fusion.n_views=3", "scene.rig_fusion.width=64", "scene.rig_fusion.height=48",
                          "scene.rig_fusion.n_lights=8", "method.nehab_tsdf.voxel_fraction=0.02", *overrides])
    by_method = {r["method"]: r for r in rows}
    for name in ("neural_depth", "neural_depth_normals", "nehab_tsdf"):
        row = by_method[name]
        assert row["status"] == "ok", row.get("reason")
        assert row["chamfer_l1"] > 0 and 0 < row["normal_consistency"] <= 1 and row["hausdorff"] > 0
        assert (tmp_path / row["mesh"]).is_file()
    assert by_method["ps_robust"]["status"] == "ok" and by_method["ps_robust"]["normal_error_mean_deg"] < 30


def test_a_mesh_of_a_photometric_capture_without_depth_or_truth_is_skipped_not_left_unscored(tmp_path, shared_data):
    """suite=real's specular bunny has no depth and no true surface: Poisson on its cloud (made from the
    ground-truth normals) is skipped with the reason, photometric stereo is scored."""
    from neuralsurf.cli import evaluate

    cfg = compose_evaluate(["suite=real", "scenes=[bunny_specular_ps]", "methods=[poisson,ps_least_squares]",
                            f"data_root={shared_data}", "render=false", "device=cpu"])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path)
    rows = {row["method"]: row for row in evaluate(cfg)}
    assert rows["poisson"]["status"] == "skipped" and "ground-truth normals" in rows["poisson"]["reason"]
    assert rows["ps_least_squares"]["status"] == "ok" and rows["ps_least_squares"]["normal_error_mean_deg"] > 0
