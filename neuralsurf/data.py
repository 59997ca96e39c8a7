"""Real data sets on request: the Stanford bunny scans and a 7-Scenes sample.

`fetch(name)` returns the folder of a data set, in the layout the tests and configs expect:

- ``stanford_bunny/``: ``data/`` (ten range scans ``bun*.ply``, ``chin.ply``, ``ear_back.ply``,
  ``top2.ply``, ``top3.ply`` and ``bun.conf``) and ``reconstruction/`` (``bun_zipper*.ply``), as in
  Stanford's archive (Stanford 3D Scanning Repository; free for research, credit the Stanford
  Computer Graphics Laboratory).
- ``7scenes_redkitchen_every10/``: ``frames/frame-XXXXXX.{color.png,depth.png,pose.txt}``, every
  10th frame of the first 1,000 of sequence 1 of Microsoft 7-Scenes' redkitchen (non-commercial
  research use), and ``camera-intrinsics.txt`` (the published fx = fy = 585, cx = 320, cy = 240).

Where it looks, in order:

1. ``$NEURALSURF_DATA/<folder>``: a local copy (e.g. a lab's shared disk); nothing is downloaded.
2. ``<cache>/<folder>``, the cache being ``$NEURALSURF_CACHE`` or ``~/.cache/neuralsurf``.
3. Otherwise the archive is downloaded into ``<cache>/downloads/`` (an HTTP Range request resumes
   an interrupted download), checked against its sha256 when the registry has one, and unpacked
   into ``<cache>/<folder>``. The archive is kept; delete ``<cache>/downloads`` to reclaim the space.

Checksums: the registry below carries ``sha256=None`` for both archives, because they could not be
downloaded where this module was written; such a download is not verified and says so in a
warning. Fill in the sha256 (``sha256sum`` of the archive) to have every later download checked.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import re
import shutil
import tarfile
import urllib.error
import urllib.request
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from neuralsurf.errors import ConfigError, DownloadError, FileFormatError

__all__ = ["DATASETS", "Dataset", "cache_dir", "download", "fetch", "locate"]

_CHUNK = 1 << 20
"""Bytes read from the network per step."""


@dataclass(frozen=True)
class Dataset:
    """One downloadable data set."""

    folder: str
    """Its folder under NEURALSURF_DATA or the cache (the layout in the module docstring)."""
    url: str
    """Where its archive is published."""
    sha256: str | None
    """Hex sha256 of the archive, or None when not known (the download is then not verified)."""
    prepare: Callable[[Path, Path], None]
    """(archive, empty folder) -> fills the folder with the data set's layout."""
    terms: str
    """Licence or terms of use, shown in the docs."""


def _unpack_bunny(archive: Path, folder: Path) -> None:
    """Stanford's bunny.tar.gz holds bunny/data/... and bunny/reconstruction/...: keep both, minus `bunny/`."""
    with tarfile.open(archive) as tar:
        members = []
        for member in tar.getmembers():
            parts = Path(member.name).parts
            if len(parts) > 1 and parts[1] in ("data", "reconstruction") and (member.isfile() or member.isdir()):
                member.name = str(Path(*parts[1:]))
                members.append(member)
        if not any(m.name.endswith("bun.conf") for m in members):
            raise FileFormatError(f"{str(archive)!r} holds no bunny/data/bun.conf; it is not Stanford's bunny archive")
        tar.extractall(folder, members=members, filter="data")


SEVEN_SCENES_K = "585 0 320\n0 585 240\n0 0 1\n"
"""The intrinsics 7-Scenes publishes for its depth camera (640 x 480)."""


