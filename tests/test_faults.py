"""Faults: damaged or crafted inputs and misuse end in a NeuralsurfError (or a warning) that names the
problem and the fix, never in a raw exception, a silent wrong result or a huge allocation."""

import math
import re
import time
from pathlib import Path

import pytest
import torch

from neuralsurf.checkpoints import field_state, load_checkpoint, load_field, save_checkpoint
from neuralsurf.errors import CheckpointError
from neuralsurf.models import SDFMLP, HashGrid
from neuralsurf.priors import deepsdf, load_prior
from neuralsurf.structures import Normalization


def small_field():
    torch.manual_seed(0)
    return SDFMLP(width=16, depth=2, skip_layers=(), weight_norm=False,
                  encoding=HashGrid(levels=2, log2_table_size=8, max_resolution=16))


@pytest.fixture
def field_path(tmp_path):
    """A checkpoint of a small SDFMLP field, as FitResult.save writes it."""
    path = tmp_path / "field.pt"
    save_checkpoint(path, field_state(small_field(), Normalization(), 0.05, 0))
    return path


@pytest.fixture
def prior_path(tmp_path):
    """A checkpoint of a small DeepSDF prior (AutoDecoder)."""
    torch.manual_seed(0)
    path = tmp_path / "prior.pt"
    save_checkpoint(path, field_state(deepsdf(3, latent_dim=4, width=16, depth=2, skip_layers=()),
                                      Normalization(), 0.05, 0))
    return path


def tampered(path, change):
    """A copy of the checkpoint at `path` with `change(state)` applied; returns its path."""
    state = load_checkpoint(path)
    change(state)
    out = path.with_name("tampered.pt")
    save_checkpoint(out, state)
    return out


def set_argument(name, value):
    return lambda state: state["model_spec"]["arguments"].__setitem__(name, value)


def test_a_huge_width_in_a_checkpoint_fails_fast_without_allocating(field_path):
    path = tampered(field_path, set_argument("width", 10**9))
    started = time.perf_counter()
    with pytest.raises(CheckpointError, match=r"width=1000000000 exceeds .* values the checkpoint stores"):
        load_field(path)
    assert time.perf_counter() - started < 5.0  # was: 12 GB allocated over ~50 s


def test_arguments_that_disagree_with_the_weights_are_refused_before_building(field_path):
    with pytest.raises(CheckpointError, match=r"arguments and weights disagree.*layers\.0\.weight"):
        load_field(tampered(field_path, set_argument("width", 200)))


def test_a_deep_spec_stops_building_once_it_outgrows_the_stored_weights(field_path):
    started = time.perf_counter()
    with pytest.raises(CheckpointError, match="larger than its stored weights"):
        load_field(tampered(field_path, set_argument("depth", 1000)))
    assert time.perf_counter() - started < 5.0


def test_load_field_refuses_a_prior_and_load_prior_refuses_a_field(field_path, prior_path):
    with pytest.raises(CheckpointError, match=r"learned prior \(AutoDecoder\).*neuralsurf\.priors\.load_prior"):
        load_field(prior_path)
    with pytest.raises(CheckpointError, match=r"holds a SDFMLP, not a learned prior.*load_field"):
        load_prior(field_path)
    assert load_prior(prior_path).codes.weight.shape == (3, 4)  # the right loader still reads each


@pytest.mark.parametrize("content", [torch.zeros(3), [1, 2, 3], "text"])
@pytest.mark.parametrize("loader", [load_field, load_prior])
def test_a_file_that_is_not_a_checkpoint_dict_is_a_checkpoint_error(tmp_path, content, loader):
    path = tmp_path / "foreign.pt"
    torch.save(content, path)
    with pytest.raises(CheckpointError, match=rf"{path.name} holds a \w+, not a neuralsurf checkpoint"):
        loader(path)


FIELD_TAMPERING = {
    "width_text": (set_argument("width", "abc"), r"SDFMLP cannot be built from the stored arguments"),
    "margin_text": (lambda s: s.__setitem__("margin", "abc"), r"margin is 'abc', not a number in 0\.\.10"),
    "margin_nan": (lambda s: s.__setitem__("margin", math.nan), r"margin is nan, not a number in 0\.\.10"),
    "margin_huge": (lambda s: s.__setitem__("margin", 1e300), r"margin is 1e\+300, not a number in 0\.\.10 \(unit-cube"),
    "centre_nan": (lambda s: s["normalization"]["center"].fill_(math.nan),
                   r"its normalization centre is \[nan, nan, nan\], not finite"),
    "weights_text": (lambda s: s.__setitem__("model", "x"), r"the weights are a str, not a dict of tensors"),
    "weights_nan": (lambda s: s["model"]["layers.0.weight"].fill_(math.nan),
                    r"weight 'layers.0.weight' holds 112 NaN or inf"),
}


