"""neuralsurf.data: local copies first, then downloads from a local HTTP server (never the network):
checksums of the archive and of the unpacked files (the manifest), resuming with an HTTP Range request,
unpacking into the layout the tests use, `python -m neuralsurf data`, and scenes that find fetched data."""

import hashlib
import http.server
import io
import os
import subprocess
import sys
import tarfile
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from neuralsurf import data
from neuralsurf.errors import ConfigError, DownloadError, FileFormatError
from neuralsurf.scenes import recipes

REPO = Path(__file__).resolve().parents[1]
PAYLOAD = bytes(range(256)) * 4096  # 1 MiB
SHA = hashlib.sha256(PAYLOAD).hexdigest()


class Server:
    """A file server on 127.0.0.1 that honours Range requests and can drop the connection after `cut`
    bytes; it shuts itself down after `lifetime_s` seconds if `close` is never called."""

    def __init__(self, files: dict[str, bytes], lifetime_s: float = 120.0):
        self.files, self.cut, self.ranges = files, None, []
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                body = server.files.get(self.path)
                if body is None:
                    self.send_error(404)
                    return
                start = 0
                if "Range" in self.headers:
                    server.ranges.append(self.headers["Range"])
                    start = int(self.headers["Range"].split("=")[1].split("-")[0])
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
                else:
                    self.send_response(200)
                self.send_header("Content-Length", str(len(body) - start))
                self.end_headers()
                if server.cut is not None:
                    self.wfile.write(body[start : start + server.cut])
                    server.cut = None
                    self.close_connection = True
                    return
                self.wfile.write(body[start:])

            def log_message(self, *args):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.timeout = 10
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.deadline = threading.Timer(lifetime_s, self.httpd.shutdown)
        self.deadline.daemon = True
        self.deadline.start()

    def close(self):
        self.deadline.cancel()
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server():
    server = Server({"/file.bin": PAYLOAD})
    yield server
    server.close()


def test_download_checks_the_sha256(tmp_path, server):
    path = data.download(f"{server.url}/file.bin", tmp_path / "file.bin", SHA, progress=False)
    assert path.read_bytes() == PAYLOAD and server.ranges == []


