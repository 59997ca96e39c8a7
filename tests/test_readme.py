"""Every command in the README runs as written: each line of its ```bash blocks and each ```python
block, from a scratch folder that holds the files the README names (scan.ply, mesh.ply, gt.ply, an
RGB-D folder my_capture), with tiny settings appended to train.py and evaluate.py so that the whole
README runs in a few minutes. ```text blocks are not run."""

import multiprocessing
import os
import re
import runpy
import shlex
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from neuralsurf.data import locate

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
TEST_COMMAND = "./install.sh dev && .venv/bin/python -m pytest -q"
"""The README's test command: CI runs it (.ci/run), so this test checks it is there instead of running it."""

TINY_TRAIN = ["trainer.steps=2", "trainer.log_every=1", "trainer.image_every=0", "trainer.progress=false",
              "extract.resolution=32", "score.n_samples=5000"]
NEEDS_DATA = {"redkitchen": "7scenes_redkitchen", "7scenes_redkitchen": "7scenes_redkitchen",
              "stanford_scans": "stanford_bunny", "stanford_bunny": "stanford_bunny"}
"""Words of a command -> the data set it needs (skipped with the fetch command when neither
NEURALSURF_DATA nor the cache has it: the tests never download)."""
TINY_EVALUATE = ["suite=tiny", "render_size=64"]
"""Appended to evaluate.py commands: the command's own scenes=/methods= still win over the suite's."""
ENTRY_POINT = re.compile(r"(?:(?:\S*python3?\s+)?(train|evaluate)\.py|neuralsurf-(train|evaluate)|"
                         r"\S*python3?\s+-m\s+neuralsurf\s+(train|evaluate))(?=\s|$)")
"""A train.py / evaluate.py call in any of its spellings; its group names the config."""
SUITE_ONLY = re.compile(r"(python evaluate\.py|neuralsurf-evaluate|python -m neuralsurf evaluate) suite=(\w+)")
"""An evaluate.py command naming only a suite: the tiny settings would replace that suite (the run would be
the bare command's), so its composed config is checked instead (the suites run in test_evaluation)."""
SMALL_OBSERVATIONS = {
    "PointSamples": {"n_near": 20_000, "n_free": 5_000, "winding_points": 1_000},
    "DepthRays": {"max_rays": 200_000, "winding_points": 1_000, "denoise_k": 0},
    "CollectionSDF": {"shapes_per_batch": 6, "samples_per_shape": 256},
    "CollectionOccupancy": {"shapes_per_batch": 6, "query_points": 256, "cloud_points": 300},
}
"""Options of a tiny fit, by observation class (the presets build sample pools for thousands of steps;
the rays' denoising of every hit is left out)."""
SMALL_DATA = {"max_frames": 6, "n_train": 2, "n_test": 1, "n_sdf": 4_000, "n_occ": 4_000, "n_surface": 3_000,
              "mesh_resolution": 32}
"""Data options of a tiny fit, where the data config has them: a few frames of a capture, a few shapes
of a collection."""


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced code block of a Markdown text."""
    return [(m.group(1).strip(), m.group(2)) for m in re.finditer(r"^```(\w*)[^\n]*\n(.*?)^```", text, re.MULTILINE | re.DOTALL)]


def readme_commands() -> list[str]:
    """The lines of the README's bash blocks, without trailing comments; comment-only lines skipped."""
    commands = []
    for language, body in fenced_blocks(README.read_text()):
        if language in ("bash", "sh", "shell"):
            for line in body.splitlines():
                command = re.sub(r"(^|\s+)#.*$", "", line).strip()
                if command:
                    commands.append(command)
    return commands