@pytest.mark.parametrize("case", sorted(FIELD_TAMPERING))
def test_a_tampered_field_checkpoint_names_the_file_and_the_fault(field_path, case):
    change, message = FIELD_TAMPERING[case]
    path = tampered(field_path, change)
    with pytest.raises(CheckpointError, match=message) as error:
        load_field(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize("change, message", [
    (lambda s: s.__setitem__("model", "x"), r"the weights are a str"),
    (lambda s: s["model"]["codes.weight"].fill_(math.inf), r"weight 'codes.weight' holds 12 NaN or inf"),
    (lambda s: s["model_spec"]["arguments"]["codes"]["arguments"].__setitem__("count", "abc"),
     r"LatentCodes cannot be built"),
])
def test_a_tampered_prior_checkpoint_names_the_file_and_the_fault(prior_path, change, message):
    path = tampered(prior_path, change)
    with pytest.raises(CheckpointError, match=message) as error:
        load_prior(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize("entry, part", [((0, 3), "translation"), ((1, 1), "rotation")])
def test_a_nan_in_a_camera_pose_is_an_input_error_naming_the_frame(entry, part):
    from neuralsurf.errors import InputError
    from neuralsurf.structures import DepthFrames

    K = torch.tensor([[5.0, 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]])
    poses = torch.eye(4).repeat(3, 1, 1)
    DepthFrames(torch.ones(3, 6, 8), K, poses)  # the valid frames pass
    poses[1][entry] = math.nan
    with pytest.raises(InputError, match=rf"cam_to_world\[1\] holds NaN or inf \(in its {part}"):
        DepthFrames(torch.ones(3, 6, 8), K, poses)


@pytest.mark.subprocess
def test_a_second_run_into_a_busy_run_directory_is_refused_and_a_killed_ones_lock_is_free(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from neuralsurf.errors import ConfigError
    from neuralsurf.runlock import busy_message, run_lock

    script = ("import time\nfrom neuralsurf.runlock import run_lock\n"
              f"with run_lock({str(tmp_path)!r}):\n    print('held', flush=True)\n    time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(ConfigError, match=rf"in use by pid {holder.pid} on .*choose another hydra\.run\.dir"), \
                run_lock(tmp_path):
            pass
        assert f"pid {holder.pid}" in busy_message(tmp_path)
    finally:
        holder.send_signal(signal.SIGKILL)  # a killed run leaves no stale lock behind
        holder.wait()
    assert busy_message(tmp_path) is None
    with run_lock(tmp_path), pytest.raises(ConfigError, match=rf"in use by pid {os.getpid()}"), run_lock(tmp_path):
        pass
    assert busy_message(tmp_path) is None  # released at the end


def test_train_refuses_a_run_directory_another_train_holds(tmp_path):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from neuralsurf.cli import check_run_dir_argument, train
    from neuralsurf.errors import ConfigError
    from neuralsurf.runlock import run_lock

    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=sphere_sdf", "device=cpu"])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path)
    with run_lock(tmp_path), pytest.raises(ConfigError, match="is in use by pid"):
        train(cfg)
    assert not (tmp_path / "checkpoints").exists()
    with run_lock(tmp_path), pytest.raises(SystemExit, match=r"hydra\.run\.dir=.*is in use by pid"):
        check_run_dir_argument([f"hydra.run.dir={tmp_path}"])  # train.py's check, before Hydra writes there
    check_run_dir_argument([f"hydra.run.dir={tmp_path}"])  # free again


def test_completing_a_cloud_outside_the_priors_unit_frame_warns_with_its_bounds_and_the_fix():
    import warnings

    from neuralsurf.priors import complete_cloud, occupancy_network

    torch.manual_seed(0)
    prior = occupancy_network(2, latent_dim=8, encoder_hidden=8, hidden=8, blocks=1)
    sphere = torch.nn.functional.normalize(torch.randn(200, 3), dim=1) * 0.4
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        complete_cloud(prior, sphere)
    assert not caught, "a cloud in the unit frame needs no warning"
    with pytest.warns(UserWarning) as caught:
        complete_cloud(prior, sphere * 100 + 100)
    assert any(re.search(r"spans x, y, z = \[60.*outside the prior's unit frame.*Normalization", str(w.message))
               for w in caught)


def lit_sphere(size=16):
    """Images (4, size, size) of a Lambertian sphere under four lights, its disc mask and the lights."""
    from neuralsurf.photometric import render_lambertian

    y, x = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    mask = x**2 + y**2 < 0.8
    normals = torch.stack([x, y, -torch.sqrt((1 - x**2 - y**2).clamp_min(0))], -1).double()
    lights = torch.tensor([[0.0, 0, -1], [0.5, 0, -1], [0, 0.5, -1], [-0.5, 0, -1]], dtype=torch.float64)
    images = render_lambertian(normals, torch.full(mask.shape, 0.7, dtype=torch.float64), lights).float()
    return images, mask, lights.float()


@pytest.mark.parametrize("method", ["least_squares", "robust"])
def test_photometric_stereo_refuses_an_empty_mask_and_black_images(method):
    from neuralsurf.errors import InputError
    from neuralsurf.photometric import METHODS

    images, mask, lights = lit_sphere()
    assert METHODS[method](images, lights, mask).mask.sum() > 0
    with pytest.raises(InputError, match=r"the mask is empty \(0 of 16 x 16 pixels\)"):
        METHODS[method](images, lights, torch.zeros_like(mask))
    with pytest.raises(InputError, match="every image is black inside the mask"):
        METHODS[method](torch.zeros_like(images), lights, mask)


def test_photometric_stereo_warns_with_the_share_of_saturated_intensities():
    import warnings

    from neuralsurf.photometric import least_squares_stereo

    images, mask, lights = lit_sphere()
    def warnings_of(capture: torch.Tensor) -> list[str]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            least_squares_stereo(capture, lights, mask)
        return [str(w.message) for w in caught]

    assert warnings_of(images) == []  # a well exposed capture
    assert any(re.search(r"100% of the masked intensities sit at their image's maximum.*saturated", m)
               for m in warnings_of(torch.ones_like(images)))
    clipped = images.clamp(max=0.3)  # part of the sphere clipped in each image
    assert any(re.search(r"\d+% of the masked intensities .*saturated", m) for m in warnings_of(clipped))


def test_a_scene_name_cannot_write_outside_the_run_directory(tmp_path):
    from neuralsurf.evaluation import run_benchmark
    from neuralsurf.evaluation.filenames import safe_name
    from neuralsurf.scenes import analytic_scene

    name = "../../escape/<script>"
    run_dir = tmp_path / "a" / "b" / "run"
    rows = run_benchmark({"sphere": lambda: analytic_scene(n_points=500, name=name)},
                         {"gt": lambda: (lambda scene, **_: scene.ground_truth)}, run_dir, n_samples=500,
                         render_size=32, save_meshes=False, log=lambda line: None)
    assert rows[0]["status"] == "ok" and "render_error" not in rows[0]
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert all(run_dir in p.parents for p in written), [str(p) for p in written]
    assert (run_dir / rows[0]["render"]).is_file() and "/" not in rows[0]["render"].removeprefix("renders/")
    assert safe_name("sphere") == "sphere" and "/" not in safe_name(name) and not safe_name("..").startswith(".")


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs a /proc file system")
def test_a_run_directory_that_cannot_be_created_is_a_clear_exit(tmp_path):
    from neuralsurf.cli import check_run_dir_argument

    with pytest.raises(SystemExit, match=r"hydra\.run\.dir=/proc/nsprobe/run: the run directory cannot be created "
                                         r"in /proc .*choose a folder you can write to"):
        check_run_dir_argument(["hydra.run.dir=/proc/nsprobe/run"])
    check_run_dir_argument([f"hydra.run.dir={tmp_path}/new/run", "hydra.sweep.dir=${now:%H}"])  # fine: no exit
    assert list(tmp_path.iterdir()) == []  # the check leaves nothing behind


def test_a_diverged_fit_whose_loss_stays_finite_says_diverged():
    import functools

    from neuralsurf.errors import NeuralsurfError
    from neuralsurf.observations import PointSamples
    from neuralsurf.scenes import Sphere
    from neuralsurf.training import default_optimizer, fit

    torch.manual_seed(0)
    model = SDFMLP(width=16, depth=2, skip_layers=(), weight_norm=False)
    cloud = Sphere(center=(1.0, 0.0, 0.0), radius=2.0).sample_surface(500, seed=0)
    with pytest.raises(NeuralsurfError, match=r"the fit diverged: after 3 steps the field is constant .*lower the "
                                              r"learning rate"):
        fit(model, PointSamples(cloud, batch_size=64, n_near=500, n_free=100), steps=3, device="cpu",
            progress=False, image_every=0, optimizer=functools.partial(default_optimizer, lr=1e9))


def test_extracting_a_constant_field_names_a_diverged_fit():
    from neuralsurf.errors import ExtractionError
    from neuralsurf.extract import extract_mesh

    bounds = torch.tensor([[-1.0] * 3, [1.0] * 3], dtype=torch.float64)
    with pytest.raises(ExtractionError, match=r"no 0-level set.*constant there, as a diverged fit leaves it"):
        extract_mesh(lambda x: torch.full(x.shape[:-1], 2.8e8, dtype=x.dtype), resolution=8, bounds=bounds,
                     progress=False)


# ----------------------------------------------------------------------------- stored files and rows

def expanded_weights(path, width):
    """A copy of the checkpoint at `path` whose spec says `width` and whose every weight is a stride-0 view
    of one stored value (`torch.zeros(()).expand(shape)`): a few KB on disk for any model size."""
    from neuralsurf.models.spec import build_model

    state = load_checkpoint(path)
    state["model_spec"]["arguments"]["width"] = width
    with torch.device("meta"):
        skeleton = build_model(state["model_spec"]).state_dict()
    state["model"] = {name: torch.zeros((), dtype=value.dtype).expand(value.shape) for name, value in skeleton.items()}
    out = path.with_name("expanded.pt")
    torch.save(state, out)
    return out


def test_expanded_weights_cannot_pass_for_a_large_stored_model(field_path):
    path = expanded_weights(field_path, 2000)
    assert path.stat().st_size < 64 * 1024
    with pytest.raises(CheckpointError, match=r"expanded\.pt\['model'\]\['.*'\]: a tensor of shape .* stores 4 bytes "
                                              r"for its \d+ \(an expanded or non-contiguous view\); the checkpoint was "
                                              r"tampered with"):
        load_field(path)
    started = time.perf_counter()
    with pytest.raises(CheckpointError, match="expanded or non-contiguous"):
        load_field(expanded_weights(field_path, 40_000))  # 1.6e9 values described, none allocated
    assert time.perf_counter() - started < 5.0


def test_a_non_contiguous_weight_is_refused_and_sizes_count_stored_bytes(field_path):
    from neuralsurf.models.spec import check_weights, stored_elements

    def transpose(state):
        name = next(k for k, v in state["model"].items() if v.ndim == 2 and v.shape[0] != v.shape[1])
        state["model"][name] = state["model"][name].t().contiguous().t()

    with pytest.raises(CheckpointError, match="non-contiguous"):
        load_field(tampered(field_path, transpose))
    shared = torch.arange(10.0)
    weights = {"a": shared[:6], "b": shared[4:]}  # one storage of 10 values seen twice
    assert stored_elements(check_weights(weights, "w")) == 10
    with pytest.raises(CheckpointError, match=r"w: weight 'c'.*stores 4 bytes for its 400"):
        check_weights({"c": torch.ones(1).expand(100)}, "w")


def png_bytes(colour=(255, 0, 0)):
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (4, 4), colour).save(buffer, format="PNG")
    return buffer.getvalue()


def ok_row(**entries):
    return {"scene": "sphere", "method": "poisson", "status": "ok", "reason": "", "seconds": 1.0, **entries}


@pytest.fixture
def results(tmp_path):
    """A results folder with renders/good.png, beside a PNG file outside it (tmp_path/secret.png)."""
    folder = tmp_path / "results"
    (folder / "renders").mkdir(parents=True)
    (folder / "renders" / "good.png").write_bytes(png_bytes())
    (tmp_path / "secret.png").write_bytes(png_bytes((0, 0, 255)) + b"SECRET")
    return folder


@pytest.mark.parametrize("where", ["absolute", "dot-dot", "symlink"])
def test_a_row_cannot_embed_a_file_outside_its_results_folder(results, where, caplog):
    import base64

    from neuralsurf.evaluation.store import rebuild_report, store_row

    secret = results.parent / "secret.png"
    if where == "symlink":
        (results / "renders" / "link.png").symlink_to(secret)
    render = {"absolute": str(secret), "dot-dot": "../secret.png", "symlink": "renders/link.png"}[where]
    store_row(results, ok_row(render=render, held_out_render=render), "key", {}, True)
    store_row(results, ok_row(method="tsdf", render="renders/good.png"), "key", {}, True)
    rows, _ = rebuild_report(results)
    page = (results / "report.html").read_text()
    assert len(rows) == 2 and base64.b64encode(png_bytes()).decode() in page
    assert base64.b64encode(secret.read_bytes()).decode() not in page
    assert re.search(r"image '.*' lies outside .*results; skipped", caplog.text)


def test_only_regular_png_files_under_the_cap_are_read_from_a_results_folder(results, caplog):
    import os

    from neuralsurf.evaluation.filenames import read_stored, stored_file

    (results / "renders" / "text.png").write_bytes(b"not an image")
    os.mkfifo(results / "renders" / "fifo.png")  # a read would block forever
    (results / "renders" / "device.png").symlink_to("/dev/zero")
    assert read_stored(results, "renders/good.png", "render") == png_bytes()
    for name, reason in [("renders/text.png", "is not a PNG image"), ("renders/fifo.png", "not a regular file"),
                         ("renders/device.png", "lies outside"), ("renders/none.png", "cannot be read"),
                         (17, "not a path"), ("renders", "not a regular file")]:
        assert read_stored(results, name, "render") is None
        assert reason in caplog.text.splitlines()[-1]
    assert read_stored(results, "renders/good.png", "render", max_bytes=10) is None
    assert "more than 10" in caplog.text.splitlines()[-1]
    assert stored_file(results, "renders/good.png", "mesh") == (results / "renders" / "good.png").resolve()


def test_rows_naming_files_outside_the_folder_are_computed_again_and_get_no_error_view(results, caplog):
    import numpy as np

    from neuralsurf.evaluation.distances import write_error_views
    from neuralsurf.evaluation.store import reusable_row, store_row

    outside = results.parent / "distances.npz"
    np.savez(outside, vertices=np.zeros((3, 3)), faces=np.zeros((1, 3), np.int32), gt_vertices=np.zeros((3, 3)),
             gt_faces=np.zeros((1, 3), np.int32), to_gt=np.zeros(3), to_mesh=np.zeros(3), render_size=np.int64(8))
    row = ok_row(render="renders/good.png", distances="../distances.npz")
    store_row(results, row, "key", {}, True)
    assert reusable_row(results, "sphere", "poisson", "key") is None
    assert write_error_views([row], results) == {}
    assert "distances '../distances.npz' lies outside" in caplog.text
    store_row(results, ok_row(render="renders/good.png"), "key", {}, True)
    assert reusable_row(results, "sphere", "poisson", "key")["render"] == "renders/good.png"


def test_a_damaged_distances_file_costs_its_view_not_the_report(results, caplog):
    import numpy as np

    from neuralsurf.evaluation.store import rebuild_report, store_row

    (results / "distances").mkdir()
    np.savez(results / "distances" / "objects.npz", vertices=np.array([None, 1], dtype=object))
    np.savez(results / "distances" / "partial.npz", vertices=np.zeros((3, 3)))
    store_row(results, ok_row(distances="distances/objects.npz"), "key", {}, True)
    store_row(results, ok_row(method="tsdf", distances="distances/partial.npz"), "key", {}, True)
    rows, _ = rebuild_report(results)
    assert len(rows) == 2 and (results / "report.html").is_file()
    assert "objects.npz: array 'vertices' has dtype object, not plain numbers" in caplog.text
    assert "partial.npz lacks" in caplog.text


def test_a_killed_row_write_or_a_copied_row_file_is_not_a_second_row(results):
    import shutil

    from neuralsurf.evaluation.store import read_rows, store_row

    path = store_row(results, ok_row(), "key", {}, True)
    shutil.copy(path, path.with_name(f".{path.stem}.123-456.tmp.json"))  # left by a kill before the rename
    shutil.copy(path, path.with_name("copy.json"))
    assert [(r["scene"], r["method"]) for r in read_rows(results)] == [("sphere", "poisson")]


def test_a_malformed_row_is_skipped_with_a_warning_and_the_report_goes_on(results, caplog):
    import json

    from neuralsurf.evaluation.store import ROWS, rebuild_report, store_row

    store_row(results, ok_row(), "key", {}, True)
    bad = {"sphere__no_seconds": ok_row(method="no_seconds", seconds=None),
           "sphere__text_metric": ok_row(method="text_metric", chamfer_l1="small"),
           "3__number_scene": ok_row(scene=3, method="number_scene"),
           "sphere__odd_status": ok_row(method="odd_status", status="great"),
           "sphere__list_render": ok_row(method="list_render", render=["a"])}
    for stem, row in bad.items():
        (results / ROWS / f"{stem}.json").write_text(json.dumps({"key": "key", "final": True, "row": row}))
    rows, table = rebuild_report(results)
    assert [r["method"] for r in rows] == ["poisson"] and "poisson" in table
    for reason in ["an ok row without its seconds", "chamfer_l1 is 'small', not a number", "scene is 3, not a name",
                   "status is 'great'", "render is ['a'], not text"]:
        assert reason in caplog.text


def test_the_viewer_skips_rows_that_are_not_rows_and_meshes_outside_the_folder(tmp_path, caplog):
    import json

    from neuralsurf.io import write_mesh
    from neuralsurf.scenes import Sphere
    from neuralsurf.view import run_groups

    folder = tmp_path / "run"
    (folder / "meshes").mkdir(parents=True)
    mesh = Sphere(radius=0.3).mesh(1)
    write_mesh(folder / "meshes" / "sphere__poisson.ply", mesh)
    write_mesh(tmp_path / "outside.ply", mesh)
    rows = [3, ["sphere"], {"method": "m"}, ok_row(method="outside", mesh="../outside.ply"),
            ok_row(mesh="meshes/sphere__poisson.ply")]
    (folder / "results.json").write_text(json.dumps({"rows": rows}))
    (folder / "scenes").mkdir()
    (folder / "scenes" / "sphere-0123.pt").symlink_to("/dev/zero")  # a scene cache that never ends
    groups = run_groups(folder)
    assert [[item.label for item in g.items] for g in groups] == [["poisson"]]
    assert "mesh '../outside.ply' lies outside" in caplog.text and "not a row of scene, method and status" in caplog.text
    assert "scene 'scenes/sphere-0123.pt' lies outside" in caplog.text


def test_the_viewer_refuses_a_port_outside_0_to_65535(capsys):
    from neuralsurf.view import main

    with pytest.raises(SystemExit) as exit_:
        main(["mesh.ply", "--port", "99999"])
    assert exit_.value.code == 2
    assert "argument --port: '99999' is not a port number; give an integer in 0..65535" in capsys.readouterr().err


# ----------------------------------------------------------------------------- readers and writers

def trajectory(ids):
    return "".join(f"{i} {i} {k + 1}\n" + "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" for k, i in enumerate(ids))


@pytest.mark.parametrize("ids, frames, message", [
    ([0, -1], 3, r"line 6 names frame -1; ids must be distinct, >= 0 and below 3"),
    ([0, 1, 1], 3, r"line 11 names frame 1; ids must be distinct"),
    ([0, 3], 3, r"line 6 names frame 3; ids must be distinct, >= 0 and below 3 \(the depth images in depth/\)"),
    ([2, -5], None, r"line 6 names frame -5; ids must be distinct, >= 0$"),
])
def test_redwood_trajectory_ids_must_name_distinct_depth_images(tmp_path, ids, frames, message):
    from neuralsurf.errors import FileFormatError
    from neuralsurf.io.rgbd import read_trajectory_log

    (tmp_path / "traj.log").write_text(trajectory(ids))
    with pytest.raises(FileFormatError, match=message):
        read_trajectory_log(tmp_path / "traj.log", frames=frames)
    (tmp_path / "good.log").write_text(trajectory([2, 0, 1]))
    assert read_trajectory_log(tmp_path / "good.log", frames=3)[0].tolist() == [2, 0, 1]


@pytest.mark.parametrize("quaternion", ["0 0 0 0", "0 0 nan 1"])
def test_a_tum_pose_without_a_rotation_is_an_input_error_naming_the_file(tmp_path, quaternion):
    from neuralsurf.errors import InputError
    from neuralsurf.io import read_rgbd_folder

    (tmp_path / "depth.txt").write_text("1.000000 depth/1.png\n")
    (tmp_path / "groundtruth.txt").write_text(f"1.0000 0 0 0 {quaternion}\n")
    with pytest.raises(InputError, match=r"groundtruth\.txt'?: quaternion \(x y z w\) \[.*\] is not a rotation "
                                         r"\(zero length, NaN or not 4 numbers\); correct the pose"):
        read_rgbd_folder(tmp_path, with_color=False, progress=False)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs a /proc file system")
@pytest.mark.parametrize("suffix", [".ply", ".obj", ".off", ".stl", ".glb"])
def test_write_mesh_into_a_folder_that_cannot_be_written_is_a_file_format_error(suffix):
    from neuralsurf.errors import FileFormatError
    from neuralsurf.io import write_mesh
    from neuralsurf.scenes import Sphere

    with pytest.raises(FileFormatError, match=rf"cannot write mesh file '/proc/mesh{suffix}': .*; check that its "
                                              rf"folder is writable"):
        write_mesh(f"/proc/mesh{suffix}", Sphere(radius=0.3).mesh(0))


def test_the_fallback_extraction_drops_special_modes_and_owners(tmp_path, monkeypatch):
    import io
    import os
    import stat
    import tarfile

    from neuralsurf import data

    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        member = tarfile.TarInfo("data/tool")
        member.mode, member.uid, member.gid, member.uname, member.size = 0o6777, 12345, 12345, "nobody", 2
        tar.addfile(member, io.BytesIO(b"hi"))
    monkeypatch.delattr(tarfile, "data_filter", raising=False)  # Python before 3.11.4
    buffer.seek(0)
    with tarfile.open(fileobj=buffer) as tar:
        data._extract(tar, tmp_path, tar.getmembers())
    status = (tmp_path / "data" / "tool").stat()
    assert stat.S_IMODE(status.st_mode) == 0o755 and (status.st_uid, status.st_gid) == (os.getuid(), os.getgid())


def npz_with(tmp_path, name, header_shape, dtype="<f4", payload=b"\0" * 12):
    """An .npz whose member `name` declares `header_shape` of `dtype` but stores `payload`."""
    import zipfile

    header = repr({"descr": dtype, "fortran_order": False, "shape": header_shape}).encode()
    header += b" " * (63 - (10 + len(header)) % 64) + b"\n"
    array = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + payload
    path = tmp_path / f"{name}.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr(f"{name}.npy", array)
    return path


def test_array_headers_are_checked_against_the_file_before_reading(tmp_path):
    import numpy as np

    from neuralsurf.errors import FileFormatError
    from neuralsurf.io.npz import read_npz
    from neuralsurf.io.shape_folders import read_occupancy_shape

    with pytest.raises(FileFormatError, match=r"points\.npz: array 'points' declares shape \(100000000000, 3\) "
                                              r"\(float32\), more than its \d+ bytes hold"):
        read_npz(npz_with(tmp_path, "points", (10**11, 3)))
    assert read_npz(npz_with(tmp_path, "small", (1, 3)))["small"].shape == (1, 3)
    shape = tmp_path / "class" / "shape"
    shape.mkdir(parents=True)
    np.savez(shape / "points.npz", points=np.array([["a", "b", "c"]]), occupancies=np.ones(1, bool))
    np.savez(shape / "pointcloud.npz", points=np.zeros((1, 3), np.float32))
    with pytest.raises(FileFormatError, match=r"points\.npz: array 'points' has dtype <U1, not plain numbers"):
        read_occupancy_shape(shape)


# ----------------------------------------------------------------------------- config values

@pytest.mark.parametrize("key, value, allowed", [
    ("optimizer.lr", "abc", "a finite number > 0"), ("optimizer.lr", -1, "a finite number > 0"),
    ("model.width", "abc", r"an integer in 1\.\.16384"), ("model.width", 40_000, r"an integer in 1\.\.16384"),
    ("seed", "abc", r"an integer in 0\.\.4294967295 or null"), ("data.n_points", -5, r"an integer in 1\.\.1000000000"),
    ("trainer.steps", 2.5, "an integer >= 0"), ("extract.resolution", 1, r"an integer in 2\.\.65536"),
    ("method.neural_sdf.optimizer.lr", float("nan"), "a finite number > 0"),
    ("scene.sphere.n_points", 0, r"an integer in 1\.\.1000000000"), ("model.depth", True, r"an integer in 1\.\.256"),
])
def test_a_config_value_of_the_wrong_type_or_range_is_one_config_error(key, value, allowed):
    from omegaconf import OmegaConf

    from neuralsurf.config_checks import check_config
    from neuralsurf.errors import ConfigError

    config = OmegaConf.to_container(OmegaConf.from_dotlist([f"{key}=0"]))
    OmegaConf.update(cfg := OmegaConf.create(config), key, value)
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)}=.*: expected {allowed}; set {re.escape(key)}=<value> "
                                          rf"in that range$"):
        check_config(OmegaConf.to_container(cfg), memory=2**40)