def test_checksum_mismatch_is_a_clear_error_and_leaves_no_file(tmp_path, server):
    with pytest.raises(DownloadError, match=f"has sha256 {SHA}, expected {'0' * 64}.*deleted"):
        data.download(f"{server.url}/file.bin", tmp_path / "file.bin", "0" * 64, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_an_interrupted_download_resumes_with_a_range_request(tmp_path, server):
    server.cut = 300_000
    with pytest.raises(DownloadError, match="interrupted after 300000 .*run again to resume"):
        data.download(f"{server.url}/file.bin", tmp_path / "file.bin", SHA, progress=False)
    assert (tmp_path / "file.bin.part").stat().st_size == 300_000 and not (tmp_path / "file.bin").exists()
    path = data.download(f"{server.url}/file.bin", tmp_path / "file.bin", SHA, progress=False)
    assert server.ranges == ["bytes=300000-"]  # only the rest was asked for
    assert path.read_bytes() == PAYLOAD and list(tmp_path.iterdir()) == [path]


def test_no_checksum_warns_that_the_file_is_not_verified(tmp_path, server):
    with pytest.warns(UserWarning, match="checksum of .* is not verified"):
        data.download(f"{server.url}/file.bin", tmp_path / "file.bin", None, progress=False)


def test_unreachable_server_and_missing_file_are_download_errors(tmp_path, server):
    with pytest.raises(DownloadError, match="HTTP 404"):
        data.download(f"{server.url}/absent.bin", tmp_path / "absent.bin", progress=False)
    with pytest.raises(DownloadError, match="failed.*NEURALSURF_DATA"):
        data.download("http://127.0.0.1:9/nothing", tmp_path / "nothing", progress=False, timeout=5)


# ----------------------------------------------------------------------------------------------
# archives in the upstream layouts, built here from small fixture files


def _sha(content: bytes) -> str:
    return hashlib.sha256(content).hexdigest()


def _bunny_files() -> dict[str, bytes]:
    """What Stanford's archive unpacks to (a small stand-in), by path under stanford_bunny/."""
    ply = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n" \
          b"end_header\n0 0 0\n"
    return {"data/bun.conf": b"camera 0 0 0 0 0 0 1\nbmesh bun000.ply 0 0 0 0 0 0 1\n", "data/bun000.ply": ply,
            "data/README": b"Range Data\n", "reconstruction/bun_zipper.ply": ply,
            "reconstruction/README": b"Surface Reconstructions\n"}  # fmt: skip


def _bunny_tarball(files: dict[str, bytes]) -> bytes:
    """bunny.tar.gz: `files` under bunny/, plus a file outside data/ and reconstruction/ (not unpacked)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, content in {**{f"bunny/{k}": v for k, v in files.items()}, "bunny/README": b"elsewhere"}.items():
            info = tarfile.TarInfo(name)
            info.size = len(content)
            tar.addfile(info, io.BytesIO(content))
    return buffer.getvalue()


def _pose(i: int) -> np.ndarray:
    """A camera-to-world matrix of frame `i`, 4 x 4 float64 with values of 8 significant digits."""
    pose = np.eye(4)
    pose[:3, 3] = [0.1234567 * i, -0.3404563, 2.9656917e-3 * i]
    pose[0, 1], pose[1, 0] = 0.27262229, -0.27248618
    return pose


def _upstream_pose_text(pose: np.ndarray) -> str:
    """A pose as 7-Scenes writes it: %.7e with three-digit exponents, tab-separated, a tab before each newline."""
    def number(value):
        mantissa, exponent = f"{value:.7e}".split("e")
        return f"{mantissa}e{exponent[0]}{int(exponent[1:]):03d}"
    return "".join("\t".join(number(v) for v in row) + "\t\n" for row in pose)


def _savetxt(matrix: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.savetxt(buffer, matrix)
    return buffer.getvalue()


def _redkitchen_files(n: int = 25) -> dict[str, bytes]:
    """seq-01.zip's frames 0 .. n-1 in the upstream layout, by name in that zip."""
    files = {}
    for i in range(n):
        files[f"seq-01/frame-{i:06d}.color.png"] = b"\x89PNG colour %d" % i
        files[f"seq-01/frame-{i:06d}.depth.png"] = b"\x89PNG depth %d" % i
        files[f"seq-01/frame-{i:06d}.pose.txt"] = _upstream_pose_text(_pose(i)).encode()
    return files


def _redkitchen_zip(files: dict[str, bytes]) -> bytes:
    """redkitchen.zip: one inner zip per sequence, seq-01.zip holding `files`."""
    inner = io.BytesIO()
    with zipfile.ZipFile(inner, "w") as seq:
        for name, content in files.items():
            seq.writestr(name, content)
    outer = io.BytesIO()
    with zipfile.ZipFile(outer, "w") as kitchen:
        kitchen.writestr("redkitchen/seq-01.zip", inner.getvalue())
        kitchen.writestr("redkitchen/seq-02.zip", b"not read")
    return outer.getvalue()


K_TEXT = (b"5.850000000000000000e+02 0.000000000000000000e+00 3.200000000000000000e+02\n"
          b"0.000000000000000000e+00 5.850000000000000000e+02 2.400000000000000000e+02\n"
          b"0.000000000000000000e+00 0.000000000000000000e+00 1.000000000000000000e+00\n")  # fmt: skip
"""camera-intrinsics.txt as the unpacker writes it (numpy.savetxt of the 3 x 3 K)."""


def _redkitchen_manifest(n: int = 25) -> dict[str, str]:
    """The manifest of `_redkitchen_files(n)` unpacked: the intrinsics and every 10th pose, as numpy.savetxt
    writes them."""
    manifest = {"camera-intrinsics.txt": _sha(K_TEXT)}
    for i in range(0, n, 10):
        manifest[f"frames/frame-{i:06d}.pose.txt"] = _sha(_savetxt(_pose(i)))
    return manifest


def _archive_and_manifest(name: str) -> tuple[bytes, dict[str, str]]:
    """A good archive of data set `name` in its upstream layout, and the manifest of what it unpacks to."""
    if name == "stanford_bunny":
        return _bunny_tarball(_bunny_files()), {k: _sha(v) for k, v in _bunny_files().items()}
    return _redkitchen_zip(_redkitchen_files()), _redkitchen_manifest()


@pytest.fixture
def registry(tmp_path, monkeypatch):
    """serve(name, archive, manifest): data set `name` of the registry published by a local server (its
    archive-level sha256 None, as in the real registry), with an empty cache in tmp_path/cache and
    NEURALSURF_DATA unset. Returns the Server."""
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("NEURALSURF_DATA", raising=False)
    servers = []

    def serve(name, archive, manifest, sha256=None):
        server = Server({"/archive.bin": archive})
        servers.append(server)
        real = data.DATASETS[name]
        monkeypatch.setitem(data.DATASETS, name, data.Dataset(
            real.folder, f"{server.url}/archive.bin", sha256, real.prepare, real.terms, manifest, real.size))  # fmt: skip
        return server

    yield serve
    for server in servers:
        server.close()


def _left_in(cache: Path) -> list[str]:
    return sorted(p.relative_to(cache).as_posix() for p in cache.rglob("*")) if cache.exists() else []


@pytest.mark.parametrize("name", ["stanford_bunny", "7scenes_redkitchen"])
def test_fetch_downloads_unpacks_checks_the_manifest_and_then_reuses_it(tmp_path, registry, name):
    archive, manifest = _archive_and_manifest(name)
    server = registry(name, archive, manifest)
    assert data.locate(name) is None
    with pytest.warns(UserWarning, match=f"archive of {name} .* has no sha256 .* {len(manifest)} files of its manifest"):
        folder = data.fetch(name, progress=False)
    assert folder == tmp_path / "cache" / data.DATASETS[name].folder
    assert data.check_manifest(folder, manifest) == []
    if name == "stanford_bunny":
        assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()) == sorted(manifest)
    else:
        frames = sorted(p.name for p in (folder / "frames").iterdir())
        assert frames[:3] == ["frame-000000.color.png", "frame-000000.depth.png", "frame-000000.pose.txt"]
        assert len(frames) == 9 and frames[-1] == "frame-000020.pose.txt"  # frames 0, 10, 20
        assert (folder / "frames" / "frame-000010.depth.png").read_bytes() == b"\x89PNG depth 10"  # as it is
        assert np.allclose(np.loadtxt(folder / "frames" / "frame-000010.pose.txt"), _pose(10), rtol=0, atol=1e-15)
    server.files.clear()  # a second fetch must not need the server
    assert data.fetch(name, progress=False) == folder


