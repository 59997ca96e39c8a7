"""neuralsurf-view: what it collects from a run of evaluate.py or from mesh files, its errors, and the page
in headless Chromium with the run's meshes in its scene."""

import io
import shutil
import socket
import sys
import time

import numpy as np
import pytest
import torch
from test_error_colours import GT_RADIUS, RADII, oracle_run, sphere

from neuralsurf.errors import InputError, MissingDependencyError
from neuralsurf.evaluation.render import viridis
from neuralsurf.io import write_mesh
from neuralsurf.view import (
    CAMERAS,
    GROUND_TRUTH,
    HELD_OUT,
    INPUT,
    UP_DIRECTIONS,
    Group,
    Item,
    Viewer,
    collect,
    main,
    screen_axes,
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The oracle run of test_error_colours: spheres of radius 1.02 ("near") and 1.05 ("far") against the unit
    sphere; the colour scale's top is the far sphere's offset, 0.05."""
    folder = tmp_path_factory.mktemp("run")
    oracle_run(folder, render=False)
    return folder


def test_a_run_shows_each_method_in_error_colours_the_ground_truth_and_what_each_missed(run):
    (group,) = collect([run])
    assert group.name == "ball" and group.scale == pytest.approx(0.05, abs=2e-3)
    labels = [item.label for item in group.items]
    assert labels == [GROUND_TRUTH, "far", "missed by far", "near", "missed by near"]
    items = {item.label: item for item in group.items}
    assert np.allclose(np.linalg.norm(items[GROUND_TRUTH].vertices, axis=1), GT_RADIUS, atol=1e-6)
    for name, radius in RADII.items():
        item = items[name]
        assert np.allclose(np.linalg.norm(item.vertices, axis=1), radius, atol=1e-6) and item.visible
        vertices, _, colours = item.coloured
        expected = viridis(np.full(len(vertices), (radius - GT_RADIUS) / group.scale)) * 255
        assert np.abs(colours.astype(float) - expected).max() <= 1.5
        assert not items[f"missed by {name}"].visible  # the ground truth coloured by what it missed: off at first


def test_the_run_s_input_points_and_cameras_come_from_its_scene_cache(run, tmp_path):
    from neuralsurf.scenes import depth_scene, scan_depth

    shutil.copytree(run, tmp_path, dirs_exist_ok=True)
    frames = scan_depth(sphere(GT_RADIUS, 3), n_views=3, width=32, height=24)
    (tmp_path / "scenes").mkdir()
    scene = depth_scene("ball", frames, hold_out_every=3)  # the third view held out
    torch.save(scene, tmp_path / "scenes" / "ball-0123.pt")  # as evaluate.py's scene cache
    items = {item.label: item for item in collect([tmp_path])[0].items}
    assert np.allclose(items[CAMERAS].poses, frames.cam_to_world[:2].double().numpy())
    assert np.allclose(items[HELD_OUT].poses, frames.cam_to_world[2:].double().numpy())
    K = frames.K[0].double().numpy()
    assert items[CAMERAS].fov == pytest.approx(2 * np.arctan(24 / (2 * K[1, 1])))
    assert len(items[INPUT].vertices) > 0 and not items[INPUT].visible


def test_mesh_files_and_folders_of_meshes(tmp_path):
    write_mesh(tmp_path / "a.ply", sphere(1.0, 2))
    (tmp_path / "more").mkdir()
    write_mesh(tmp_path / "more" / "a.ply", sphere(2.0, 2))
    (group,) = collect([tmp_path / "a.ply", tmp_path / "more"])
    assert group.name == "files" and [item.label for item in group.items] == ["a.ply", "more/a.ply"]
    assert group.items[0].coloured is None and len(group.items[1].faces) == len(sphere(2.0, 2).faces)


def test_bad_paths_are_clear_errors(tmp_path, capsys):
    with pytest.raises(InputError, match="nowhere not found; give a run folder"):
        collect([tmp_path / "nowhere"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty holds no meshes"):
        collect([tmp_path / "empty"])
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputError, match="notes.txt is not a mesh file"):
        collect([tmp_path / "notes.txt"])
    assert main([str(tmp_path / "empty")]) == 2 and "holds no meshes" in capsys.readouterr().err


def test_python_dash_m_neuralsurf_view_is_the_same_command(tmp_path, monkeypatch, capsys):
    import runpy

    monkeypatch.setattr(sys, "argv", ["neuralsurf", "view", str(tmp_path / "nowhere")])
    with pytest.raises(SystemExit) as done:
        runpy.run_module("neuralsurf", run_name="__main__")
    assert done.value.code == 2 and "neuralsurf-view: " in capsys.readouterr().err


def test_without_viser_it_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    write_mesh(tmp_path / "a.ply", sphere(1.0, 1))
    monkeypatch.setitem(sys.modules, "viser", None)
    with pytest.raises(MissingDependencyError, match=r"pip install 'neuralsurf\[view\]'"):
        Viewer(collect([tmp_path / "a.ply"]))
    assert main([str(tmp_path / "a.ply")]) == 2 and "pip install 'neuralsurf[view]'" in capsys.readouterr().err


@pytest.mark.parametrize("up", UP_DIRECTIONS)
def test_the_opening_view_is_upright_and_right_handed(up):
    right, upward, towards = screen_axes(up)
    assert np.allclose(np.cross(right, upward), towards)  # x right, y up, z towards the viewer (OpenGL)
    assert np.allclose(upward, (1 if up[0] == "+" else -1) * np.eye(3)["xyz".index(up[1])])


def test_an_up_that_is_not_an_axis_is_named():
    pytest.importorskip("viser")
    with pytest.raises(InputError, match="up='y' is not an axis; choose one of"):
        Viewer([Group("a", [Item("m", np.zeros((1, 3)))])], up="y")


def test_scenes_layouts_and_check_boxes_decide_what_is_shown_and_where(tmp_path):
    pytest.importorskip("viser")
    ball = sphere(1.0, 1)
    mesh = (ball.vertices.numpy().astype(np.float32), ball.faces.numpy())
    groups = [Group("one", [Item("a", *mesh), Item("b", *mesh), Item("points", mesh[0])]), Group("two", [Item("c", *mesh)])]
    viewer = Viewer(groups, port=free_port())
    try:
        def shown():
            return {viewer.nodes[name]: tuple(np.round(handle.position, 6))
                    for name in viewer.nodes if (handle := viewer.server.scene.get_handle_by_name(name)).visible}

        assert shown() == {"a": (0, 0, 0), "b": (2.5, 0, 0), "points": (0, 0, 0)}  # 1.25 x the scene's size apart
        viewer.boxes[0][0].value = False  # what unticking "a" does
        viewer.refresh()
        assert shown() == {"b": (0, 0, 0), "points": (0, 0, 0)}
        viewer.layout.value = "overlaid"
        viewer.boxes[0][0].value = True
        viewer.refresh()
        assert shown() == {"a": (0, 0, 0), "b": (0, 0, 0), "points": (0, 0, 0)}
        viewer.scene.value = "two"
        viewer.refresh()
        assert shown() == {"c": (0, 0, 0)} and [f.visible for f in viewer.folders] == [False, True]
    finally:
        viewer.stop()


def _yellow_pixels(png: bytes) -> int:
    """Pixels of viridis' top (yellow) in a screenshot: the far sphere in error colours (a few dozen in the
    axes' gizmo)."""
    from PIL import Image

    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return int(((image[..., 0] > 170) & (image[..., 1] > 150) & (image[..., 2] < 90)).sum())


@pytest.mark.browser
def test_the_page_loads_in_headless_chromium_with_the_run_s_meshes(run):
    pytest.importorskip("viser")
    from test_evaluation import chromium_driver

    viewer = Viewer(collect([run]), port=free_port())
    try:
        shown = {viewer.nodes[name] for name in viewer.nodes}
        assert shown == {GROUND_TRUTH, "near", "far", "missed by near", "missed by far"}
        assert all(viewer.server.scene.get_handle_by_name(name) is not None for name in viewer.nodes)
        browser = chromium_driver()
        try:
            browser.set_window_size(1000, 700)
            browser.get(f"http://127.0.0.1:{viewer.port}/")
            deadline = time.monotonic() + 30
            text = "return document.body.innerText"
            while time.monotonic() < deadline and not (viewer.server.get_clients()
                                                        and "missed by far" in browser.execute_script(text)):
                time.sleep(0.2)
            page = browser.execute_script(text)
            assert all(label in page for label in ("near", "far", "missed by near", GROUND_TRUTH)), page
            yellow = 0
            while time.monotonic() < deadline and yellow < 1000:  # the scene renders after the page's controls
                time.sleep(0.5)
                yellow = _yellow_pixels(browser.get_screenshot_as_png())
            assert yellow >= 1000, "the far sphere, yellow in error colours, is not drawn"
            viewer.colours.value = "grey"  # what the colours drop-down does
            viewer.refresh()
            while time.monotonic() < deadline and yellow >= 200:
                time.sleep(0.5)
                yellow = _yellow_pixels(browser.get_screenshot_as_png())
            assert yellow < 200, "grey meshes still drawn in error colours"
        finally:
            browser.quit()
    finally:
        viewer.stop()