def test_an_extraction_grid_larger_than_the_memory_is_refused_with_the_largest_that_fits():
    from neuralsurf.config_checks import check_config
    from neuralsurf.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^extract\.resolution=4096: its extraction grid needs at least 320\.2 GiB, "
                                          r"more than the 6\.0 GiB available; use extract\.resolution=1087 or less$"):
        check_config({"extract": {"resolution": 4096}}, memory=6 * 2**30)
    check_config({"extract": {"resolution": 1087}}, memory=6 * 2**30)
    with pytest.raises(ConfigError, match="use extract.resolution=1087 or less"):
        check_config({"extract": {"resolution": 1088}}, memory=6 * 2**30)


@pytest.mark.parametrize("argv, bad", [(["-m", "shard=range(3)", "shards=2"], "shard=2 shards=2"),
                                       (["-m", "shard=0,1", "shards=1"], "shard=1 shards=1"),
                                       (["-m", "shard=0", "shards=0"], "shard=0 shards=0")])
def test_a_shard_sweep_out_of_range_is_refused_before_any_job(argv, bad):
    from neuralsurf.config_checks import check_config, check_sweep_arguments
    from neuralsurf.errors import ConfigError

    with pytest.raises(ConfigError, match=rf"^{bad}: expected integers with shards >= 1 and 0 <= shard < shards"):
        check_sweep_arguments(argv)
    check_sweep_arguments(["-m", "shard=range(4)", "shards=4", "seed=1"])
    with pytest.raises(ConfigError, match="shard='a'"):
        check_config({"shard": "a", "shards": 2})
    with pytest.raises(ConfigError, match=r"^seed='abc'"):  # the key given, not the places it is copied to
        check_config({"data": {"seed": "abc"}, "seed": "abc"})