@pytest.mark.parametrize("name", ["stanford_bunny", "7scenes_redkitchen"])
def test_a_tampered_file_is_an_error_naming_it_and_nothing_is_left_behind(tmp_path, registry, name):
    good, manifest = _archive_and_manifest(name)
    if name == "stanford_bunny":
        tampered, culprit = _bunny_tarball({**_bunny_files(), "data/bun000.ply": b"ply\nchanged\n"}), "data/bun000.ply"
    else:
        files = _redkitchen_files()
        files["seq-01/frame-000010.pose.txt"] = _upstream_pose_text(_pose(10) * 1.001).encode()
        tampered, culprit = _redkitchen_zip(files), "frames/frame-000010.pose.txt"
    server = registry(name, tampered, manifest)
    with pytest.warns(UserWarning), pytest.raises(DownloadError, match=(
            f"{name}: 1 of the {len(manifest)} files in its manifest do not match .*{culprit} has sha256 "
            f"[0-9a-f]{{64}}, expected {manifest[culprit]}.*archive were deleted.*data fetch {name}` again")):  # fmt: skip
        data.fetch(name, progress=False)
    assert _left_in(tmp_path / "cache") == ["downloads"]  # no folder, no staging folder, no archive
    server.files["/archive.bin"] = good  # the next fetch downloads again
    with pytest.warns(UserWarning):
        assert data.check_manifest(data.fetch(name, progress=False), manifest) == []


def test_a_file_missing_from_the_archive_is_named(tmp_path, registry):
    files = _bunny_files()
    del files["reconstruction/bun_zipper.ply"]
    registry("stanford_bunny", _bunny_tarball(files), {k: _sha(v) for k, v in _bunny_files().items()})
    with pytest.warns(UserWarning), pytest.raises(DownloadError, match="reconstruction/bun_zipper.ply is missing"):
        data.fetch("stanford_bunny", progress=False)
    assert _left_in(tmp_path / "cache") == ["downloads"]


