"""Error-coloured meshes in evaluate.py's report: per-vertex distances to the ground truth as viridis
vertex colours on one scale per scene, the ground truth coloured by what each method missed, the
renders with their colour bars in report.html and the coloured GLBs."""

import re
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from neuralsurf.evaluation.distances import PERCENTILE, distance_colors, shared_scale
from neuralsurf.evaluation.render import VIRIDIS, default_view, shade, viridis
from neuralsurf.geometry import closest_on_mesh
from neuralsurf.io import read_mesh
from neuralsurf.structures import Mesh, PointCloud

GT_RADIUS, RADII = 1.0, {"near": 1.02, "far": 1.05}


def sphere(radius: float, subdivisions: int) -> Mesh:
    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Mesh(np.asarray(ball.vertices), np.asarray(ball.faces))


def test_viridis_ends_and_clips():
    assert np.allclose(viridis(np.array([0.0, 1.0])), VIRIDIS[[0, -1]])
    assert np.allclose(viridis(np.array([-3.0, 7.0, np.nan])), VIRIDIS[[0, -1, 0]])
    lightness = viridis(np.linspace(0, 1, 50)) @ np.array([0.2126, 0.7152, 0.0722])
    assert (np.diff(lightness) > 0).all()  # perceptually ordered: brighter with the distance


def test_shared_scale_is_the_percentile_of_every_distance_pooled():
    a, b = np.full(100, 0.02), np.linspace(0, 1, 101)
    assert shared_scale([a, b]) == pytest.approx(np.percentile(np.concatenate([a, b]), PERCENTILE))
    assert shared_scale([np.zeros(100), np.array([0.3])]) == pytest.approx(0.3)  # percentile 0: the maximum
    assert np.allclose(distance_colors(np.array([0.0, 0.5, 9.0]), 1.0), viridis(np.array([0.0, 0.5, 1.0])))


def test_shade_draws_vertex_colours_interpolated_across_faces():
    ball = sphere(1.0, 3)
    red_top = np.where(ball.vertices[:, 1:2].numpy() > 0, [[1.0, 0, 0]], [[0, 0, 1.0]])
    image = shade(Mesh(ball.vertices, ball.faces, red_top), default_view(np.array([[-1.0] * 3, [1.0] * 3]),
                  azimuth_deg=0, elevation_deg=0), 64, 64, vertex_colors=True, ambient=1.0)
    assert tuple(image[16, 32]) == (255, 0, 0) and tuple(image[48, 32]) == (0, 0, 255)  # y up: red above
    assert tuple(image[0, 0]) == (255, 255, 255)  # background


def method_of(radius: float):
    """A method factory whose method returns a sphere of `radius` whatever the scene."""
    return lambda: (lambda scene, **_: sphere(radius, 4))


def oracle_run(tmp_path: Path, render: bool = True) -> list[dict]:
    """Two methods on a unit sphere: spheres of radius 1.02 ("near") and 1.05 ("far")."""
    from neuralsurf.evaluation import run_benchmark
    from neuralsurf.evaluation.store import rebuild_report
    from neuralsurf.scenes import Scene

    gt = sphere(GT_RADIUS, 5)
    scene = Scene(name="ball", cloud=PointCloud(gt.vertices), description="unit sphere", ground_truth=gt)
    methods = {name: method_of(radius) for name, radius in RADII.items()}
    rows = run_benchmark({"ball": lambda: scene}, methods, tmp_path, n_samples=2000, render=render, render_size=48,
                         log=lambda line: None)
    rebuild_report(tmp_path)
    return rows


def test_oracle_sphere_colours_and_shared_scale(tmp_path):
    rows = oracle_run(tmp_path)
    assert [row["status"] for row in rows] == ["ok", "ok"]
    gt = sphere(GT_RADIUS, 5)
    pooled = []
    for name, radius in RADII.items():
        prediction = sphere(radius, 4)
        pooled += [closest_on_mesh(prediction.vertices, gt)[0].numpy(),
                   closest_on_mesh(gt.vertices, prediction)[0].numpy()]
    top = float(np.percentile(np.concatenate(pooled), PERCENTILE))
    assert top == pytest.approx(0.05, abs=2e-3)  # the far sphere's offset sets the top
    report = (tmp_path / "report.html").read_text()
    shown = [float(value) for value in re.findall(r"data-top='([^']+)'", report)]
    assert len(shown) == 2 and shown == pytest.approx([top, top], rel=1e-9)  # one scale for the scene
    for name, radius in RADII.items():
        offset, prediction = radius - GT_RADIUS, sphere(radius, 4)
        coloured = read_mesh(tmp_path / "meshes" / f"ball__{name}__error.glb")
        distance = np.linalg.norm(coloured.vertices.numpy(), axis=1) - GT_RADIUS  # every vertex at the offset
        assert np.allclose(distance, offset, atol=1e-6)
        expected = viridis(np.full(len(distance), offset / top))
        assert np.abs(coloured.vertex_colors.numpy() - expected).max() < 1.5 / 255  # 8-bit colours
        # the ground truth by what the prediction missed: its vertices lie the offset less the sag of the
        # prediction's facets away
        missed = read_mesh(tmp_path / "meshes" / f"ball__{name}__gt_error.glb")
        to_prediction = closest_on_mesh(gt.vertices, prediction)[0].numpy()
        assert ((to_prediction > offset - 2e-3) & (to_prediction < offset + 1e-6)).all()
        assert np.abs(missed.vertex_colors.numpy() - viridis(to_prediction / top)).max() < 1.5 / 255
        assert f"meshes/ball__{name}__error.glb" in report and f"meshes/ball__{name}__gt_error.glb" in report