def test_every_shipped_config_passes_the_checks():
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from neuralsurf.config_checks import check_config

    configs = Path(__file__).resolve().parents[1] / "neuralsurf" / "configs"
    with initialize_config_dir(str(configs), version_base="1.3"):
        options = [f"{group}={p.stem}" for group in ("experiment", "data", "model") for p in (configs / group).glob("*.yaml")]
        for option in sorted(options):
            cfg = compose("train", overrides=[option])
            check_config(OmegaConf.to_container(cfg, resolve=True), memory=2**40)
        for suite in sorted(p.stem for p in (configs / "suite").glob("*.yaml")):
            cfg = compose("evaluate", overrides=[f"suite={suite}"])
            check_config(OmegaConf.to_container(cfg, resolve=True), memory=2**40)


@pytest.mark.subprocess
def test_train_py_with_a_bad_learning_rate_exits_with_one_line_before_building(tmp_path):
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, str(repo / "train.py"), "experiment=sphere_sdf", "optimizer.lr=abc",
                           f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=300, check=False)
    output = done.stdout + done.stderr
    assert done.returncode == 1 and "Traceback" not in output
    assert re.search(r"ConfigError: optimizer\.lr='abc': expected a finite number > 0; set optimizer\.lr=<value> in "
                     r"that range", output)
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_a_report_file_that_cannot_be_replaced_is_a_file_format_error(results):
    from neuralsurf.errors import FileFormatError
    from neuralsurf.evaluation.store import rebuild_report, store_row

    store_row(results, ok_row(), "key", {}, True)
    (results / "report.html").mkdir()
    with pytest.raises(FileFormatError, match=r"cannot write the report of .*results: Is a directory \(.*results/report\.html\); each report "
                                              r"file must be a writable file"):
        rebuild_report(results)