def readme_python_blocks() -> list[str]:
    return [body for language, body in fenced_blocks(README.read_text()) if language == "python"]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """A scratch folder with the repository's entry points linked in and the user files the README names."""
    from neuralsurf.geometry import cloud_from_mesh
    from neuralsurf.io import write_mesh, write_point_cloud
    from neuralsurf.scenes import Sphere

    folder = tmp_path_factory.mktemp("readme")
    for name in ("train.py", "evaluate.py", "install.sh", ".venv", "pyproject.toml"):
        if (REPO / name).exists():
            (folder / name).symlink_to(REPO / name)
    sphere = Sphere(radius=0.3).mesh()
    write_mesh(folder / "gt.ply", sphere)
    write_mesh(folder / "mesh.ply", Sphere(radius=0.305).mesh())
    write_point_cloud(folder / "scan.ply", cloud_from_mesh(sphere, n=5000, noise=0.0, seed=0))
    write_capture(folder / "my_capture")
    write_frames_only_capture(folder / "my_frames")
    return folder


def write_frames_only_capture(folder: Path) -> None:
    """Depth and colour frames of a PrimeSense (640x480) without poses or intrinsics: livingroom1's images
    when NEURALSURF_DATA has them, else six synthetic views of a room (`test_tracking.write_frames_only`)."""
    real = Path(os.environ.get("NEURALSURF_DATA", "/nonexistent")) / "livingroom1_redwood"
    if real.is_dir():
        folder.mkdir()
        for name in ("depth", "image"):
            (folder / name).symlink_to(real / name)
        return
    from test_tracking import write_frames_only

    from neuralsurf.io.trajectories import sensor_intrinsics

    write_frames_only(folder, K=torch.from_numpy(sensor_intrinsics("kinect_v1")), width=640, height=480)


def write_capture(folder: Path) -> None:
    """An RGB-D folder in 7-Scenes layout: the real sample when NEURALSURF_DATA has it, else six depth
    views of a grey sphere (camera-intrinsics.txt beside frames/frame-XXXXXX.{color.png,depth.png,pose.txt})."""
    real = Path(os.environ.get("NEURALSURF_DATA", "/nonexistent")) / "7scenes_redkitchen_every10"
    if real.is_dir():
        folder.symlink_to(real)
        return
    from PIL import Image

    from neuralsurf.scenes import Sphere, scan_depth

    frames = scan_depth(Sphere(radius=0.3).mesh(), n_views=6, width=64, height=48)
    (folder / "frames").mkdir(parents=True)
    np.savetxt(folder / "camera-intrinsics.txt", frames.K[0].cpu().numpy())
    for i in range(len(frames)):
        millimetres = (frames.depth[i].cpu().numpy() * 1000).round().astype(np.uint16)
        Image.fromarray(millimetres).save(folder / "frames" / f"frame-{i:06d}.depth.png")
        grey = np.full((*millimetres.shape, 3), 128, np.uint8)
        Image.fromarray(grey).save(folder / "frames" / f"frame-{i:06d}.color.png")
        np.savetxt(folder / "frames" / f"frame-{i:06d}.pose.txt", frames.cam_to_world[i].cpu().numpy())


def composed(call: str) -> dict:
    """The job config a train.py or evaluate.py call composes (what its `--cfg job` prints), composed in this
    process: a subprocess would spend seconds importing the package to run nothing."""
    match = ENTRY_POINT.search(call)
    assert match, f"not a train.py or evaluate.py call: {call}"
    config = next(group for group in match.groups() if group)
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base="1.3"):
        return OmegaConf.to_container(compose(config, shlex.split(call[match.end():])))


def tiny_overrides(call: str) -> list[str]:
    """Overrides that shrink what a train.py call prepares (its observations' pools, its data, a refined
    model's start, the prior's scoring), read from its composed config."""
    cfg = composed(call)
    overrides = [f"observation.{name}.{key}={value}" for name, options in (cfg.get("observation") or {}).items()
                 for kind, small in SMALL_OBSERVATIONS.items() if f".{kind}." in options.get("_target_", "")
                 for key, value in small.items() if key in options]
    overrides += [f"data.{key}={value}" for key, value in SMALL_DATA.items() if key in cfg["data"]]
    overrides += ["model.start_resolution=32"] if "start_resolution" in cfg["model"] else []
    return overrides + (["score.latent_steps=5"] if "latent_steps" in (cfg.get("score") or {}) else [])


