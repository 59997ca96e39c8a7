"""Hydra multirun over a learned prior's settings: one run directory per job."""

import subprocess
import sys
from pathlib import Path

import pytest

from neuralsurf.checkpoints import load_checkpoint

REPO = Path(__file__).resolve().parents[1]
TINY = ["trainer.steps=4", "trainer.progress=false", "trainer.checkpoint_every=4", "device=cpu",
        "data.classes=[lamp]", "data.n_train=2", "data.n_test=1", "data.n_sdf=2000", "data.n_occ=500",
        "data.n_surface=3000", "data.mesh_resolution=32", "data.workers=0", "observation.shapes.shapes_per_batch=2",
        "observation.shapes.samples_per_shape=64", "score.n_points=500", "score.latent_steps=2", "extract.resolution=32"]


@pytest.mark.subprocess
@pytest.mark.slow
def test_multirun_gives_one_run_directory_per_job(tmp_path):
    sweep = tmp_path / "sweep"
    command = [sys.executable, "train.py", "-m", "experiment=shapes_deepsdf_tiny", "model.latent_dim=8,16",
               f"hydra.sweep.dir={sweep}", f"data.root={tmp_path / 'shapes'}", *TINY]
    done = subprocess.run(command, check=False, cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={"NEURALSURF_PROGRESS": "0", "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin",
                               "HOME": str(tmp_path)})
    assert done.returncode == 0, done.stderr[-3000:]
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in jobs] == ["0", "1"]
    for job, latent_dim in zip(jobs, (8, 16)):
        assert f"model.latent_dim={latent_dim}" in (job / ".hydra" / "overrides.yaml").read_text()
        assert (job / "metrics.json").is_file() and (job / "mesh.ply").is_file() and (job / "train.log").is_file()
        state = load_checkpoint(job / "checkpoints" / "last.pt")
        assert state["step"] == 4 and state["model"]["codes.weight"].shape == (2, latent_dim)
        assert (job / "interpolation.png").is_file()  # the shapes between the two training codes
        assert state["config"]["model"]["latent_dim"] == latent_dim
