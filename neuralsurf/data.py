"""Real data sets on request: the Stanford bunny scans and a 7-Scenes sample.

`fetch(name)` returns the folder of a data set, in the layout the tests and configs expect:

- ``stanford_bunny/``: ``data/`` (ten range scans ``bun*.ply``, ``chin.ply``, ``ear_back.ply``,
  ``top2.ply``, ``top3.ply``, ``bun.conf`` and ``README``) and ``reconstruction/``
  (``bun_zipper*.ply`` and ``README``), as in Stanford's archive (Stanford 3D Scanning Repository;
  free for research, credit the Stanford Computer Graphics Laboratory).
- ``7scenes_redkitchen_every10/``: ``frames/frame-XXXXXX.{color.png,depth.png,pose.txt}``, every
  10th frame of the first 1,000 of sequence 1 of Microsoft 7-Scenes' redkitchen (non-commercial
  research use), and ``camera-intrinsics.txt`` (the published fx = fy = 585, cx = 320, cy = 240).
  The images are copied from the archive byte for byte; each pose and the intrinsics are written as
  4 x 4 (3 x 3) float64 values in ``%.18e`` notation, one row per line (what ``numpy.savetxt``
  writes), so that their bytes depend on the values only.
- ``rgbd_dataset_freiburg1_desk/``: TUM RGB-D's fr1/desk sequence as its archive holds it (``rgb/``,
  ``depth/``, ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``, ``accelerometer.txt``; the TUM layout of
  `neuralsurf.io.read_rgbd_folder`, whose intrinsics follow the ``freiburg1`` in the folder's name).

Where it looks, in order:

1. ``$NEURALSURF_DATA/<folder>``: a local copy (e.g. a lab's shared disk); nothing is downloaded.
2. ``<cache>/<folder>``, the cache being ``$NEURALSURF_CACHE`` or ``~/.cache/neuralsurf``.
3. Otherwise the archive is downloaded into ``<cache>/downloads/`` (an HTTP Range request resumes
   an interrupted download), checked against its sha256 when the registry has one, unpacked, and
   the unpacked files are checked against the data set's manifest before the folder appears as
   ``<cache>/<folder>``. The archive is kept; delete ``<cache>/downloads`` to reclaim the space.

Scenes (`neuralsurf.scenes.recipes.data_path`) look in the same two places, so a fetched set needs
no environment variable. A local copy may hold ``color.jpg`` images instead (neuralsurf.io reads both). From the shell: ``python -m neuralsurf data list``,
``python -m neuralsurf data fetch <name> [<name> ...]``, ``data verify <name> ...`` (a copy found against
its manifest) and ``data manifest <name>`` (the sha256 lines of a copy found).

Checksums. Each data set has a manifest, ``neuralsurf/data_manifests/<name>.sha256`` in
``sha256sum`` format (``cd <folder> && sha256sum -c <manifest>`` checks a copy by hand): the sha256
of the files it unpacks to, by path relative to its folder. A missing or different file is a
DownloadError naming it, and neither the unpacked files nor the archive are kept. The manifests hold
the files whose bytes are known:

- stanford_bunny: all 17 files (a file of the archive it does not list is dropped, with a warning).
- 7scenes_redkitchen: ``camera-intrinsics.txt`` and the 100 ``pose.txt`` (their bytes follow from
  their values, see above). The colour and depth images are not in it: their bytes in Microsoft's
  archive are not known to this registry. The unpacker checks that every frame has its three files.
- tum_fr1_desk: none (no file of TUM's archive has a sha256 known to this registry): a fetch warns that
  nothing is verified, and the unpacker checks the layout (the three lists and the images they name).
  Whoever has a trusted copy writes its manifest with ``python -m neuralsurf data manifest
  tum_fr1_desk > neuralsurf/data_manifests/tum_fr1_desk.sha256``; every later fetch is then checked.

A manifest file that does not exist is an empty manifest.

The registry carries ``sha256=None`` for every archive (the archive-level sha256 is unknown), and a
fetch says so in a warning; the manifest check is what verifies a download. Fill in the sha256
(``sha256sum`` of the archive) to have every later download checked before it is unpacked.
"""

