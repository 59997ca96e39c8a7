"""neuralsurf-export: a finished run's field meshed again (resolution, format, box) without fitting; the
outputs of a train.py run: metrics.json as strict JSON, TensorBoard as one run."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from omegaconf import OmegaConf

from neuralsurf.checkpoints import load_field
from neuralsurf.errors import ConfigError
from neuralsurf.export import export_run, main
from neuralsurf.extract import extract_mesh
from neuralsurf.io import read_mesh

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
TINY = ["experiment=sphere_sdf", "data.n_points=3000", "trainer.steps=3", "trainer.log_every=1",
        "trainer.image_every=0", "trainer.progress=false", "extract.resolution=32", "device=cpu",
        "observation.points.batch_size=64", "observation.points.n_near=2000", "observation.points.n_free=500"]


def compose(config_name: str, overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = hydra_compose(config_name=config_name, overrides=overrides)
    OmegaConf.set_struct(cfg, False)
    return cfg


def strict_json(path: Path):
    """The file parsed as JSON that rejects NaN and Infinity."""
    def refuse(constant):
        raise ValueError(f"{path} holds {constant}, which is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A tiny train.py run of the analytic sphere."""
    from neuralsurf.cli import train

    folder = tmp_path_factory.mktemp("run")
    cfg = compose("train", TINY)
    cfg.run_dir = str(folder)
    train(cfg)
    return folder


