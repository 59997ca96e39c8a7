"""The report's charts and tables: a chart per metric family that the rows have, exact Chamfer on a log
scale, only the columns with values, skipped rows folded into one line per reason naming its cause."""

import math

import numpy as np
import pytest
import torch
from PIL import Image

from neuralsurf.evaluation.methods import NotApplicable, tsdf
from neuralsurf.evaluation.render import PALETTE, bar_chart
from neuralsurf.evaluation.report import markdown_table, write_html, write_plots
from neuralsurf.evaluation.rooms import neural_voxels
from neuralsurf.observations import DepthRays
from neuralsurf.observations.base import NotObserved
from neuralsurf.scenes import Scene
from neuralsurf.structures import PointCloud

ROWS = [
    {"method": "neural_sdf", "scene": "sphere", "status": "ok", "chamfer_l1": 6.29e-3, "chamfer_l1_exact": 1.7e-4,
     "fscore_1%": 1.0, "normal_consistency_exact": 0.999, "seconds": 12.0},
    {"method": "poisson", "scene": "sphere", "status": "ok", "chamfer_l1": 6.29e-3, "chamfer_l1_exact": 7.1e-5,
     "fscore_1%": 1.0, "normal_consistency_exact": 0.998, "seconds": 1.5},
    {"method": "neural_voxels", "scene": "redkitchen", "status": "ok", "depth_error_mean": 0.0327,
     "depth_completeness": 0.91, "seconds": 2.5},
    {"method": "ps_robust", "scene": "rig_specular", "status": "ok", "normal_error_mean_deg": 5.4,
     "normal_error_median_deg": 3.1, "seconds": 0.8},
    {"method": "tsdf", "scene": "rig_lambertian", "status": "skipped",
     "reason": "TSDF fusion needs depth frames; rig_lambertian is a photometric capture (images under known lights)"},
    {"method": "tsdf", "scene": "rig_specular", "status": "skipped",
     "reason": "TSDF fusion needs depth frames; rig_specular is a photometric capture (images under known lights)"},
    {"method": "neural_depth", "scene": "sphere", "status": "skipped",
     "reason": "scene 'sphere' is not a depth capture (no depth frames as its input)"},
]


def bar_heights(image: Image.Image, colours: list[tuple[int, int, int]]) -> list[int]:
    """The height in pixels of the tallest bar of each colour."""
    pixels = np.asarray(image)
    return [int((pixels == np.array(colour)).all(axis=2).sum(axis=0).max()) for colour in colours]


def test_a_chart_per_metric_family_the_rows_have(tmp_path):
    plots = write_plots(ROWS, tmp_path)
    assert sorted(plots) == sorted(f"plots/{name}.png" for name in (
        "chamfer_l1_exact", "fscore", "normal_consistency_exact", "depth_error_mean", "depth_completeness",
        "normal_error_mean_deg", "seconds", "time_vs_chamfer"))
    assert all((tmp_path / plot).is_file() for plot in plots)
    assert not (tmp_path / "plots" / "iou.png").exists()  # no row has an IoU


def test_exact_chamfer_bars_follow_a_log_scale():
    values = {("sphere", "neural_sdf"): 1.7e-4, ("sphere", "poisson"): 7.1e-5}
    image = bar_chart("exact Chamfer", ["sphere"], ["neural_sdf", "poisson"], values, log=True)
    high, low = bar_heights(image, PALETTE[:2])
    plot_height = 360 - 30 - 56
    decades = [math.log10(v) + 5 for v in (1.7e-4, 7.1e-5)]  # the axis spans 1e-5 .. 1e-3
    assert high == pytest.approx(plot_height * decades[0] / 2, abs=2)
    assert low == pytest.approx(plot_height * decades[1] / 2, abs=2)


def test_many_long_scene_names_widen_the_chart_and_keep_every_bar():
    scenes = [f"bunny_depth_sparse_variant_{i}" for i in range(12)]
    methods = ["neural_sdf", "neural_sdf_points", "tsdf", "poisson", "neural_voxels"]
    values = {(scene, method): 1.0 + i for i, scene in enumerate(scenes) for method in methods}
    image = bar_chart("many", scenes, methods, values)
    assert image.width >= 12 * (14 * 5 + 12)
    assert all(height > 0 for height in bar_heights(image, PALETTE[:5]))


def test_tables_show_only_columns_with_values_and_fold_skipped_rows(tmp_path):
    table = markdown_table(ROWS)
    header = table.splitlines()[0]
    assert "Chamfer-L1 exact" in header and "held-out depth err m" in header and "normal err mean deg" in header
    assert "IoU" not in header and "Hausdorff" not in header and "CUDA" not in header
    skipped = [line for line in table.splitlines() if line.startswith("skipped")]
    assert skipped == [
        ("skipped (TSDF fusion needs depth frames; the scene is a photometric capture (images under known lights)): "
         "tsdf on rig_lambertian, rig_specular"),
        "skipped (the scene is not a depth capture (no depth frames as its input)): neural_depth on sphere"]
    page = write_html(ROWS, tmp_path, []).read_text()
    assert page.count("<tr>") == 1 + 4  # the header and the computed rows
    assert page.count("<li class='skipped'>") == 2 and "IoU" not in page.split("<table>")[1].split("</table>")[0]


def test_skip_reasons_name_what_the_scene_is():
    cloud = PointCloud(torch.rand(50, 3))
    capture = Scene("rig", cloud, None, None, photometric=("a capture",), cloud_from_truth=True)
    points = Scene("scan", cloud, None, None)
    with pytest.raises(NotApplicable, match=r"rig is a photometric capture \(images under known lights\)$"):
        tsdf(capture)
    with pytest.raises(NotApplicable, match="rig is a photometric capture"):
        neural_voxels(capture)
    with pytest.raises(NotApplicable, match="scan is a point cloud"):
        tsdf(points)
    with pytest.raises(NotObserved, match="no measured points either"):
        DepthRays.from_scene(capture)
    with pytest.raises(NotObserved, match=r"fit its points with PointSamples"):
        DepthRays.from_scene(points)