def test_a_frame_without_its_depth_image_or_with_a_broken_pose_is_a_file_format_error(tmp_path, registry):
    files = _redkitchen_files()
    del files["seq-01/frame-000020.depth.png"]
    server = registry("7scenes_redkitchen", _redkitchen_zip(files), _redkitchen_manifest())
    with pytest.warns(UserWarning), pytest.raises(FileFormatError, match="no frame-000020.depth.png.*data fetch"):
        data.fetch("7scenes_redkitchen", progress=False)
    assert _left_in(tmp_path / "cache") == ["downloads"]
    files = _redkitchen_files()
    files["seq-01/frame-000010.pose.txt"] = b"<html>not a pose</html>"
    server.files["/archive.bin"] = _redkitchen_zip(files)
    with pytest.warns(UserWarning), pytest.raises(FileFormatError, match="frame-000010.pose.txt .* not a 4x4 matrix"):
        data.fetch("7scenes_redkitchen", progress=False)
    assert _left_in(tmp_path / "cache") == ["downloads"]


def test_an_interrupted_fetch_resumes_and_a_known_archive_sha256_is_checked(tmp_path, registry):
    archive, manifest = _archive_and_manifest("stanford_bunny")
    server = registry("stanford_bunny", archive, manifest, sha256=_sha(archive))
    server.cut = 100
    with pytest.raises(DownloadError, match="interrupted after 100 .*run again to resume"):
        data.fetch("stanford_bunny", progress=False)
    assert _left_in(tmp_path / "cache") == ["downloads", "downloads/archive.bin.part"]
    folder = data.fetch("stanford_bunny", progress=False)  # no warning: the archive's sha256 is known
    assert server.ranges == ["bytes=100-"] and data.check_manifest(folder, manifest) == []


def test_a_local_copy_under_neuralsurf_data_comes_first(tmp_path, monkeypatch):
    (tmp_path / "mine" / "stanford_bunny" / "data").mkdir(parents=True)
    monkeypatch.setenv("NEURALSURF_DATA", str(tmp_path / "mine"))
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
    monkeypatch.setitem(data.DATASETS, "stanford_bunny", data.Dataset(
        "stanford_bunny", "http://127.0.0.1:9/never", None, lambda a, f: None, "", {}))  # fmt: skip
    assert data.fetch("stanford_bunny") == tmp_path / "mine" / "stanford_bunny"
    with pytest.raises(ConfigError, match="unknown data set 'bunny'; choose one of stanford_bunny, 7scenes_redkitchen"):
        data.fetch("bunny")


def test_a_manifest_line_not_in_sha256sum_format_is_named(tmp_path):
    (tmp_path / "m.sha256").write_text(f"{'a' * 64}  data/bun.conf\n{'b' * 63}  data/README\n")
    with pytest.raises(FileFormatError, match="m.sha256' line 2 is not '<sha256>  <path>'"):
        data.read_manifest(tmp_path / "m.sha256")


# ----------------------------------------------------------------------------------------------
# python -m neuralsurf data


def test_data_main_fetches_from_the_server_and_prints_the_folder(tmp_path, registry, capsys):
    archive, manifest = _archive_and_manifest("7scenes_redkitchen")
    registry("7scenes_redkitchen", archive, manifest)
    with pytest.warns(UserWarning):
        assert data.main(["fetch", "--no-progress", "7scenes_redkitchen"]) == 0
    folder = tmp_path / "cache" / "7scenes_redkitchen_every10"
    assert capsys.readouterr().out == f"{folder}\n" and data.check_manifest(folder, manifest) == []
    assert data.main(["list"]) == 0
    out = capsys.readouterr().out
    assert f"where:    found in cache: {folder}" in out
    assert "where:    not present; get it with: python -m neuralsurf data fetch stanford_bunny" in out


def _neuralsurf(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "neuralsurf", *args], capture_output=True, text=True, cwd=REPO,
                          env=env, timeout=120, check=False)


@pytest.mark.subprocess
@pytest.mark.slow
def test_python_dash_m_neuralsurf_data_list_and_fetch(tmp_path):
    (tmp_path / "mine" / "stanford_bunny").mkdir(parents=True)
    (tmp_path / "cache" / "7scenes_redkitchen_every10").mkdir(parents=True)
    env = {**os.environ, "NEURALSURF_DATA": str(tmp_path / "mine"), "NEURALSURF_CACHE": str(tmp_path / "cache")}
    listed = _neuralsurf("data", "list", env=env)
    assert listed.returncode == 0, listed.stderr[-2000:]
    assert f"found in NEURALSURF_DATA: {tmp_path / 'mine' / 'stanford_bunny'}" in listed.stdout
    assert f"found in cache: {tmp_path / 'cache' / '7scenes_redkitchen_every10'}" in listed.stdout
    assert "non-commercial research use" in listed.stdout  # the terms
    fetched = _neuralsurf("data", "fetch", "stanford_bunny", "7scenes_redkitchen", env=env)
    assert fetched.returncode == 0, fetched.stderr[-2000:]
    assert fetched.stdout.splitlines() == [str(tmp_path / "mine" / "stanford_bunny"),
                                           str(tmp_path / "cache" / "7scenes_redkitchen_every10")]  # fmt: skip
    unknown = _neuralsurf("data", "fetch", "stanford_bunny", "bunny", env=env)
    assert unknown.returncode == 1 and unknown.stdout == ""  # nothing fetched before every name is checked
    assert "unknown data set 'bunny'; choose one of stanford_bunny" in unknown.stderr
    assert "Traceback" not in unknown.stderr