def _unpack_redkitchen(archive: Path, folder: Path, sequence: str = "seq-01", step: int = 10, first: int = 1000) -> None:
    """From redkitchen.zip (one inner zip per sequence), frames 0, step, ... below `first` of `sequence`."""
    pattern = re.compile(r"frame-(\d{6})\.(color\.png|depth\.png|pose\.txt)$")
    with zipfile.ZipFile(archive) as outer:
        inner_name = next((n for n in outer.namelist() if n.endswith(f"{sequence}.zip")), None)
        if inner_name is None:
            raise FileFormatError(f"{str(archive)!r} holds no {sequence}.zip; it is not 7-Scenes' redkitchen.zip")
        (folder / "frames").mkdir(parents=True)
        with outer.open(inner_name) as stream, zipfile.ZipFile(stream) as inner:
            for name in inner.namelist():
                match = pattern.search(name)
                if match and int(match.group(1)) % step == 0 and int(match.group(1)) < first:
                    with inner.open(name) as source, open(folder / "frames" / Path(name).name, "wb") as target:
                        shutil.copyfileobj(source, target)
    (folder / "camera-intrinsics.txt").write_text(SEVEN_SCENES_K)


DATASETS: dict[str, Dataset] = {
    "stanford_bunny": Dataset(
        folder="stanford_bunny",
        url="http://graphics.stanford.edu/pub/3Dscanrep/bunny.tar.gz",
        sha256=None,  # not computed: no network where this was written (see the module docstring)
        prepare=_unpack_bunny,
        terms="Stanford 3D Scanning Repository: free for research; credit the Stanford Computer Graphics Laboratory",
    ),
    "7scenes_redkitchen": Dataset(
        folder="7scenes_redkitchen_every10",
        url="http://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8/redkitchen.zip",
        sha256=None,  # not computed: no network where this was written (see the module docstring)
        prepare=_unpack_redkitchen,
        terms="Microsoft 7-Scenes: non-commercial research use",
    ),
}
"""The data sets `fetch` knows, by name."""


def cache_dir() -> Path:
    """$NEURALSURF_CACHE, or ~/.cache/neuralsurf."""
    return Path(os.environ.get("NEURALSURF_CACHE") or Path.home() / ".cache" / "neuralsurf").expanduser()


def _dataset(name: str) -> Dataset:
    if name not in DATASETS:
        raise ConfigError(f"unknown data set {name!r}; choose one of {', '.join(DATASETS)}")
    return DATASETS[name]


def locate(name: str) -> Path | None:
    """The folder of data set `name` if a local copy (NEURALSURF_DATA) or the cache holds it, else None;
    never downloads."""
    dataset = _dataset(name)
    local = os.environ.get("NEURALSURF_DATA")
    for root in ([Path(local).expanduser()] if local else []) + [cache_dir()]:
        if (root / dataset.folder).is_dir():
            return root / dataset.folder
    return None


