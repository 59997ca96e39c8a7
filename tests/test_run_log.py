"""What a user sees of a train.py run: progress, warnings and errors in train.log, and a neuralsurf error
as one clear line instead of Hydra's wrapped traceback."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def train(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "train.py", *overrides, f"hydra.run.dir={run_dir}", "trainer.progress=false",
               "device=cpu"]
    return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300, check=False)


@pytest.mark.subprocess
@pytest.mark.slow
def test_train_log_holds_a_progress_line_per_tenth_of_the_steps_and_the_warnings(tmp_path):
    overrides = ("experiment=sphere_sdf", "trainer.steps=40", "trainer.log_every=2", "extract.resolution=32",
                 "trainer.image_every=0")
    done = train(tmp_path, *overrides)
    assert done.returncode == 0, done.stderr[-3000:]
    log = (tmp_path / "train.log").read_text()
    steps = [int(s) for s in re.findall(r"step (\d+)/40 \(\d+%\): loss [-+.\de]+ \(.*\), lr [-+.\de]+, [.\d]+ steps/s", log)]
    assert steps[-1] == 40 and all(any(tenth * 4 < s <= (tenth + 1) * 4 for s in steps) for tenth in range(10))
    again = train(tmp_path, *overrides)  # a finished run resumed: its warning reaches the log
    assert again.returncode == 0, again.stderr[-3000:]
    assert "already holds 40 >= 40 steps; nothing to train" in (tmp_path / "train.log").read_text()


@pytest.mark.subprocess
def test_a_missing_key_or_file_is_one_clear_line_in_the_console_and_the_log(tmp_path):
    done = train(tmp_path / "no_path", "data=file")
    assert done.returncode == 1
    output = done.stdout + done.stderr
    assert "ConfigError: data.path is required: add data.path=<value>" in output
    assert "Traceback" not in output and "HYDRA_FULL_ERROR" not in output
    assert "data.path is required" in (tmp_path / "no_path" / "train.log").read_text()

    done = train(tmp_path / "missing", "data=file", "data.path=missing.ply")
    output = done.stdout + done.stderr
    assert done.returncode == 1 and "point cloud file not found: 'missing.ply'" in output
    assert "Error in call to target" not in output and "Traceback" not in output