def test_data_help_names_both_commands(capsys):
    with pytest.raises(SystemExit) as done:
        data.main(["--help"])
    assert done.value.code == 0 and "{list,fetch,verify,manifest}" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        data.main(["fetch", "--help"])
    assert done.value.code == 0 and "sha256 manifest" in capsys.readouterr().out


# ----------------------------------------------------------------------------------------------
# TUM RGB-D: the archive as TUM publishes it, no checksum known; a manifest written from a trusted copy


TUM = "rgbd_dataset_freiburg1_desk"


def _tum_tarball(n: int = 3, drop: str | None = None) -> tuple[bytes, list[np.ndarray]]:
    """A TUM-layout sequence of `n` 640x480 views of test_rgbd's plane through the freiburg1 intrinsics, as
    <TUM>.tgz (without the member `drop`), and the poses."""
    from test_rgbd import plane_depth, random_pose

    from neuralsurf.io.rgbd import TUM_K

    fx, fy, cx, cy = TUM_K["freiburg1"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    files, poses, lists = {}, [], {"depth.txt": ["# depth maps"], "rgb.txt": ["# color images"],
                                   "groundtruth.txt": ["# timestamp tx ty tz qx qy qz qw"]}
    for i in range(n):
        stamp, pose = 1305031102.0 + i / 30, random_pose(30 + i)
        poses.append(pose)
        depth = io.BytesIO()
        Image.fromarray(np.round(plane_depth(pose, K, 480, 640) * 5000).astype(np.uint16)).save(depth, format="PNG")
        files[f"depth/{stamp:.6f}.png"] = depth.getvalue()
        colour = io.BytesIO()
        Image.fromarray(np.full((480, 640, 3), 40 * i, np.uint8)).save(colour, format="PNG")
        files[f"rgb/{stamp + 0.01:.6f}.png"] = colour.getvalue()
        lists["depth.txt"].append(f"{stamp:.6f} depth/{stamp:.6f}.png")
        lists["rgb.txt"].append(f"{stamp + 0.01:.6f} rgb/{stamp + 0.01:.6f}.png")
        quaternion = Rotation.from_matrix(pose[:3, :3]).as_quat()  # x y z w, as TUM writes it
        lists["groundtruth.txt"].append(f"{stamp + 0.004:.4f} " + " ".join(f"{v:.6f}" for v in (*pose[:3, 3], *quaternion)))
    files.update({name: ("\n".join(lines) + "\n").encode() for name, lines in lists.items()})
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, content in files.items():
            if name != drop:
                info = tarfile.TarInfo(f"{TUM}/{name}")
                info.size = len(content)
                tar.addfile(info, io.BytesIO(content))
    return buffer.getvalue(), poses


def test_tum_fetch_unpacks_the_sequence_readable_with_the_freiburg1_intrinsics(tmp_path, registry, capsys, monkeypatch):
    from test_rgbd import assert_on_plane

    from neuralsurf.io import read_rgbd_folder
    from neuralsurf.io.rgbd import TUM_K

    archive, poses = _tum_tarball()
    registry("tum_fr1_desk", archive, {})  # as in the registry: no checksum known
    with pytest.warns(UserWarning) as warned:
        folder = data.fetch("tum_fr1_desk", progress=False)
    said = " ".join(str(w.message) for w in warned)
    assert "has no sha256" in said and "has no manifest: its unpacked files are not verified" in said
    assert folder == tmp_path / "cache" / TUM and (folder / "groundtruth.txt").is_file()
    frames = read_rgbd_folder(folder, with_color=False)
    fx, fy, cx, cy = TUM_K["freiburg1"]  # from the folder's name
    assert np.allclose(frames.K[0].double().numpy(), [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], atol=1e-4)
    assert np.allclose(frames.cam_to_world.double().numpy(), np.stack(poses), atol=1e-5)
    assert_on_plane(frames, atol=3e-4)  # 1/5000 m steps
    # a trusted copy's manifest, then every file checked: a changed one is named
    assert data.main(["manifest", "tum_fr1_desk"]) == 0
    lines = capsys.readouterr().out.splitlines()
    (tmp_path / "tum.sha256").write_text("\n".join(lines) + "\n")
    manifest = data.read_manifest(tmp_path / "tum.sha256")
    assert len(manifest) == 9 and data.check_manifest(folder, manifest) == []
    (folder / "groundtruth.txt").write_text("# changed\n")
    real = data.DATASETS["tum_fr1_desk"]
    monkeypatch.setitem(data.DATASETS, "tum_fr1_desk", data.Dataset(real.folder, real.url, None, real.prepare, real.terms,
                                                                    manifest))
    assert data.main(["verify", "tum_fr1_desk"]) == 1
    assert "groundtruth.txt has sha256" in capsys.readouterr().out


def test_a_tum_archive_without_an_image_its_list_names_is_a_file_format_error(tmp_path, registry):
    archive, _ = _tum_tarball(drop="depth/1305031102.033333.png")
    registry("tum_fr1_desk", archive, {})
    with pytest.warns(UserWarning), pytest.raises(FileFormatError, match=(
            "depth.txt names 1 images the archive does not hold .*1305031102.033333.png.*data fetch tum_fr1_desk")):
        data.fetch("tum_fr1_desk", progress=False)
    assert _left_in(tmp_path / "cache") == ["downloads"]


def test_verify_and_manifest_name_the_fetch_command_of_an_absent_set(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("NEURALSURF_DATA", raising=False)
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path))
    assert data.main(["verify", "tum_fr1_desk"]) == 1
    assert "python -m neuralsurf data fetch tum_fr1_desk" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# scenes find fetched data without NEURALSURF_DATA