@pytest.mark.subprocess
def test_train_takes_the_run_lock_before_hydra_writes_into_the_run_directory(tmp_path):
    import os
    import subprocess
    import sys

    from neuralsurf.cli import check_run_dir_argument
    from neuralsurf.runlock import busy_message, run_lock

    run = tmp_path / "run"
    check_run_dir_argument([f"hydra.run.dir={run}"], lock=True)  # as train.py does before Hydra starts
    script = f"from neuralsurf.cli import check_run_dir_argument\ncheck_run_dir_argument(['hydra.run.dir={run}'], lock=True)"
    second = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=False)
    assert second.returncode == 1 and "Traceback" not in second.stderr
    assert f"error: hydra.run.dir={run}: run directory {run} is in use by pid {os.getpid()}" in second.stderr
    assert sorted(p.name for p in run.iterdir()) == [".neuralsurf.lock"]  # nothing of the second run's
    with run_lock(run):  # the run itself goes on under the lock taken for it
        assert busy_message(run) is not None
    assert busy_message(run) is None


def onet_folder(root, shapes=3):
    """Occupancy Networks' layout: class c, `shapes` spheres of radius 0.4 (points.npz, pointcloud.npz)."""
    import numpy as np

    for i in range(shapes):
        rng = np.random.default_rng(i)
        folder = root / "c" / f"s{i}"
        folder.mkdir(parents=True)
        points = rng.uniform(-0.55, 0.55, (4001, 3)).astype(np.float32)
        normals = rng.normal(size=(800, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        np.savez(folder / "points.npz", points=points, occupancies=np.packbits(np.linalg.norm(points, axis=1) < 0.4))
        np.savez(folder / "pointcloud.npz", points=(0.4 * normals).astype(np.float32), normals=normals.astype(np.float32))
    return root


def prior_config(tmp_path, experiment, source, *overrides):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    configs = Path(__file__).resolve().parents[1] / "neuralsurf" / "configs"
    with initialize_config_dir(str(configs), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}", "data=shape_folder", f"data.source={source}",
                                          "data.normalize=false", f"data.root={tmp_path / 'cache'}", "data.workers=0",
                                          "data.n_sdf=2000", "data.n_occ=1000", "data.n_surface=400", "trainer.steps=2",
                                          "trainer.progress=false", "trainer.checkpoint_every=1", "device=cpu",
                                          *overrides])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(tmp_path / "run")
    return cfg