from __future__ import annotations

import argparse
import hashlib
import http.client
import os
import re
import shutil
import sys
import tarfile
import urllib.error
import urllib.request
import warnings
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from neuralsurf.errors import ConfigError, DownloadError, FileFormatError, NeuralsurfError
from neuralsurf.io.rgbd import SEVEN_SCENES_K
from neuralsurf.progress import progress_bar

__all__ = ["DATASETS", "Dataset", "cache_dir", "check_manifest", "download", "fetch", "locate", "main",
           "manifest_lines", "read_manifest"]

_CHUNK = 1 << 20
"""Bytes read from the network per step."""

MANIFESTS = Path(__file__).parent / "data_manifests"
"""The folder of the registry's manifests (package data): ``<name>.sha256``."""


@dataclass(frozen=True)
class Dataset:
    """One downloadable data set."""

    folder: str
    """Its folder under NEURALSURF_DATA or the cache (the layout in the module docstring)."""
    url: str
    """Where its archive is published."""
    sha256: str | None
    """Hex sha256 of the archive, or None when not known (the archive is then not verified)."""
    prepare: Callable[[Path, Path], None]
    """(archive, empty folder) -> fills the folder with the data set's layout."""
    terms: str
    """Licence or terms of use, shown by ``data list`` and in the docs."""
    manifest: Mapping[str, str]
    """Hex sha256 of unpacked files, by path relative to `folder` (posix): checked after every unpack."""
    size: str = ""
    """What a fetch downloads and keeps, in words (``data list``)."""
    complete: bool = False
    """The manifest lists every file of the data set: an unpacked file it does not list is dropped."""


def read_manifest(path: str | Path) -> dict[str, str]:
    """A ``sha256sum``-format file (``<64 hex>  <relative path>`` per line) as {relative path: hex}.

    Raises FileFormatError naming the file and line when a line is not in that format."""
    path = Path(path)
    manifest = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        match = re.fullmatch(r"([0-9a-fA-F]{64}) [ *](\S.*)", line)
        if match is None:
            raise FileFormatError(f"{str(path)!r} line {number} is not '<sha256>  <path>' (sha256sum "
                                  f"format): {line[:80]!r}")
        manifest[match.group(2)] = match.group(1).lower()
    return manifest


def _unpack_bunny(archive: Path, folder: Path) -> None:
    """Stanford's bunny.tar.gz holds bunny/data/... and bunny/reconstruction/...: keep both, minus `bunny/`."""
    with tarfile.open(archive) as tar:
        members = []
        for member in tar.getmembers():
            parts = Path(member.name).parts
            if len(parts) > 1 and parts[1] in ("data", "reconstruction") and (member.isfile() or member.isdir()):
                if ".." in parts or Path(member.name).is_absolute():
                    raise FileFormatError(f"{str(archive)!r} holds {member.name!r}, outside its folder; it is not "
                                          f"Stanford's bunny archive")
                member.name = str(Path(*parts[1:]))
                members.append(member)
        if not any(m.name.endswith("bun.conf") for m in members):
            raise FileFormatError(f"{str(archive)!r} holds no bunny/data/bun.conf; it is not Stanford's bunny archive")
        _extract(tar, folder, members)


def _extract(tar: tarfile.TarFile, folder: Path, members: list[tarfile.TarInfo]) -> None:
    """Extract `members` (regular files and folders inside `folder`, checked by the caller) with tarfile's
    "data" filter; where Python lacks it (before 3.11.4), the same done here: special and group/other
    write permission bits dropped, owned by the current user."""
    if hasattr(tarfile, "data_filter"):
        tar.extractall(folder, members=members, filter="data")
        return
    for member in members:
        member.mode = (member.mode & 0o755) | (0o700 if member.isdir() else 0o600)
        member.uid, member.gid = getattr(os, "getuid", int)(), getattr(os, "getgid", int)()
        member.uname = member.gname = ""
    tar.extractall(folder, members=members, numeric_owner=True)


