"""neuralsurf.data: local copies first, then downloads from a local HTTP server (never the network):
checksums, resuming with an HTTP Range request, unpacking into the layout the tests use."""

import hashlib
import http.server
import io
import tarfile
import threading
import zipfile

import pytest

from neuralsurf import data
from neuralsurf.errors import ConfigError, DownloadError

PAYLOAD = bytes(range(256)) * 4096  # 1 MiB
SHA = hashlib.sha256(PAYLOAD).hexdigest()


class Server:
    """A file server on 127.0.0.1 that honours Range requests and can drop the connection after `cut` bytes."""

    def __init__(self, files: dict[str, bytes]):
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
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
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


def _bunny_tarball() -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, text in [("bunny/data/bun.conf", b"bmesh bun000.ply 0 0 0 0 0 0 1\n"),
                           ("bunny/data/bun000.ply", b"ply\n"), ("bunny/reconstruction/bun_zipper.ply", b"ply\n"),
                           ("bunny/README", b"elsewhere")]:  # fmt: skip
            info = tarfile.TarInfo(name)
            info.size = len(text)
            tar.addfile(info, io.BytesIO(text))
    return buffer.getvalue()


def _redkitchen_zip() -> bytes:
    inner = io.BytesIO()
    with zipfile.ZipFile(inner, "w") as seq:
        for i in range(25):
            for suffix in ("color.png", "depth.png", "pose.txt"):
                seq.writestr(f"seq-01/frame-{i:06d}.{suffix}", f"{i} {suffix}")
    outer = io.BytesIO()
    with zipfile.ZipFile(outer, "w") as kitchen:
        kitchen.writestr("redkitchen/seq-01.zip", inner.getvalue())
        kitchen.writestr("redkitchen/seq-02.zip", b"not read")
    return outer.getvalue()


@pytest.mark.parametrize("name", ["stanford_bunny", "7scenes_redkitchen"])
def test_fetch_downloads_unpacks_into_the_cache_and_then_reuses_it(tmp_path, monkeypatch, name):
    archive = _bunny_tarball() if name == "stanford_bunny" else _redkitchen_zip()
    server = Server({"/archive": archive})
    try:
        dataset = data.DATASETS[name]
        monkeypatch.setitem(data.DATASETS, name, data.Dataset(
            dataset.folder, f"{server.url}/archive", hashlib.sha256(archive).hexdigest(), dataset.prepare, dataset.terms
        ))  # fmt: skip
        monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
        monkeypatch.delenv("NEURALSURF_DATA", raising=False)
        assert data.locate(name) is None
        folder = data.fetch(name, progress=False)
        assert folder == tmp_path / "cache" / dataset.folder
        if name == "stanford_bunny":
            assert sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*.*")) == [
                "data/bun.conf", "data/bun000.ply", "reconstruction/bun_zipper.ply"]  # fmt: skip
        else:
            frames = sorted(p.name for p in (folder / "frames").iterdir())
            assert frames[:3] == ["frame-000000.color.png", "frame-000000.depth.png", "frame-000000.pose.txt"]
            assert len(frames) == 9 and frames[-1] == "frame-000020.pose.txt"  # frames 0, 10, 20
            assert (folder / "camera-intrinsics.txt").read_text().split()[0] == "585"
        server.files.clear()  # a second fetch must not need the server
        assert data.fetch(name, progress=False) == folder
    finally:
        server.close()


def test_a_local_copy_under_neuralsurf_data_comes_first(tmp_path, monkeypatch):
    (tmp_path / "mine" / "stanford_bunny" / "data").mkdir(parents=True)
    monkeypatch.setenv("NEURALSURF_DATA", str(tmp_path / "mine"))
    monkeypatch.setenv("NEURALSURF_CACHE", str(tmp_path / "cache"))
    monkeypatch.setitem(data.DATASETS, "stanford_bunny", data.Dataset(
        "stanford_bunny", "http://127.0.0.1:9/never", None, lambda a, f: None, ""))  # fmt: skip
    assert data.fetch("stanford_bunny") == tmp_path / "mine" / "stanford_bunny"
    with pytest.raises(ConfigError, match="unknown data set 'bunny'; choose one of stanford_bunny, 7scenes_redkitchen"):
        data.fetch("bunny")


def test_the_real_registry_names_its_urls_and_the_shared_layout():
    assert data.DATASETS["stanford_bunny"].url == "http://graphics.stanford.edu/pub/3Dscanrep/bunny.tar.gz"
    assert data.DATASETS["7scenes_redkitchen"].folder == "7scenes_redkitchen_every10"
    for dataset in data.DATASETS.values():  # None until computed from the real archive (module docstring)
        assert dataset.sha256 is None or len(dataset.sha256) == 64