def test_metrics_json_is_strict_json_and_tensorboard_lists_the_run_once(run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    metrics = strict_json(run / "metrics.json")
    assert metrics["steps"] == 3 and metrics["chamfer_l1_exact"] > 0
    for name, reason in metrics.get("undefined", {}).items():
        assert metrics[name] is None and reason
    assert [p for p in (run / "tensorboard").iterdir() if p.is_dir()] == []  # no sub-run of its own
    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    assert {"_hparams_/experiment", "_hparams_/session_start_info"} <= set(events.PluginTagToContent("hparams"))
    assert "metric/steps" in events.Tags()["scalars"] and "train/lr" in events.Tags()["scalars"]


def test_export_at_the_runs_resolution_gives_the_runs_mesh(run, tmp_path):
    path = export_run(run, tmp_path / "again.ply", progress=False)
    again, original = read_mesh(path), read_mesh(run / "mesh.ply")
    assert again.faces.shape == original.faces.shape
    assert torch.allclose(again.vertices.double(), original.vertices.double(), atol=1e-6)


@pytest.mark.parametrize("file_format", ["obj", "glb", "off", "stl"])
def test_export_at_another_resolution_and_format(run, file_format):
    path = export_run(run, resolution=24, file_format=file_format, progress=False)
    assert path == run / f"mesh_24.{file_format}"
    expected = extract_mesh(load_field(run / "checkpoints" / "last.pt"), resolution=24, progress=False)
    mesh = read_mesh(path)
    assert len(mesh.faces) == len(expected.faces)
    assert torch.allclose(mesh.vertices.double().mean(0), expected.vertices.double().mean(0), atol=1e-4)


def test_export_of_a_box_meshes_only_inside_it_at_the_resolution_over_the_box(run, tmp_path):
    field = load_field(run / "checkpoints" / "last.pt")
    lo, hi = field.bounds.double()
    half = [*lo.tolist(), *((lo + hi) / 2).tolist()]
    path = export_run(run, tmp_path / "part.ply", resolution=32, box=half, progress=False)
    mesh = read_mesh(path)
    corner = torch.tensor(half).reshape(2, 3).double()
    spacing = float((corner[1] - corner[0]).max()) / 32
    assert ((mesh.vertices.double() >= corner[0] - 1e-6) & (mesh.vertices.double() <= corner[1] + 1e-6)).all()
    whole = read_mesh(run / "mesh.ply")
    assert len(mesh.faces) > 0 and spacing < float((hi - lo).max()) / 32  # finer cells over the smaller box
    assert len(mesh.faces) < 2 * len(whole.faces)


def test_export_refuses_what_it_cannot_do(run, tmp_path, capsys):
    assert main([str(tmp_path), "--quiet"]) == 1
    assert "checkpoints/last.pt" in capsys.readouterr().err
    assert main([str(run), "-o", str(tmp_path / "x.ply"), "--format", "obj", "--quiet"]) == 1
    assert "--format" in capsys.readouterr().err
    assert main([str(run), "--box", "0", "0", "0", "0", "1", "1", "--quiet"]) == 1
    assert "max above its min" in capsys.readouterr().err
    room = tmp_path / "room"
    (room / ".hydra").mkdir(parents=True)
    (room / ".hydra" / "config.yaml").write_text("model:\n  _target_: neuralsurf.rooms.RoomSettings\n")
    assert main([str(room), "--quiet"]) == 1
    assert "model=room_voxels" in capsys.readouterr().err


def test_export_of_an_evaluate_row_and_of_its_results_folder(tmp_path, capsys):
    from neuralsurf.cli import evaluate

    cfg = compose("evaluate", ["suite=tiny", "methods=[neural_sdf]", "method.neural_sdf.save_checkpoint=true",
                               "render=false"])
    cfg.run_dir = str(tmp_path)
    rows = evaluate(cfg)
    assert rows[0]["status"] == "ok"
    row_file = tmp_path / "rows" / "sphere__neural_sdf.json"
    assert "NaN" not in row_file.read_text() and strict_json(row_file)["row"]["scene"] == "sphere"
    assert strict_json(tmp_path / "results.json")["rows"][0]["method"] == "neural_sdf"
    fit = tmp_path / "fits" / "sphere__neural_sdf"
    assert main([str(tmp_path), "--quiet"]) == 1
    assert str(fit) in capsys.readouterr().err  # the results folder names its fitted rows
    assert main([str(fit), "--resolution", "20", "--format", "stl", "--quiet"]) == 0
    assert len(read_mesh(fit / "mesh_20.stl").faces) > 0


@pytest.mark.subprocess
@pytest.mark.slow
def test_console_script_and_python_dash_m(run, tmp_path):
    script = Path(sys.executable).parent / "neuralsurf-export"
    if not script.is_file():
        pytest.skip("the neuralsurf-export script is not installed in this environment: run ./install.sh again")
    done = subprocess.run([script, str(run), "-o", str(tmp_path / "a.off"), "--resolution", "16", "--quiet"],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0 and (tmp_path / "a.off").is_file(), done.stderr[-2000:]
    done = subprocess.run([sys.executable, "-m", "neuralsurf", "export", "--help"], capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0 and "--resolution" in done.stdout and "--box" in done.stdout


def test_a_room_is_meshed_near_its_input_and_an_object_everywhere():
    from neuralsurf.export import meshed_near_input

    rgbd = compose("train", ["~experiment", "data=rgbd", "data.path=x"])
    assert meshed_near_input(OmegaConf.to_container(rgbd.data), {})  # rgbd_scene's near_distance default: 5 cm
    assert not meshed_near_input({**OmegaConf.to_container(rgbd.data), "near_distance": None}, {})
    sphere = OmegaConf.to_container(compose("train", ["~experiment", "data=sphere"]).data)
    assert not meshed_near_input(sphere, {"resolution": 64})
    assert meshed_near_input(sphere, {"observed_voxel": 0.04})
    assert meshed_near_input(None, {"near_distance": 0.05})


def test_a_stored_scene_config_cannot_choose_code_to_run(tmp_path):
    """A run folder's scene config names data for a shipped recipe, never a function of its own choosing."""
    from neuralsurf.export import build_stored_scene, meshed_near_input

    marker = tmp_path / "ran"
    planted = {"_target_": "os.system", "command": f"touch {marker}"}
    with pytest.raises(ConfigError, match="not one of neuralsurf's scene recipes"):
        build_stored_scene(planted)
    nested = {"_target_": "neuralsurf.scenes.rgbd_scene", "path": {"_target_": "os.system", "command": f"touch {marker}"}}
    with pytest.raises(ConfigError, match="plain"):
        build_stored_scene(nested)
    assert not meshed_near_input({"_target_": "os.getcwd"}, {})
    assert not marker.exists()