TUM_LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt")
"""The lists every TUM RGB-D sequence folder holds."""


def _unpack_tum(archive: Path, folder: Path, sequence: str = "rgbd_dataset_freiburg1_desk") -> None:
    """TUM's <sequence>.tgz holds <sequence>/{rgb,depth}/*.png and <sequence>/*.txt: keep them, minus
    `<sequence>/`. Raises FileFormatError when a member lies outside that folder, a list is missing, or
    an image a list names is not in the archive."""
    with tarfile.open(archive) as tar:
        members = []
        for member in tar.getmembers():
            parts = Path(member.name).parts
            if ".." in parts or Path(member.name).is_absolute():
                raise FileFormatError(f"{str(archive)!r} holds {member.name!r}, outside its folder; it is not TUM's "
                                      f"{sequence}.tgz")
            if len(parts) > 1 and parts[0] == sequence and (member.isfile() or member.isdir()):
                member.name = str(Path(*parts[1:]))
                members.append(member)
        names = {m.name for m in members if m.isfile()}
        lacking = [name for name in TUM_LISTS if name not in names]
        if lacking:
            raise FileFormatError(f"{str(archive)!r} holds no {sequence}/{lacking[0]}; it is not TUM's {sequence}.tgz")
        for listed in ("rgb.txt", "depth.txt"):
            text = tar.extractfile(next(m for m in members if m.name == listed)).read().decode("ascii", "replace")
            missing = [words[1] for words in (line.split() for line in text.splitlines())
                       if len(words) == 2 and not words[0].startswith("#") and words[1] not in names]
            if missing:
                raise FileFormatError(f"{str(archive)!r}: {listed} names {len(missing)} images the archive does not "
                                      f"hold (first {missing[0]!r}); the archive is incomplete")
        _extract(tar, folder, members)


def _manifest(name: str) -> dict[str, str]:
    """The manifest of data set `name` (`read_manifest` of data_manifests/<name>.sha256); {} when there is
    no such file (no checksum of its files is known)."""
    path = MANIFESTS / f"{name}.sha256"
    return read_manifest(path) if path.is_file() else {}


def _matrix_text(values: Sequence[float], columns: int) -> str:
    """`values` (rows * columns floats, row-major) as text: one row per line, ``%.18e``, space-separated."""
    rows = [values[i : i + columns] for i in range(0, len(values), columns)]
    return "".join(" ".join(f"{value:.18e}" for value in row) + "\n" for row in rows)


def _pose_text(text: str, where: str) -> str:
    """A 7-Scenes pose file (16 numbers, any spacing) rewritten by `_matrix_text` (4 x 4).

    Raises FileFormatError naming `where` when it does not hold 16 numbers."""
    try:
        values = [float(token) for token in text.split()]
    except ValueError:
        values = []
    if len(values) != 16:
        raise FileFormatError(f"{where} is not a 4x4 matrix of numbers; the archive is not 7-Scenes' "
                              f"redkitchen.zip")
    return _matrix_text(values, 4)


_FRAME = re.compile(r"frame-(\d{6})\.(color\.png|depth\.png|pose\.txt)$")
"""A 7-Scenes frame file: index and kind."""


