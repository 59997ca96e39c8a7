"""evaluate.py's harness: every scene/method/suite config composes; a tiny run writes the tables, the
plots, the renders and report.html (opened in headless Chromium); a failing method is a row; two runs
give the same metrics."""

import csv
import io
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from neuralsurf.cli import without_feeds
from neuralsurf.evaluation.report import CHARTS
from neuralsurf.scenes import Scene
from neuralsurf.structures import Mesh

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
SCENES = sorted(p.stem for p in (CONFIGS / "scene").glob("*.yaml"))
METHODS = sorted(p.stem for p in (CONFIGS / "method").glob("*.yaml"))
SUITES = sorted(p.stem for p in (CONFIGS / "suite").glob("*.yaml"))
QUICK_FSCORE_BAR = {"sphere": 0.99, "bunny_noisy": 0.85, "bunny_depth": 0.9}
"""F@1% every method passes in the quick suite (measured: >= 1.0, 0.907 and 0.953 at the worst)."""
METRICS = ["chamfer_l1", "chamfer_l2", "chamfer_l1_exact", "normal_consistency", "fscore_1%", "hausdorff"]


ALWAYS_FAILS = "+method.broken._target_=failing_method.always_fails"
"""A method named broken that raises (tests/failing_method.py): how a failed row looks."""