def test_data_root_is_the_fetch_cache_when_neuralsurf_data_is_unset(tmp_path, monkeypatch):
    monkeypatch.delenv("NEURALSURF_DATA", raising=False)
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
    assert recipes.data_root() == tmp_path / "cache" == data.cache_dir()
    assert recipes.data_root(tmp_path / "given") == tmp_path / "given"
    with pytest.raises(recipes.SceneUnavailable, match=(
            "stanford_bunny/data/bun.conf not found: run `python -m neuralsurf data fetch stanford_bunny`, pass "
            "data_root=<folder holding stanford_bunny/> or set NEURALSURF_DATA")):  # fmt: skip
        recipes.stanford_scans.__wrapped__()  # not the per-process cache of built scenes
    with pytest.raises(recipes.SceneUnavailable, match="data fetch 7scenes_redkitchen`"):
        recipes.redkitchen()
    (tmp_path / "cache" / "stanford_bunny").mkdir(parents=True)
    monkeypatch.setenv("NEURALSURF_DATA", str(tmp_path / "elsewhere"))  # without the set: the cache still has it
    assert recipes.data_path(None, "stanford_bunny") == tmp_path / "cache" / "stanford_bunny"


def test_the_tum_scene_holds_frames_out_and_names_its_fetch_command_when_absent(tmp_path, monkeypatch):
    from neuralsurf.scenes.recipes import rgbd_capture

    monkeypatch.delenv("NEURALSURF_DATA", raising=False)
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
    with pytest.raises(recipes.SceneUnavailable, match=f"{TUM} not found: run `python -m neuralsurf data fetch tum_fr1_desk`"):
        rgbd_capture("tum_fr1_desk", TUM)
    with tarfile.open(fileobj=io.BytesIO(_tum_tarball()[0])) as tar:
        tar.extractall(tmp_path / "mine")  # the test's own archive
    scene = rgbd_capture("tum_fr1_desk", TUM, root=str(tmp_path / "mine"), hold_out_every=3, cloud_stride=8)
    assert len(scene.frames) == 2 and len(scene.held_out) == 1 and scene.depth_input and scene.ground_truth is None