def _unpack_redkitchen(archive: Path, folder: Path, sequence: str = "seq-01", step: int = 10, first: int = 1000) -> None:
    """From redkitchen.zip (one inner zip per sequence), frames 0, step, ... below `first` of `sequence`:
    images copied as they are, poses rewritten by `_pose_text`, plus camera-intrinsics.txt.

    Raises FileFormatError when the sequence is missing, a pose is not a matrix or a frame lacks one of
    its three files."""
    with zipfile.ZipFile(archive) as outer:
        inner_name = next((n for n in outer.namelist() if n.endswith(f"{sequence}.zip")), None)
        if inner_name is None:
            raise FileFormatError(f"{str(archive)!r} holds no {sequence}.zip; it is not 7-Scenes' redkitchen.zip")
        (folder / "frames").mkdir(parents=True)
        kinds: dict[int, set[str]] = {}
        with outer.open(inner_name) as stream, zipfile.ZipFile(stream) as inner:
            for name in inner.namelist():
                match = _FRAME.search(name)
                if not match or int(match.group(1)) % step or int(match.group(1)) >= first:
                    continue
                kinds.setdefault(int(match.group(1)), set()).add(match.group(2))
                target = folder / "frames" / Path(name).name
                if match.group(2) == "pose.txt":
                    text = inner.read(name).decode("ascii", errors="replace")
                    target.write_text(_pose_text(text, f"{name} in {inner_name}"))
                else:
                    with inner.open(name) as source, open(target, "wb") as file:
                        shutil.copyfileobj(source, file)
    _check_frames(kinds, f"{inner_name} in {str(archive)!r}")
    (folder / "camera-intrinsics.txt").write_text(_matrix_text([v for row in SEVEN_SCENES_K for v in row], 3))


def _check_frames(kinds: Mapping[int, set[str]], where: str) -> None:
    """Every frame index in `kinds` has its colour, depth and pose file; raises FileFormatError otherwise."""
    if not kinds:
        raise FileFormatError(f"{where} holds no frame-XXXXXX.* files; it is not a 7-Scenes sequence")
    for index, have in sorted(kinds.items()):
        lacking = sorted({"color.png", "depth.png", "pose.txt"} - have)
        if lacking:
            raise FileFormatError(f"{where} has no frame-{index:06d}.{lacking[0]}; the archive is incomplete")