def with_tiny_settings(command: str, pools: bool = False) -> str:
    """`command` with tiny settings appended to each train.py / evaluate.py call in it (with `pools`, the
    train.py calls' sample pools and data shrunk too)."""
    def shrink(call: str) -> str:
        if re.search(r"(train\.py|neuralsurf-train|-m neuralsurf train)(\s|$)", call):
            extra = TINY_TRAIN + (tiny_overrides(call) if pools else [])
        elif re.search(r"(evaluate\.py|neuralsurf-evaluate|-m neuralsurf evaluate)(\s|$)", call):
            extra = TINY_EVALUATE
        elif re.search(r"(neuralsurf-export|-m neuralsurf export)(\s|$)", call):
            return re.sub(r"--resolution \d+", "--resolution 32", call)
        else:
            return call
        return f"{call.rstrip()} {' '.join(extra)}"

    return " && ".join(shrink(call) for call in command.split("&&"))


PYTHON_SCRIPT = re.compile(r"(?:\S*/)?python3?\s+(?P<script>[\w./-]+\.py)(?P<arguments>(?:\s+[^&|;<>$`]*)?)")
"""A command that is one `python SCRIPT.py ARGS` call (no shell operators): `run` starts it from a Python that has
imported the package already."""
PRELOADED = multiprocessing.get_context("forkserver")
PRELOADED.set_forkserver_preload(["neuralsurf.cli"])
"""Processes forked from a server that imported neuralsurf (torch, Open3D, Hydra) once, untouched by any test:
each README call saves the seconds of those imports, and runs as `python SCRIPT.py ARGS` would."""


def run_script(script: str, arguments: list[str], cwd: str, env: dict, stdout: str, stderr: str) -> None:
    """`python script arguments` in this process (a fork of `PRELOADED`'s server), its output to two files."""
    for fd, name in ((1, stdout), (2, stderr)):
        with open(name, "w") as file:
            os.dup2(file.fileno(), fd)
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    sys.argv = [script, *arguments]
    sys.path.insert(0, str(Path(script).resolve().parent))
    runpy.run_path(script, run_name="__main__")