def test_sphere_normals_of_a_disc_and_least_squares_stereo_recovers_them():
    """The grey sphere's ground truth: a disc mask's sphere, facing the camera (z < 0); Lambertian images of it
    under lights in front (`render_lambertian`) give them back by least squares where every light reaches."""
    from neuralsurf.photometric import photometric_stereo, render_lambertian
    from neuralsurf.scenes.captures import sphere_normals
    from neuralsurf.structures import PhotometricCapture

    v, u = np.mgrid[0:90, 0:120]
    mask = torch.from_numpy((u - 60.0) ** 2 + (v - 44.0) ** 2 <= 35.0**2)
    normals = sphere_normals(mask)
    assert torch.allclose(normals[mask].norm(dim=-1), torch.ones(int(mask.sum())), atol=1e-5)
    assert torch.allclose(normals[44, 60], torch.tensor([0.0, 0.0, -1.0]), atol=1e-2)
    assert normals[44, 60 + 17, 0] == pytest.approx(17 / 35, abs=0.02) and (normals[mask][:, 2] <= 0).all()
    lights = torch.tensor([[0.3, -0.2, -1.0], [-0.4, 0.1, -1.0], [0.1, 0.4, -1.0], [0.0, 0.0, -1.0]])
    lights = lights / lights.norm(dim=-1, keepdim=True)
    images = render_lambertian(normals, torch.full(mask.shape, 0.7), lights)
    lit = mask & ((normals @ lights.T) > 0.05).all(-1)
    result = photometric_stereo(PhotometricCapture(images, lights, mask=mask, normals=normals), "least_squares")
    assert (result.normals[lit] * normals[lit]).sum(-1).min() > 0.9999


def test_the_uw_grey_sphere_names_where_it_looks_when_absent(tmp_path):
    from neuralsurf.scenes.captures import uw_gray_sphere

    with pytest.raises(recipes.SceneUnavailable, match="gray.txt not found: pass data_root=<folder holding uw_photometric/>"):
        uw_gray_sphere.__wrapped__(root=str(tmp_path))


def test_scenes_read_real_data_from_the_cache(tmp_path, monkeypatch, shared_data):
    folder = shared_data / "7scenes_redkitchen_every10"
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / folder.name).symlink_to(folder)
    monkeypatch.delenv("NEURALSURF_DATA", raising=False)
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
    scene = recipes.redkitchen(max_frames=2, hold_out_every=0)
    assert len(scene.frames.depth) == 2 and len(scene.cloud) > 1000


# ----------------------------------------------------------------------------------------------
# the real registry


def test_the_real_registry_has_https_urls_and_a_manifest_per_data_set():
    assert data.DATASETS["stanford_bunny"].url == "https://graphics.stanford.edu/pub/3Dscanrep/bunny.tar.gz"
    assert data.DATASETS["7scenes_redkitchen"].url.startswith("https://download.microsoft.com/")
    assert data.DATASETS["7scenes_redkitchen"].folder == "7scenes_redkitchen_every10"
    bunny, kitchen = data.DATASETS["stanford_bunny"].manifest, data.DATASETS["7scenes_redkitchen"].manifest
    assert len(bunny) == 17 and "data/bun.conf" in bunny and "reconstruction/bun_zipper.ply" in bunny
    assert len(kitchen) == 101 and sum(k.endswith(".pose.txt") for k in kitchen) == 100
    assert not any(k.endswith((".png", ".jpg")) for k in kitchen)  # image bytes are not known
    assert kitchen["camera-intrinsics.txt"] == _sha(K_TEXT)  # what the unpacker writes
    for dataset in data.DATASETS.values():
        assert dataset.sha256 is None or len(dataset.sha256) == 64


@pytest.mark.parametrize("name", ["stanford_bunny", "7scenes_redkitchen"])
def test_the_real_manifests_match_the_copies_under_neuralsurf_data(shared_data, name):
    folder = shared_data / data.DATASETS[name].folder
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    assert data.check_manifest(folder, data.DATASETS[name].manifest) == []


def test_the_redkitchen_poses_unpack_to_the_bytes_of_the_manifest(shared_data):
    """Each pose of the copy, written the way 7-Scenes writes it, unpacks to the bytes its manifest names."""
    folder = shared_data / "7scenes_redkitchen_every10" / "frames"
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    manifest = data.DATASETS["7scenes_redkitchen"].manifest
    for path in sorted(folder.glob("*.pose.txt")):
        upstream = _upstream_pose_text(np.loadtxt(path))
        assert _sha(data._pose_text(upstream, path.name).encode()) == manifest[f"frames/{path.name}"], path.name