DATASETS: dict[str, Dataset] = {
    "stanford_bunny": Dataset(
        folder="stanford_bunny",
        url="https://graphics.stanford.edu/pub/3Dscanrep/bunny.tar.gz",
        sha256=None,  # the archive's sha256 is not known; the manifest checks what it unpacks to
        prepare=_unpack_bunny,
        terms="Stanford 3D Scanning Repository: free for research; credit the Stanford Computer Graphics Laboratory",
        manifest=_manifest("stanford_bunny"),
        size="bunny.tar.gz (a few MB); unpacked about 22 MB",
        complete=True,
    ),
    "7scenes_redkitchen": Dataset(
        folder="7scenes_redkitchen_every10",
        url="https://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8/redkitchen.zip",
        sha256=None,  # the archive's sha256 is not known; the manifest checks what it unpacks to
        prepare=_unpack_redkitchen,
        terms="Microsoft 7-Scenes: non-commercial research use",
        manifest=_manifest("7scenes_redkitchen"),
        size="redkitchen.zip (several GB: all seven sequences, kept in <cache>/downloads); 100 frames unpacked",
    ),
    "tum_fr1_desk": Dataset(
        folder="rgbd_dataset_freiburg1_desk",
        url="https://cvg.cit.tum.de/rgbd/dataset/freiburg1/rgbd_dataset_freiburg1_desk.tgz",
        sha256=None,  # neither the archive's sha256 nor its files' are known (see the module docstring)
        prepare=_unpack_tum,
        terms="TUM RGB-D benchmark (Sturm et al., IROS 2012): CC BY 4.0",
        manifest=_manifest("tum_fr1_desk"),
        size="rgbd_dataset_freiburg1_desk.tgz (a few hundred MB, kept in <cache>/downloads), unpacked as it is",
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


def _roots() -> list[tuple[str, Path]]:
    """Where data sets are looked for, in order: [(label, root)]: ("NEURALSURF_DATA", its folder) when
    set, then ("cache", cache_dir())."""
    local = os.environ.get("NEURALSURF_DATA")
    return ([("NEURALSURF_DATA", Path(local).expanduser())] if local else []) + [("cache", cache_dir())]


def find_folder(folder: str | Path) -> tuple[str, Path] | None:
    """(where, path) of the first of $NEURALSURF_DATA/`folder`, <cache>/`folder` that exists, where being
    "NEURALSURF_DATA" or "cache"; None when neither does. Never downloads."""
    for where, root in _roots():
        if (root / folder).exists():
            return where, root / folder
    return None


def locate(name: str) -> Path | None:
    """The folder of data set `name` if a local copy (NEURALSURF_DATA) or the cache holds it, else None;
    never downloads. Raises ConfigError for an unknown name."""
    found = find_folder(_dataset(name).folder)
    return found[1] if found is not None and found[1].is_dir() else None


def fetch(name: str, progress: bool = True) -> Path:
    """The folder of data set `name` (see the module docstring): the local copy under NEURALSURF_DATA,
    else the cache, else downloaded, unpacked and checked against its manifest into the cache first.

    Raises ConfigError for an unknown name, DownloadError when the download fails or a checksum
    (archive or manifest) does not match, FileFormatError when the archive does not hold the expected files.
    """
    found = locate(name)
    if found is not None:
        return found
    dataset = _dataset(name)
    if os.environ.get("NEURALSURF_DATA"):
        warnings.warn(
            f"NEURALSURF_DATA={os.environ['NEURALSURF_DATA']!r} has no {dataset.folder}/ folder; downloading "
            f"{name} into {str(cache_dir())!r} instead (scenes look there too)",
            stacklevel=2,
        )
    if dataset.sha256 is None:
        warnings.warn(
            f"the archive of {name} ({dataset.url}) has no sha256 in the registry and is not verified; the "
            f"{len(dataset.manifest)} files of its manifest are checked once it is unpacked",
            stacklevel=2,
        )
    target = cache_dir() / dataset.folder
    if target.exists() and not target.is_dir():  # before the download: the folder could not take its place
        raise FileFormatError(f"{str(target)!r} is a file where the folder of data set {name} goes; move it away "
                              f"and run `python -m neuralsurf data fetch {name}` again")
    archive = download(dataset.url, cache_dir() / "downloads" / dataset.url.rsplit("/", 1)[-1], dataset.sha256,
                       progress, warn_unverified=False)
    staging = target.with_name(f".{target.name}.unpacking")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        _unpack_checked(name, dataset, archive, staging)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    os.replace(staging, target)  # a folder appears only complete and checked
    return target


def _unpack_checked(name: str, dataset: Dataset, archive: Path, folder: Path) -> None:
    """Unpack `archive` into the empty `folder` and check it against the manifest of data set `name`.

    On failure deletes the archive (the next fetch downloads it again) and raises FileFormatError
    (not unpackable, not the expected layout) or DownloadError (files missing or different)."""
    rerun = f"run `python -m neuralsurf data fetch {name}` again"
    try:
        dataset.prepare(archive, folder)
    except (tarfile.TarError, zipfile.BadZipFile, EOFError) as error:
        archive.unlink(missing_ok=True)
        raise FileFormatError(f"cannot unpack {str(archive)!r} ({type(error).__name__}: {error}); the "
                              f"archive was deleted: {rerun}") from error
    except FileFormatError as error:
        archive.unlink(missing_ok=True)
        raise FileFormatError(f"{error}; the archive was deleted: {rerun}") from error
    if dataset.complete and dataset.manifest:
        _drop_unlisted(name, folder, dataset.manifest)
    problems = check_manifest(folder, dataset.manifest)
    if problems:
        archive.unlink(missing_ok=True)
        shown = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        raise DownloadError(
            f"{name}: {len(problems)} of the {len(dataset.manifest)} files in its manifest do not match what "
            f"{dataset.url} unpacks to: {shown}. The archive is damaged or changed upstream; the unpacked "
            f"files and the archive were deleted: {rerun}, and if it fails the same way, the data changed "
            f"upstream (report it)"
        )
    if not dataset.manifest:
        warnings.warn(f"data set {name} has no manifest: its unpacked files are not verified", stacklevel=3)


def _drop_unlisted(name: str, folder: Path, manifest: Mapping[str, str]) -> None:
    """Remove the files (and links) under `folder` that `manifest` does not list, with a warning naming them."""
    unlisted = sorted(p for p in folder.rglob("*") if not p.is_dir() and p.relative_to(folder).as_posix() not in manifest)
    for path in unlisted:
        path.unlink()
    if unlisted:
        shown = ", ".join(p.relative_to(folder).as_posix() for p in unlisted[:5])
        warnings.warn(f"{name}: {len(unlisted)} files of the archive are not in its manifest and were dropped ({shown})",
                      stacklevel=4)


def check_manifest(folder: str | Path, manifest: Mapping[str, str]) -> list[str]:
    """What in `folder` differs from `manifest` ({relative path: hex sha256}): one line per file that is
    missing or has another sha256, naming it; [] when every listed file matches. Files the manifest does
    not list are not looked at."""
    folder = Path(folder)
    problems = []
    for relative, expected in sorted(manifest.items()):
        path = folder / relative
        if not path.is_file():
            problems.append(f"{relative} is missing")
        elif (actual := _sha256(path)) != expected.lower():
            problems.append(f"{relative} has sha256 {actual}, expected {expected.lower()}")
    return problems


def _sha256(path: Path) -> str:
    """Hex sha256 of the file at `path`."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(_CHUNK), b""):
            digest.update(block)
    return digest.hexdigest()


def download(url: str, path, sha256: str | None = None, progress: bool = True, timeout: float = 60.0,
             warn_unverified: bool = True) -> Path:
    """Download `url` to `path`, resuming an earlier interrupted attempt, and check its sha256.

    Bytes arrive in `path` + ".part"; a rerun after an interruption asks the server for the rest
    only (HTTP Range), or starts over when the server does not support ranges. The file gets its
    final name once complete and, when `sha256` is given, matching: on a mismatch nothing is left
    behind and DownloadError says so. With `sha256=None` the file is not verified (a warning says
    so, unless `warn_unverified` is False: the caller checks it otherwise). An existing `path` is
    returned as is (after the check, when `sha256` is given).

    Returns the Path of the complete file. Raises DownloadError naming the URL and what to do.
    """
    path = Path(path)
    if path.is_file():
        _verify(path, url, sha256, warn_unverified)
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
    _verify(part, url, sha256, warn_unverified)
    os.replace(part, path)
    return path


def _verify(path: Path, url: str, sha256: str | None, warn_unverified: bool = True) -> None:
    """Check the sha256 of a downloaded file; on a mismatch delete it and raise DownloadError."""
    if sha256 is None:
        if not warn_unverified:
            return
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


def _folder_size(folder: Path) -> int:
    """Bytes of the files under `folder`."""
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())


def _describe(name: str) -> str:
    """Lines of ``data list`` for data set `name`: name, folder, where it is found, size and terms."""
    dataset = DATASETS[name]
    found = find_folder(dataset.folder)
    if found is not None and found[1].is_dir():
        where = f"found in {found[0]}: {found[1]} ({_folder_size(found[1]) / 1e6:.1f} MB)"
    else:
        where = f"not present; get it with: python -m neuralsurf data fetch {name}"
    return (f"{name}\n  folder:   {dataset.folder}/\n  where:    {where}\n  download: {dataset.size}\n"
            f"  terms:    {dataset.terms}")


def _parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m neuralsurf data``."""
    roots = ("$NEURALSURF_DATA/<folder> (a local copy), else the cache ($NEURALSURF_CACHE or "
             "~/.cache/neuralsurf)")
    parser = argparse.ArgumentParser(
        prog="python -m neuralsurf data",
        description=f"Real data sets: list them, fetch them into the cache, verify a copy against its manifest or "
                    f"print a copy's checksums. A data set is looked for in {roots}; scenes (stanford_scans, "
                    f"redkitchen, tum_fr1_desk) find it there without any setting.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="{list,fetch,verify,manifest}")
    commands.add_parser("list", help="each data set: its folder, where it is found now, download size, terms",
                        description="Each data set: its folder, where it is found now (NEURALSURF_DATA, "
                                    "cache, or not present), what a fetch downloads, and its terms of use.")
    fetch_parser = commands.add_parser(
        "fetch", help="download, unpack and check data sets into the cache (nothing when already present)",
        description=f"Find each data set in {roots}; when absent, download it, unpack it into the cache and "
                    "check it against its sha256 manifest. Prints each data set's folder, one per line.")
    fetch_parser.add_argument("names", nargs="+", metavar="name", help=f"one of: {', '.join(DATASETS)}")
    fetch_parser.add_argument("--no-progress", action="store_true", help="no download progress bar")
    verify_parser = commands.add_parser(
        "verify", help="check the copy found of each data set against its manifest (nothing is downloaded)",
        description="Check the copy of each data set found (NEURALSURF_DATA or the cache) against its sha256 "
                    "manifest; exit status 1 naming each missing or different file.")
    verify_parser.add_argument("names", nargs="+", metavar="name", help=f"one of: {', '.join(DATASETS)}")
    manifest_parser = commands.add_parser(
        "manifest", help="print the sha256 of every file of the copy found (sha256sum format)",
        description="Print '<sha256>  <path>' for every file of the copy of a data set found, for its "
                    "manifest (neuralsurf/data_manifests/<name>.sha256) when that copy is trusted.")
    manifest_parser.add_argument("name", help=f"one of: {', '.join(DATASETS)}")
    return parser


def _present(name: str) -> Path:
    """The folder of data set `name` found here (`locate`); DownloadError naming the fetch command if none."""
    folder = locate(name)
    if folder is None:
        raise DownloadError(f"{name} is not present (neither NEURALSURF_DATA nor the cache holds "
                            f"{_dataset(name).folder}/); get it with: python -m neuralsurf data fetch {name}")
    return folder


def manifest_lines(folder: str | Path) -> list[str]:
    """``sha256sum`` lines (``<hex>  <relative posix path>``) of every file under `folder`, sorted by path."""
    folder = Path(folder)
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return [f"{_sha256(path)}  {path.relative_to(folder).as_posix()}" for path in files]


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m neuralsurf data {list,fetch,verify,manifest}``: returns the exit status (0 on success, 1
    when a data set is unknown, cannot be fetched, is absent or differs from its manifest: the message goes to
    stderr, without a traceback)."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "list":
            print(f"cache: {cache_dir()}")
            print(f"NEURALSURF_DATA: {os.environ.get('NEURALSURF_DATA') or '(not set)'}")
            for name in DATASETS:
                print(_describe(name))
            return 0
        if args.command == "manifest":
            print("\n".join(manifest_lines(_present(args.name))))
            return 0
        for name in args.names:
            _dataset(name)  # every name checked before anything is downloaded
        if args.command == "verify":
            failed = False
            for name in args.names:
                folder, manifest = _present(name), _dataset(name).manifest
                problems = check_manifest(folder, manifest)
                failed |= bool(problems)
                print(f"{name}: {folder}: " + ("; ".join(problems) if problems else
                      f"the {len(manifest)} files of its manifest match" if manifest else
                      "no manifest: nothing to check against"), flush=True)
            return int(failed)
        for name in args.names:
            print(fetch(name, progress=not args.no_progress), flush=True)
        return 0
    except NeuralsurfError as error:
        print(f"neuralsurf data {args.command}: {error}", file=sys.stderr)
        return 1