def compose_evaluate(overrides: list[str]):
    """evaluate.py's config as `cli.evaluate` reads it (the nested collection data configs without their feeds)."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return without_feeds(compose(config_name="evaluate", overrides=overrides))


def tiny_run(tmp_path: Path, overrides: list[str] = ()) -> list[dict]:
    from neuralsurf.cli import evaluate

    cfg = compose_evaluate(["suite=tiny", "methods=[poisson,neural_sdf,tsdf]", *overrides])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path)
    return evaluate(cfg)


@pytest.mark.parametrize("suite", SUITES)
def test_every_suite_composes_and_names_known_scenes_and_methods(suite):
    cfg = compose_evaluate([f"suite={suite}"])
    assert cfg.scenes and cfg.methods
    assert set(cfg.scenes) <= set(cfg.scene) and set(cfg.methods) <= set(cfg.method)
    OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves


def test_every_scene_and_method_config_is_loaded():
    cfg = compose_evaluate([])
    assert set(SCENES) == set(cfg.scene) and set(METHODS) == set(cfg.method)
    for name in SCENES:
        assert cfg.scene[name]._target_.startswith(("neuralsurf.scenes.", "neuralsurf.priors."))
    # the neural method reuses train.py's groups
    assert cfg.method.neural_sdf.model._target_ == "neuralsurf.models.SDFMLP"
    observations = cfg.method.neural_sdf.observations
    assert list(observations) == ["rays", "points"] and cfg.method.neural_sdf.first_applicable
    assert observations.points._target_ == "neuralsurf.observations.PointSamples.from_scene"
    assert observations.rays._target_ == "neuralsurf.observations.DepthRays.from_scene"
    assert cfg.method.neural_sdf_points.observations.rays is None
    for name in ("neural_sdf", "neural_sdf_points", "neural_depth", "neural_depth_normals"):
        assert cfg.method[name]._target_ == "neuralsurf.evaluation.methods.fit_and_extract"
    assert "steps" in cfg.method.neural_sdf.trainer and "resolution" in cfg.method.neural_sdf.extract


@pytest.mark.parametrize("method", METHODS)
def test_every_method_config_instantiates(method):
    cfg = compose_evaluate([f"methods=[{method}]"])
    assert callable(instantiate(cfg.method[method], _partial_=True, _convert_="all"))


def test_cheap_scene_configs_instantiate():
    cfg = compose_evaluate(["scene.sphere.n_points=500", "data_root=/nonexistent"])
    scene = instantiate(cfg.scene.sphere)
    assert isinstance(scene, Scene) and len(scene.cloud) == 500 and scene.frames is None
    with pytest.raises(Exception, match="data_root"):
        instantiate(cfg.scene.stanford_scans)


def test_a_scene_without_its_data_is_skipped_with_the_reason(tmp_path):
    rows = tiny_run(tmp_path, ["scenes=[stanford_scans]", "data_root=/nonexistent"])
    assert [r["status"] for r in rows] == ["skipped"] * 3
    assert all("data_root" in r["reason"] for r in rows)


def test_tiny_run_writes_tables_plots_renders_and_report(tmp_path):
    rows = tiny_run(tmp_path)
    status = {(r["method"], r["scene"]): r["status"] for r in rows}
    assert status == {("poisson", "sphere"): "ok", ("neural_sdf", "sphere"): "ok", ("tsdf", "sphere"): "skipped"}
    ok = [r for r in rows if r["status"] == "ok"]
    for row in ok:
        assert all(math.isfinite(row[m]) for m in METRICS)
        assert row["seconds"] > 0 and row["peak_rss_mb"] > 0 and row["n_faces"] > 0
        assert isinstance(row["watertight"], bool)
    with open(tmp_path / "results.csv") as handle:
        table = list(csv.DictReader(handle))
    assert len(table) == 3 and {"torch", "open3d", "neuralsurf", "machine", "config"} <= set(table[0])
    stored = json.loads((tmp_path / "results.json").read_text())
    assert len(stored["rows"]) == 3 and stored["environment"]["torch"] == torch.__version__
    report = (tmp_path / "report.html").read_text()
    assert "<table>" in report and "neural_sdf" in report and "skipped" in report
    plots = list((tmp_path / "plots").glob("*.png"))
    charted = {key for key, _, _ in CHARTS if any(math.isfinite(r.get(key, math.nan)) for r in ok)}
    assert {"chamfer_l1_exact", "fscore_1%", "normal_consistency_exact", "hausdorff", "seconds"} <= charted
    assert {p.name for p in plots} == {f"{'fscore' if k == 'fscore_1%' else k}.png" for k in charted} | \
        {"time_vs_chamfer.png"}  # a chart for each metric the rows have, none for the others
    assert report.count("<img ") == len(plots) + 2 * len(ok)  # every plot, every render and its error view
    assert "data:image/png;base64," in report and 'src="renders/' not in report
    for row in ok:
        from PIL import Image

        image = np.asarray(Image.open(tmp_path / row["render"]))
        assert image.ndim == 3 and image.std() > 0  # something was drawn


def test_a_failing_method_is_a_row_and_the_run_goes_on(tmp_path):
    rows = tiny_run(tmp_path, [ALWAYS_FAILS, "methods=[broken,poisson]"])
    by_method = {r["method"]: r for r in rows}
    assert by_method["broken"]["status"] == "failed" and "always fails" in by_method["broken"]["reason"]
    assert by_method["poisson"]["status"] == "ok"
    assert (tmp_path / "errors" / "sphere__broken.txt").is_file()
    assert "failed" in (tmp_path / "report.html").read_text()


def test_empty_or_nan_meshes_are_failed_rows(tmp_path):
    from neuralsurf.evaluation import run_benchmark
    from neuralsurf.scenes import analytic_scene as analytic

    empty = Mesh(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.int64))
    nan = Mesh(torch.eye(3, dtype=torch.float64), torch.tensor([[0, 1, 2]]))
    object.__setattr__(nan, "vertices", torch.full((3, 3), math.nan, dtype=torch.float64))  # as a buggy method
    methods = {"empty": lambda: (lambda scene, **_: empty), "nan": lambda: (lambda scene, **_: nan)}
    rows = run_benchmark({"sphere": lambda: analytic(n_points=500)}, methods, tmp_path, n_samples=500,
                         render=False, save_meshes=False)
    assert [r["status"] for r in rows] == ["failed", "failed"]
    assert "empty" in rows[0]["reason"] and "NaN" in rows[1]["reason"]


def test_rows_are_scored_by_the_type_of_the_methods_output(tmp_path):
    """run_row looks the scorer up by the output's type (`SCORERS`): a ScoredMesh's own figures join its
    mesh's metrics; an output without a scorer is a failed row naming the types that have one."""
    from neuralsurf.evaluation import run_benchmark
    from neuralsurf.evaluation.rooms import ScoredMesh
    from neuralsurf.scenes import analytic_scene as analytic

    scene = analytic(n_points=500)
    methods = {"scored": lambda: (lambda scene, **_: ScoredMesh(scene.ground_truth, {"own_figure": 2.5})),
               "text": lambda: (lambda scene, **_: "a mesh")}
    rows = run_benchmark({"sphere": lambda: scene}, methods, tmp_path, n_samples=500, render=False,
                         save_meshes=False)
    assert rows[0]["status"] == "ok" and rows[0]["own_figure"] == 2.5 and rows[0]["fscore_1%"] == 1.0
    assert rows[1]["status"] == "failed" and "returned str, not a neuralsurf Mesh" in rows[1]["reason"]
    assert "NormalMapResult" in rows[1]["reason"]


def test_two_runs_give_the_same_metrics(tmp_path):
    first = tiny_run(tmp_path / "a", ["methods=[neural_sdf,poisson]", "render=false"])
    second = tiny_run(tmp_path / "b", ["methods=[neural_sdf,poisson]", "render=false"])
    for a, b in zip(first, second):
        assert a["status"] == b["status"] == "ok"
        for name in METRICS:
            assert a[name] == pytest.approx(b[name], abs=1e-6), (a["method"], name)