def test_error_views_follow_the_scene_scale_and_are_kept_when_it_holds(tmp_path):
    from neuralsurf.evaluation.distances import write_error_views
    from neuralsurf.evaluation.store import read_rows

    oracle_run(tmp_path)
    rows = read_rows(tmp_path)
    render = tmp_path / "renders" / "ball__near__error.png"
    made = render.stat().st_mtime_ns
    write_error_views(rows, tmp_path)
    assert render.stat().st_mtime_ns == made  # same scale, same distances: not drawn again
    views = write_error_views([row for row in rows if row["method"] == "near"], tmp_path)
    assert views[("ball", "near")]["top"] == pytest.approx(0.02, abs=2e-3)  # alone, the near sphere sets it
    assert render.stat().st_mtime_ns != made


def test_without_renders_the_coloured_meshes_are_still_saved_and_linked(tmp_path):
    oracle_run(tmp_path, render=False)
    report = (tmp_path / "report.html").read_text()
    assert not list(tmp_path.glob("renders/*.png"))
    for name in RADII:
        for glb in (f"meshes/ball__{name}__error.glb", f"meshes/ball__{name}__gt_error.glb"):
            assert (tmp_path / glb).is_file() and f"href='{glb}'" in report
    assert report.count("class='colour-bar'") == 2 and "distance to ground truth\"" not in report


@pytest.mark.browser
def test_tiny_report_shows_an_error_render_with_a_colour_bar_for_every_mesh_with_a_ground_truth(tmp_path):
    from selenium.webdriver.common.by import By
    from test_evaluation import ALWAYS_FAILS, chromium_driver, tiny_run

    rows = tiny_run(tmp_path, [ALWAYS_FAILS, "methods=[broken,poisson,neural_sdf]", "save_meshes=true"])
    meshes = [r for r in rows if r["status"] == "ok"]
    assert len(meshes) == 2 and all(r.get("distances") for r in meshes)
    browser = chromium_driver()
    try:
        browser.get((tmp_path / "report.html").as_uri())
        views = browser.find_elements(By.CSS_SELECTOR, "figure.error-view")
        assert len(views) == len(meshes)
        for view, row in zip(views, meshes):
            image = view.find_element(By.TAG_NAME, "img")
            assert image.get_attribute("alt") == f"{row['method']} on {row['scene']}: distance to ground truth"
            assert browser.execute_script("return arguments[0].complete && arguments[0].naturalWidth > 0", image)
            bar = view.find_element(By.CSS_SELECTOR, ".colour-bar")
            assert bar.is_displayed() and bar.size["width"] > 100 and bar.size["height"] > 5
            assert "linear-gradient" in bar.get_attribute("style")
            top = float(bar.get_attribute("data-top"))
            caption = view.find_element(By.TAG_NAME, "figcaption").text
            assert f"distance in scene units, 0 to {top:.3g}" in caption and top > 0
            links = [a.get_attribute("href") for a in view.find_elements(By.TAG_NAME, "a")]
            assert len(links) == 2 and all(link.endswith(".glb") for link in links)
            assert all(Path(link.removeprefix("file://")).is_file() for link in links)
            # the grey render of the same row stands beside it
            grey = view.find_element(By.XPATH, "preceding-sibling::img")
            assert grey.get_attribute("alt") == f"{row['method']} on {row['scene']}"
            assert grey.location["y"] == image.location["y"] and grey.location["x"] < image.location["x"]
        tops = {float(b.get_attribute("data-top")) for b in browser.find_elements(By.CSS_SELECTOR, ".colour-bar")}
        assert len(tops) == 1  # one scene, one scale
    finally:
        browser.quit()
    colours = read_mesh(tmp_path / "meshes" / "sphere__poisson__error.glb").vertex_colors
    assert colours is not None and torch.isfinite(colours).all()