def fetch(name: str, progress: bool = True) -> Path:
    """The folder of data set `name` (see the module docstring): the local copy under NEURALSURF_DATA,
    else the cache, else downloaded, checked and unpacked into the cache first.

    Raises ConfigError for an unknown name, DownloadError when the download fails or its checksum
    does not match, FileFormatError when the archive does not hold the expected files.
    """
    found = locate(name)
    if found is not None:
        return found
    dataset = _dataset(name)
    if os.environ.get("NEURALSURF_DATA"):
        warnings.warn(
            f"NEURALSURF_DATA={os.environ['NEURALSURF_DATA']!r} has no {dataset.folder}/ folder; downloading "
            f"{name} into {str(cache_dir())!r} instead",
            stacklevel=2,
        )
    archive = download(dataset.url, cache_dir() / "downloads" / dataset.url.rsplit("/", 1)[-1], dataset.sha256, progress)
    target = cache_dir() / dataset.folder
    staging = target.with_name(f".{target.name}.unpacking")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        dataset.prepare(archive, staging)
    except (tarfile.TarError, zipfile.BadZipFile, EOFError) as error:
        shutil.rmtree(staging, ignore_errors=True)
        raise FileFormatError(
            f"cannot unpack {str(archive)!r} ({type(error).__name__}: {error}); delete it and run fetch({name!r}) again"
        ) from error
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    os.replace(staging, target)  # a folder appears only complete
    return target


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(_CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def download(url: str, path, sha256: str | None = None, progress: bool = True, timeout: float = 60.0) -> Path:
    """Download `url` to `path`, resuming an earlier interrupted attempt, and check its sha256.

    Bytes arrive in `path` + ".part"; a rerun after an interruption asks the server for the rest
    only (HTTP Range), or starts over when the server does not support ranges. The file gets its
    final name once complete and, when `sha256` is given, matching: on a mismatch nothing is left
    behind and DownloadError says so. With `sha256=None` the file is not verified (a warning says
    so). An existing `path` is returned as is (after the check, when `sha256` is given).

    Returns the Path of the complete file. Raises DownloadError naming the URL and what to do.
    """
    from neuralsurf.progress import progress_bar

    path = Path(path)
    if path.is_file():
        _verify(path, url, sha256)
        return path
    part = path.with_name(path.name + ".part")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DownloadError(f"cannot create {str(path.parent)!r} for {url}: {error}; set NEURALSURF_CACHE") from error
    have = part.stat().st_size if part.is_file() else 0
    request = urllib.request.Request(url, headers={"Range": f"bytes={have}-"} if have else {})
    try:
        response = urllib.request.urlopen(request, timeout=timeout)
    except urllib.error.HTTPError as error:
        if error.code == 416 and have:  # nothing left to send: the part file is already complete
            response = None
        else:
            raise DownloadError(f"downloading {url} failed: HTTP {error.code} {error.reason}") from error
    except (urllib.error.URLError, OSError) as error:
        raise DownloadError(
            f"downloading {url} failed: {getattr(error, 'reason', error)}; check the network, or download it by "
            f"hand and set NEURALSURF_DATA to the folder holding the unpacked data"
        ) from error
    if response is not None:
        with response:
            resumed = bool(have) and response.status == 206
            length = response.headers.get("Content-Length")
            total = (have if resumed else 0) + int(length) if length is not None else None
            received = have if resumed else 0
            bar = progress_bar(desc=path.name, total=total, unit="B", unit_scale=True, enabled=progress,
                               initial=received)
            try:
                with open(part, "ab" if resumed else "wb") as file:
                    while True:
                        try:
                            block = response.read(_CHUNK)
                        except http.client.IncompleteRead as error:  # the connection dropped mid-block
                            file.write(error.partial)
                            received += len(error.partial)
                            raise
                        if not block:
                            break
                        file.write(block)
                        received += len(block)
                        bar.update(len(block))
            except (OSError, http.client.HTTPException) as error:
                raise DownloadError(
                    f"downloading {url} was interrupted after {received} bytes ({type(error).__name__}); run again "
                    f"to resume (the bytes received are kept in {str(part)!r})"
                ) from error
            finally:
                bar.close()
            if total is not None and received < total:
                raise DownloadError(
                    f"downloading {url} was interrupted after {received} of {total} bytes; run again to resume "
                    f"(the {received} bytes are kept in {str(part)!r})"
                )
    _verify(part, url, sha256)
    os.replace(part, path)
    return path


def _verify(path: Path, url: str, sha256: str | None) -> None:
    """Check the sha256 of a downloaded file; on a mismatch delete it and raise DownloadError."""
    if sha256 is None:
        warnings.warn(
            f"the checksum of {url} is not verified: the registry has no sha256 for it; check "
            f"{str(path)!r} by hand or add its sha256 to neuralsurf.data.DATASETS",
            stacklevel=3,
        )
        return
    actual = _sha256(path)
    if actual != sha256.lower():
        path.unlink(missing_ok=True)
        raise DownloadError(
            f"the file downloaded from {url} has sha256 {actual}, expected {sha256.lower()}: it is corrupt or "
            f"changed upstream, and was deleted; run again, or check the URL and the checksum"
        )