def test_a_prior_trains_on_occupancy_networks_layout_and_is_kept_unscored(tmp_path):
    import json

    from neuralsurf.cli import train
    from neuralsurf.errors import ConfigError

    source = onet_folder(tmp_path / "onet")
    with pytest.raises(ConfigError, match=r"Occupancy Networks' layout, which has no meshes to take depth views of; "
                                          r"set observation\.occupancy\.partial_views=0"):
        train(prior_config(tmp_path, "shapes_onet_tiny", source))
    assert not (tmp_path / "cache").exists()  # refused before building
    with pytest.warns(UserWarning, match="no meshes to score test shapes against: the prior is trained and kept"):
        metrics = train(prior_config(tmp_path, "shapes_onet_tiny", source, "observation.occupancy.partial_views=0",
                                     "observation.occupancy.shapes_per_batch=2"))
    assert metrics["steps"] == 2 and (tmp_path / "run" / "checkpoints" / "last.pt").is_file()
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["steps"] == 2


def test_a_mesh_folder_without_test_shapes_is_refused_before_building(tmp_path):
    from neuralsurf.cli import train
    from neuralsurf.errors import ConfigError
    from neuralsurf.io import write_mesh
    from neuralsurf.scenes import Sphere

    for name in ("a", "b"):
        write_mesh(tmp_path / "meshes" / name / "one.ply", Sphere(radius=0.4).mesh(1))
    with pytest.raises(ConfigError, match=r"no test shapes to score the prior on; list some in test\.lst or set "
                                          r"data\.test_fraction > 0"):
        train(prior_config(tmp_path, "shapes_deepsdf_tiny", tmp_path / "meshes", "data.test_fraction=0"))
    assert not (tmp_path / "cache").exists()