def run(command: str, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    """`command` run by bash in `cwd` (a `PYTHON_SCRIPT` call: by a preloaded Python) with the venv first on PATH,
    progress bars off and the data cache in `cwd`."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "NEURALSURF_PROGRESS": "0", "NEURALSURF_CACHE": str(cwd / "cache")}
    env.pop("VIRTUAL_ENV", None)
    call = PYTHON_SCRIPT.fullmatch(command.strip())
    if call is None:
        return subprocess.run(["bash", "-c", command], cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=timeout, check=False)
    outputs = [cwd / f".{name}-{os.getpid()}.txt" for name in ("stdout", "stderr")]
    process = PRELOADED.Process(target=run_script, args=(call["script"], shlex.split(call["arguments"]), str(cwd),
                                                         env, *map(str, outputs)))
    process.start()
    process.join(timeout)
    if process.is_alive():
        process.kill()
        process.join()
    stdout, stderr = (path.read_text(errors="replace") for path in outputs)
    return subprocess.CompletedProcess(command, process.exitcode, stdout, stderr)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serves(command: str, cwd: Path, seconds: float = 120) -> None:
    """Start a server command (tensorboard, neuralsurf-view) on a free local port and check it answers HTTP,
    then stop it."""
    port = free_port()
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    process = subprocess.Popen(shlex.split(command) + ["--host", "127.0.0.1", "--port", str(port)], cwd=cwd,
                               env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            assert process.poll() is None, f"{command} exited: {process.stderr.read()[-2000:]}"
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as response:
                    assert response.status == 200
                    return
            except OSError:
                time.sleep(1)
        pytest.fail(f"{command} did not answer on port {port} within {seconds} s")
    finally:
        process.terminate()
        process.wait(timeout=30)


def test_the_readme_has_the_two_set_up_commands_and_ci_runs_the_test_command():
    commands = readme_commands()
    assert commands[0] == "./install.sh && .venv/bin/python train.py experiment=bunny_sdf"
    assert commands[1] == TEST_COMMAND
    assert re.search(rf"^{re.escape(TEST_COMMAND)}$", (REPO / ".ci" / "run").read_text(), re.MULTILINE)
    assert len(README.read_text().splitlines()) <= 260


@pytest.mark.subprocess
@pytest.mark.parametrize("command", [c for c in readme_commands() if c != TEST_COMMAND])
def test_readme_command_runs(command, workspace):
    if command.startswith("./install.sh") and Path(sys.prefix).resolve() != (REPO / ".venv").resolve():
        pytest.skip("the set-up command installs into .venv; these tests run in another environment")
    missing = [name for word, name in NEEDS_DATA.items() if word in command and locate(name) is None]
    if missing:
        pytest.skip(f"needs the {missing[0]} data set: python -m neuralsurf data fetch {missing[0]}, or set "
                    f"NEURALSURF_DATA")
    if command.split()[0] == "neuralsurf-view":
        pytest.importorskip("viser", reason="the view extra is not installed: pip install -e '.[view]'")
        if not (Path(sys.executable).parent / "neuralsurf-view").is_file():
            pytest.skip("the neuralsurf-view script is not installed in this environment: run ./install.sh again")
    if command.split()[0] == "neuralsurf-export":
        if not (Path(sys.executable).parent / "neuralsurf-export").is_file():
            pytest.skip("the neuralsurf-export script is not installed in this environment: run ./install.sh again")
        run_dir = workspace / command.split()[1]
        if not (run_dir / "checkpoints" / "last.pt").is_file():  # the README's run before it was left out
            done = run(with_tiny_settings(f"python train.py experiment=sphere_sdf hydra.run.dir={run_dir}"), workspace)
            assert done.returncode == 0, done.stderr[-3000:]
    if command.split()[0] in ("tensorboard", "neuralsurf-view"):
        serves(command, workspace)
        return
    if SUITE_ONLY.fullmatch(command):
        cfg = composed(command)
        assert cfg["scenes"] and set(cfg["scenes"]) <= set(cfg["scene"]) and set(cfg["methods"]) <= set(cfg["method"])
        return
    done = run(with_tiny_settings(command, pools=True), workspace)
    assert done.returncode == 0, f"{command}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"


@pytest.mark.subprocess
@pytest.mark.parametrize("index", range(len(readme_python_blocks())))
def test_readme_python_block_runs(index, workspace):
    script = workspace / f"readme_block_{index}.py"
    script.write_text(readme_python_blocks()[index])
    done = run(f"{shlex.quote(sys.executable)} {script.name}", workspace)
    assert done.returncode == 0, f"{script.read_text()}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"


def test_tiny_settings_go_after_every_train_and_evaluate_call():
    command = with_tiny_settings("./install.sh && .venv/bin/python train.py experiment=bunny_sdf")
    assert command.endswith("experiment=bunny_sdf " + " ".join(TINY_TRAIN))
    assert with_tiny_settings("python evaluate.py suite=depth").endswith("suite=depth suite=tiny render_size=64")
    assert with_tiny_settings("neuralsurf-score mesh.ply gt.ply") == "neuralsurf-score mesh.ply gt.ply"
    assert with_tiny_settings("neuralsurf-export run --resolution 512 --format glb") == \
        "neuralsurf-export run --resolution 32 --format glb"


def test_tiny_overrides_follow_the_composed_config():
    room = tiny_overrides("python train.py experiment=room data.path=my_capture")
    assert "data.max_frames=6" in room and "observation.rays.denoise_k=0" in room
    assert not any(o.startswith("observation.points.") for o in room)  # the rays alone: what the room selects
    assert "observation.points.n_near=20000" in tiny_overrides("python train.py experiment=bunny_sdf")
    assert "data.n_train=2" in tiny_overrides("python train.py experiment=shapes_deepsdf")