def test_neural_checkpoint_is_scored_again(tmp_path):
    """evaluate.py method.neural_sdf.checkpoint=... rebuilds the model from the checkpoint's config."""
    first = tiny_run(tmp_path / "fit", ["methods=[neural_sdf]", "render=false",
                                        "method.neural_sdf.save_checkpoint=true"])
    checkpoint = tmp_path / "fit" / "fits" / "sphere__neural_sdf" / "checkpoints" / "last.pt"
    assert checkpoint.is_file()
    again = tiny_run(tmp_path / "again", ["methods=[neural_sdf]", "render=false",
                                          f"method.neural_sdf.checkpoint={checkpoint}"])
    assert again[0]["status"] == "ok"
    assert again[0]["chamfer_l1"] == pytest.approx(first[0]["chamfer_l1"], abs=1e-6)


@pytest.mark.subprocess
@pytest.mark.slow
def test_quick_suite_runs_as_a_user_runs_it(tmp_path):
    """`python evaluate.py suite=quick`, unchanged, in a subprocess: CI runs the quick suite itself (a few
    minutes on 2 cores), and its table lists every method x scene with sound numbers."""
    pytest.importorskip("pymeshlab", reason="the bunny scenes need neuralsurf[data]")
    out = subprocess.run([sys.executable, "evaluate.py", "suite=quick", f"hydra.run.dir={tmp_path}"],
                         check=False, cwd=REPO, capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    stored = json.loads((tmp_path / "results.json").read_text())
    rows = {(r["scene"], r["method"]): r for r in stored["rows"]}
    scenes, methods = stored["scenes"], stored["methods"]
    assert set(rows) == {(s, m) for s in scenes for m in methods} and {"tsdf", "neural_sdf", "poisson"} <= set(methods)
    for (scene, method), row in rows.items():
        if method == "tsdf" and scene != "bunny_depth":
            assert row["status"] == "skipped" and "depth frames" in row["reason"]
            continue
        assert row["status"] == "ok", row
        assert f"| {method} | {scene} | ok |" in out.stdout  # the printed table
        assert row["fscore_1%"] > QUICK_FSCORE_BAR[scene], row
    assert (tmp_path / "report.html").is_file() and stored["total_seconds"] > 0


def test_renders_are_upright_and_not_mirrored():
    """A cube at +x, +y seen from +z with y up appears in the image's top-right quarter."""
    import trimesh

    from neuralsurf.evaluation.render import default_view, raycast

    cube = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    cube.apply_translation([0.5, 0.5, 0.0])
    view = default_view(np.array([[-1.0, -1, -1], [1, 1, 1]]), azimuth_deg=0, elevation_deg=0)
    hit, *_ = raycast(Mesh.from_trimesh(cube), view, 64, 64)
    rows, cols = np.nonzero(hit)
    assert len(rows) and rows.max() < 32 and cols.min() >= 32


def chromium_driver():
    """Headless Chromium under Selenium, from Debian's chromium and chromium-driver (./install.sh dev)."""
    import shutil

    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium missing: run ./install.sh dev")
    browser, driver = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")
    if not (browser and driver):
        pytest.skip("Chromium or chromedriver missing: ./install.sh dev installs Debian's chromium and chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--window-size=1280,2000"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver))


@pytest.mark.browser
def test_report_opens_in_headless_chromium_with_table_plots_and_every_render(tmp_path):
    """report.html as a user sees it: one table row per result (a failed one with its reason), and every
    plot and render decoded by the browser and laid out with a size."""
    from PIL import Image
    from selenium.webdriver.common.by import By

    rows = tiny_run(tmp_path, [ALWAYS_FAILS, "methods=[broken,poisson,neural_sdf]"])
    browser = chromium_driver()
    try:
        browser.get((tmp_path / "report.html").as_uri())
        table_rows = browser.find_elements(By.CSS_SELECTOR, "table tr")
        assert len(table_rows) == 1 + len(rows) and all(r.is_displayed() for r in table_rows)
        failed = browser.find_element(By.CSS_SELECTOR, "td.failed")
        assert failed.is_displayed() and "always fails" in failed.text
        images = browser.execute_script(
            "return Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth, i.naturalHeight,"
            " i.getBoundingClientRect().width, i.getBoundingClientRect().height])")
        renders = [r for r in rows if r.get("render")]
        assert len(renders) == sum(r["status"] == "ok" for r in rows) == 2
        plots = list((tmp_path / "plots").glob("*.png"))
        assert len(images) == len(plots) + 2 * len(renders)  # the charts, a render and an error view per mesh
        for alt, complete, width, height, shown_width, shown_height in images:
            assert complete and width > 0 and height > 0 and shown_width > 0 and shown_height > 0, alt
        assert {f"{r['method']} on {r['scene']}" for r in renders} <= {alt for alt, *_ in images}
        screenshot = np.asarray(Image.open(io.BytesIO(browser.get_screenshot_as_png())))
        assert screenshot.std() > 0  # not a blank page
    finally:
        browser.quit()