def test_a_shape_that_cannot_be_sampled_is_named_by_its_file(tmp_path):
    from neuralsurf.errors import NeuralsurfError
    from neuralsurf.io import write_mesh
    from neuralsurf.priors.folders import FolderCollection
    from neuralsurf.scenes import Sphere
    from neuralsurf.structures import Mesh

    write_mesh(tmp_path / "meshes" / "a" / "good.ply", Sphere(radius=0.4).mesh(1))
    write_mesh(tmp_path / "meshes" / "a" / "point.ply", Mesh(torch.ones(3, 3), torch.tensor([[0, 1, 2]])))
    collection = FolderCollection(str(tmp_path / "meshes"), root=str(tmp_path / "cache"), n_sdf=500, n_occ=500,
                                  n_surface=200, test_fraction=0.0, workers=0)
    with pytest.raises(NeuralsurfError, match=r"meshes/a/point\.ply: .*one location"):
        collection.build(progress=False)


def test_a_results_dir_that_cannot_be_made_is_a_config_error(tmp_path):
    from neuralsurf.config_checks import check_config
    from neuralsurf.errors import ConfigError

    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match=r"^results_dir=.*/file/out: .*/file is a file, not a folder"):
        check_config({"results_dir": str(tmp_path / "file" / "out")})
    if Path("/proc/self").is_dir():
        with pytest.raises(ConfigError, match=r"^results_dir=/proc/out: a folder cannot be created in /proc"):
            check_config({"results_dir": "/proc/out"})
    check_config({"results_dir": str(tmp_path / "new" / "out")})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_a_file_where_a_data_sets_folder_goes_is_refused_before_the_download(tmp_path, monkeypatch):
    from neuralsurf import data
    from neuralsurf.errors import FileFormatError

    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path))
    monkeypatch.delenv("NEURALSURF_DATA", raising=False)
    monkeypatch.setattr(data, "download", lambda *args, **kwargs: pytest.fail("downloaded"))
    (tmp_path / data.DATASETS["stanford_bunny"].folder).write_text("not a folder")
    with pytest.warns(UserWarning, match="no sha256"), \
            pytest.raises(FileFormatError, match=r"is a file where the folder of data set stanford_bunny goes"):
        data.fetch("stanford_bunny", progress=False)


