"""Faults: damaged or crafted inputs and misuse end in a NeuralsurfError (or a warning) that names the
problem and the fix, never in a raw exception, a silent wrong result or a huge allocation."""

import math
import re
import time
from pathlib import Path

import pytest
import torch

from neuralsurf.errors import CheckpointError
from neuralsurf.models import SDFMLP, HashGrid
from neuralsurf.priors import deepsdf, load_prior
from neuralsurf.structures import Normalization
from neuralsurf.training import field_state, load_checkpoint, load_field, save_checkpoint


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
    "margin_text": (lambda s: s.__setitem__("margin", "abc"), r"margin is 'abc', not a finite number"),
    "margin_nan": (lambda s: s.__setitem__("margin", math.nan), r"margin is nan, not a finite number"),
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
