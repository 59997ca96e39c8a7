"""Progress bars on the steps a user waits on: shown (here with no delay) when progress=True, silent
with progress=False or NEURALSURF_PROGRESS=0 (the suite's default, set in conftest.py)."""

import warnings

import numpy as np
import pytest
import torch

import neuralsurf.progress
from neuralsurf.baselines import TSDFVolume
from neuralsurf.baselines.registration import register_multiway
from neuralsurf.extract import extract_mesh
from neuralsurf.io import read_range_scan_frames, read_range_scans, read_rgbd_folder
from neuralsurf.structures import DepthFrames, PointCloud


@pytest.fixture
def bars_visible(monkeypatch):
    """Bars appear at once and the suite's NEURALSURF_PROGRESS=0 is lifted, for this test only."""
    monkeypatch.setattr(neuralsurf.progress, "DELAY_S", 0.0)
    monkeypatch.delenv("NEURALSURF_PROGRESS", raising=False)


def wall_frames(n=3) -> DepthFrames:
    K = torch.tensor([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
    return DepthFrames(torch.full((n, 48, 64), 1.0), K, torch.eye(4).expand(n, 4, 4))


def sphere(x):
    return x.norm(dim=-1) - 0.3


def shifted_clouds() -> list[PointCloud]:
    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g, dtype=torch.float64), dim=1)
    base = base * torch.tensor([1.0, 0.7, 0.5], dtype=torch.float64)
    return [PointCloud(base + 0.002 * k) for k in range(3)]


def write_scan_folder(root):
    """Two tiny ASCII range-grid scans (a tilted plane) and their .conf."""
    rows, cols = 5, 6
    points = [(0.001 * c, -0.001 * r, 0.0005 * c) for r in range(rows) for c in range(cols)]
    lines = ["ply", "format ascii 1.0", f"obj_info num_cols {cols}", f"obj_info num_rows {rows}",
             f"element vertex {len(points)}", "property float x", "property float y", "property float z",
             f"element range_grid {rows * cols}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(f"{v:.7g}" for v in p) for p in points] + [f"1 {i}" for i in range(rows * cols)]
    for name in ("a.ply", "b.ply"):
        (root / name).write_text("\n".join(lines) + "\n")
    (root / "scans.conf").write_text("bmesh a.ply 0 0 0 0 0 0 1\nbmesh b.ply 0.001 0 0 0 0 0 1\n")
    return root / "scans.conf"


def write_7scenes(root, n=2):
    from PIL import Image

    frames = root / "frames"
    frames.mkdir(parents=True)
    for i in range(n):
        Image.fromarray(np.full((48, 64), 1500, dtype=np.uint16)).save(frames / f"frame-{i:06d}.depth.png")
        np.savetxt(frames / f"frame-{i:06d}.pose.txt", np.eye(4))
    np.savetxt(root / "camera-intrinsics.txt", [[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    return root


STEPS = {
    "TSDF fusion": lambda tmp: TSDFVolume([[-0.3, -0.3, 0.8], [0.3, 0.3, 1.2]], 0.02, device="cpu").integrate(
        wall_frames(), **tmp["kw"]
    ),
    "multiway ICP": lambda tmp: register_multiway(shifted_clouds(), 0.05, method="point_to_point", **tmp["kw"]),
    "RGB-D": lambda tmp: read_rgbd_folder(write_7scenes(tmp["dir"]), with_color=False, **tmp["kw"]),
    "range scans": lambda tmp: read_range_scans(write_scan_folder(tmp["dir"]), **tmp["kw"]),
    "range scans ": lambda tmp: read_range_scan_frames(write_scan_folder(tmp["dir"]), 1e-4, **tmp["kw"]),
    "extract": lambda tmp: extract_mesh(sphere, 32, bounds=[[-0.5] * 3, [0.5] * 3], chunk_size=1000, **tmp["kw"]),
}


@pytest.mark.parametrize("name", list(STEPS))
def test_bar_shown_when_asked_and_silent_when_not(name, tmp_path, capsys, bars_visible, monkeypatch):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        (tmp_path / "on").mkdir()
        STEPS[name]({"dir": tmp_path / "on", "kw": {}})  # progress=True is the default
        shown = capsys.readouterr().err
        (tmp_path / "off").mkdir()
        STEPS[name]({"dir": tmp_path / "off", "kw": {"progress": False}})
        silent = capsys.readouterr().err
        monkeypatch.setenv("NEURALSURF_PROGRESS", "0")
        (tmp_path / "env").mkdir()
        STEPS[name]({"dir": tmp_path / "env", "kw": {}})
        silenced_by_env = capsys.readouterr().err
    assert name.strip() in shown, shown
    assert silent == "" and silenced_by_env == ""


def test_short_steps_stay_silent_by_default(tmp_path, capsys, monkeypatch):
    """With the real 2 s delay, a step of a fraction of a second prints nothing even when enabled."""
    monkeypatch.delenv("NEURALSURF_PROGRESS", raising=False)
    assert neuralsurf.progress.DELAY_S == 2.0
    TSDFVolume([[-0.3, -0.3, 0.8], [0.3, 0.3, 1.2]], 0.02, device="cpu").integrate(wall_frames())
    assert capsys.readouterr().err == ""