def test_files_a_complete_manifest_does_not_list_are_dropped(tmp_path):
    import dataclasses
    import hashlib
    import io
    import tarfile

    from neuralsurf import data

    files = {"bunny/data/bun.conf": b"camera 0 0 0 0 0 0 1\n", "bunny/data/extra.sh": b"#!/bin/sh\n"}
    archive = tmp_path / "bunny.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        for name, content in files.items():
            member = tarfile.TarInfo(name)
            member.size = len(content)
            tar.addfile(member, io.BytesIO(content))
    manifest = {"data/bun.conf": hashlib.sha256(files["bunny/data/bun.conf"]).hexdigest()}
    dataset = dataclasses.replace(data.DATASETS["stanford_bunny"], manifest=manifest)
    assert dataset.complete
    (tmp_path / "out").mkdir()
    with pytest.warns(UserWarning, match=r"stanford_bunny: 1 files of the archive are not in its manifest and were "
                                         r"dropped \(data/extra\.sh\)"):
        data._unpack_checked("stanford_bunny", dataset, archive, tmp_path / "out")
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*")) == [
        "data", "data/bun.conf"]


def test_prior_scenes_without_test_shapes_are_refused_before_building(tmp_path):
    from neuralsurf.errors import ConfigError
    from neuralsurf.io import write_mesh
    from neuralsurf.priors.folders import FolderCollection
    from neuralsurf.priors.scenes import shapes_cloud
    from neuralsurf.scenes import Sphere

    for name in ("a", "b"):
        write_mesh(tmp_path / "meshes" / name / "one.ply", Sphere(radius=0.4).mesh(1))
    meshes = FolderCollection(str(tmp_path / "meshes"), root=str(tmp_path / "cache"), test_fraction=0.0, workers=0)
    with pytest.raises(ConfigError, match="no test shapes to evaluate on; list some in test.lst"):
        shapes_cloud(meshes)
    onet = FolderCollection(str(onet_folder(tmp_path / "onet")), root=str(tmp_path / "cache"), workers=0)
    with pytest.raises(ConfigError, match="Occupancy Networks' layout, which has no meshes to evaluate"):
        shapes_cloud(onet)
    assert not (tmp_path / "cache").exists()
