"""The installed package: console scripts, `python -m neuralsurf`, configs shipped inside the package."""

import json
import math
import subprocess
import sys
import venv
from pathlib import Path

import pytest
import torch

from neuralsurf.cli import score_main
from neuralsurf.io import write_mesh
from neuralsurf.scenes import Sphere

REPO = Path(__file__).resolve().parents[1]


def test_score_compares_two_mesh_files_and_exits_0(tmp_path, capsys):
    write_mesh(tmp_path / "gt.ply", Sphere(radius=1.0).mesh())
    write_mesh(tmp_path / "pred.ply", Sphere(radius=1.02).mesh())
    assert score_main([str(tmp_path / "pred.ply"), str(tmp_path / "gt.ply"), "--samples", "2000", "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["chamfer_l1_exact"] == pytest.approx(0.02 / 2, rel=0.05)  # gap / diameter
    assert score_main([str(tmp_path / "missing.ply"), str(tmp_path / "gt.ply")]) == 1
    assert "missing.ply" in capsys.readouterr().err


@pytest.mark.subprocess
@pytest.mark.slow
def test_score_console_script_exits_0_and_its_help_is_whole(tmp_path):
    write_mesh(tmp_path / "a.ply", Sphere(radius=1.0).mesh())
    score = Path(sys.executable).parent / "neuralsurf-score"
    done = subprocess.run([score, "a.ply", "a.ply", "--samples", "1000"], cwd=tmp_path, capture_output=True,
                          text=True, check=False)
    assert done.returncode == 0 and "chamfer_l1_exact" in done.stdout, done.stderr[-2000:]
    done = subprocess.run([sys.executable, "-m", "neuralsurf", "score", "a.ply", "a.ply", "--samples", "1000"],
                          cwd=tmp_path, capture_output=True, text=True, check=False)
    assert done.returncode == 0 and "chamfer_l1_exact" in done.stdout, done.stderr[-2000:]
    help_text = subprocess.run([score, "--help"], capture_output=True, text=True, check=True).stdout
    assert "longest side 1." in help_text and "--samples" in help_text and "--json" in help_text


@pytest.mark.subprocess
def test_python_dash_m_names_its_commands():
    done = subprocess.run([sys.executable, "-m", "neuralsurf"], capture_output=True, text=True, cwd=REPO, check=False)
    assert done.returncode != 0 and "train,evaluate,score" in done.stderr


@pytest.mark.subprocess
@pytest.mark.slow
def test_pip_install_then_train_from_an_empty_folder(tmp_path):
    """`pip install .` (not editable) into a fresh virtual environment (dependencies from this one), then
    neuralsurf-train from an empty folder: the configs come from the installed package."""
    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=True)
    python = env_dir / "bin" / "python"
    subprocess.run([python, "-m", "pip", "install", "-q", "--no-deps", str(REPO)], check=True, timeout=600)
    where = subprocess.run([python, "-c", "import neuralsurf; print(neuralsurf.__file__)"], capture_output=True,
                           text=True, check=True, cwd=tmp_path).stdout
    assert str(env_dir) in where  # the installed copy, not the checkout
    folder = tmp_path / "empty"
    folder.mkdir()
    done = subprocess.run([env_dir / "bin" / "neuralsurf-train", "experiment=bunny_sdf", "trainer.steps=5",
                           "model.start_resolution=32", "extract.resolution=32", "trainer.progress=false", "device=cpu"],
                          cwd=folder, capture_output=True, text=True, timeout=900, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = list(folder.glob("outputs/bunny_sdf/bunny/*/metrics.json"))
    assert len(metrics) == 1 and json.loads(metrics[0].read_text())["steps"] == 5


def test_one_version_everywhere_and_a_public_api():
    import importlib.metadata

    import neuralsurf

    assert importlib.metadata.version("neuralsurf") == neuralsurf.__version__
    assert f"\nversion: {neuralsurf.__version__}\n" in (REPO / "CITATION.cff").read_text()
    assert f"\n## {neuralsurf.__version__}\n" in (REPO / "CHANGELOG.md").read_text()
    assert all(hasattr(neuralsurf, name) for name in neuralsurf.__all__)
    assert (Path(neuralsurf.__file__).parent / "py.typed").is_file()


def test_score_warns_when_the_meshes_barely_overlap_and_align_moves_pred_onto_gt(tmp_path, capsys):
    from neuralsurf.scenes.analytic import Box
    from neuralsurf.structures import Mesh

    gt = Box(half_extents=(0.3, 0.2, 0.25)).mesh()
    angle = math.radians(8.0)
    rotation = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    moved = Mesh(gt.vertices @ rotation.T.to(gt.vertices) + torch.tensor([2.0, 1.0, 0.0]).to(gt.vertices), gt.faces)
    write_mesh(tmp_path / "gt.ply", gt)
    write_mesh(tmp_path / "pred.ply", moved)
    files = [str(tmp_path / "pred.ply"), str(tmp_path / "gt.ply"), "--samples", "5000", "--json"]
    assert score_main(files) == 0
    out, err = capsys.readouterr()
    assert "overlap by only 0%" in err and "--align" in err and json.loads(out)["fscore_1%"] == 0
    assert score_main([*files, "--align"]) == 0
    out, err = capsys.readouterr()
    assert "overlap by only" not in err and "aligned" in err
    assert json.loads(out)["chamfer_l1_exact"] < 1e-3  # fractions of the box's longest side


@pytest.mark.subprocess
def test_python_dash_m_help_exits_0():
    done = subprocess.run([sys.executable, "-m", "neuralsurf", "--help"], capture_output=True, text=True, cwd=REPO,
                          check=False)
    assert done.returncode == 0 and "export" in done.stdout and "train,evaluate,score" in done.stdout


def test_a_mistyped_config_group_is_answered_with_the_groups(monkeypatch):
    from neuralsurf.cli import check_override_keys

    with pytest.raises(SystemExit) as exit_:
        check_override_keys(["dat=file", "data.path=scan.ply"], "train")
    message = str(exit_.value.code)
    assert "'dat' is not a config group or option" in message
    groups = message.split("Config groups: ")[1].split(";")[0].split(", ")
    assert set(groups) == {"observation", "data", "model", "optimizer", "trainer", "extract", "experiment"}
    check_override_keys(["experiment=shapes_deepsdf", "score.latent_steps=5", "data.path=x", "+extra=1", "-m",
                         "hydra.run.dir=out", "hydra/launcher=joblib", "seed=1", "observation.rays.n_rays=8"], "train")
    check_override_keys(["suite=quick", "methods=[tsdf]", "method.tsdf.device=cpu", "results_dir=x"], "evaluate")
    # a key that a suite adds through its defaults (suite=priors_folder: `/data@folder`)
    check_override_keys(["suite=priors_folder", "folder.source=shapes", "folder.n_test=5"], "evaluate")
    with pytest.raises(SystemExit, match="'suit' is not a config group or option.*suite"):
        check_override_keys(["suit=quick"], "evaluate")


def test_install_sh_names_its_choices_for_an_unknown_argument():
    done = subprocess.run(["bash", str(REPO / "install.sh"), "--lean"], capture_output=True, text=True, check=False)
    assert done.returncode == 1 and "./install.sh lean" in done.stderr and "./install.sh dev" in done.stderr


def test_the_bunny_without_pymeshlab_says_how_to_add_it(monkeypatch):
    import importlib

    from neuralsurf.errors import MissingDependencyError

    bunny = importlib.import_module("neuralsurf.scenes.bunny")

    monkeypatch.setattr(bunny, "find_spec", lambda name: None)
    with pytest.raises(MissingDependencyError, match=r"pip install -e '\.\[data\]' in a clone"):
        bunny.bunny_path()


def test_every_imported_package_is_declared():
    import importlib.metadata
    import re

    declared = {re.split(r"[<>=\[ ]", requirement)[0].lower().replace("_", "-")
                for requirement in importlib.metadata.requires("neuralsurf") or []}
    imported = set()
    for path in (REPO / "neuralsurf").rglob("*.py"):
        imported |= set(re.findall(r"^\s*(?:import|from) ([a-zA-Z_]\w*)", path.read_text(), re.MULTILINE))
    distributions = importlib.metadata.packages_distributions()
    third_party = {name for name in imported if name in distributions and name != "neuralsurf"}
    undeclared = {name for name in third_party
                  if not {d.lower().replace("_", "-") for d in distributions[name]} & declared}
    assert not undeclared, f"imported but not declared in pyproject.toml: {sorted(undeclared)}"
