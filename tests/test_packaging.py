"""The installed package: console scripts, `python -m neuralsurf`, configs shipped inside the package."""

import json
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from neuralsurf.cli import score_main
from neuralsurf.io import write_mesh
from neuralsurf.scenes import Sphere

REPO = Path(__file__).resolve().parents[1]


def test_score_compares_two_mesh_files(tmp_path, capsys):
    write_mesh(tmp_path / "gt.ply", Sphere(radius=1.0).mesh())
    write_mesh(tmp_path / "pred.ply", Sphere(radius=1.02).mesh())
    metrics = score_main([str(tmp_path / "pred.ply"), str(tmp_path / "gt.ply"), "--samples", "2000", "--json"])
    assert json.loads(capsys.readouterr().out)["chamfer_l1_exact"] == pytest.approx(metrics["chamfer_l1_exact"])
    assert metrics["chamfer_l1_exact"] == pytest.approx(0.02 / 2, rel=0.05)  # gap / diameter


def test_python_dash_m_names_its_commands():
    done = subprocess.run([sys.executable, "-m", "neuralsurf"], capture_output=True, text=True, cwd=REPO, check=False)
    assert done.returncode != 0 and "train,evaluate,score" in done.stderr


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
                           "extract.resolution=32", "trainer.progress=false", "device=cpu"],
                          cwd=folder, capture_output=True, text=True, timeout=900, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = list(folder.glob("outputs/bunny_sdf/bunny/*/metrics.json"))
    assert len(metrics) == 1 and json.loads(metrics[0].read_text())["steps"] == 5
